"""Write an :class:`~tembayes.export.observer.ObserverExport` as JSON, NPZ or MAT.

One schema (:data:`~tembayes.export.observer.SCHEMA`), three encodings.
``json`` and ``mat`` nest; ``npz`` cannot, so its keys are the nested paths
joined by ``__``.  SI throughout (temperatures in K; a deviation in K is one
in degC).  Keys:

- ``schema``, ``parameters`` (names, the order of every vector and matrix
  over parameters), ``units``, ``states`` (node names), ``inputs``
  (``current_A``, ``t_water_K``, ``t_amb_K``), ``outputs`` (``T1_K`` ..
  ``T4_K``, ``voltage_V``), ``meta`` (run, batch, seed, points);
- ``modules`` -> module id (and ``population``, a new unit of the batch) ->

  - ``mean`` ``(p,)``, ``cov`` ``(p, p)``, ``draws`` ``(n, p)``: posterior;
  - ``measurement_noise_cov`` ``(5, 5)``: white sensor noise over the outputs;
  - ``process_noise``: ``sd`` ``(5,)``, ``tau_s`` ``(5,)``, ``q_continuous``
    ``(5,)`` (``2 sd^2 / tau``), ``source``, ``channels``: one Ornstein-Uhlenbeck
    disturbance per output; with held-out runs also ``corr`` ``(5, 5)``
    (the disturbances' correlation across the outputs: a filter that
    measures T1, T2 learns T3's disturbance through it) and
    ``sd_by_time_since_step`` ``(5, b)`` over the bins whose lower edges are
    ``step_bins_s`` (the discrepancy is larger in the transients after a
    current step: schedule the disturbance's sd on the time since the step),
    ``corr_by_time_since_step`` ``(b, 5, 5)`` and ``n_by_time_since_step``
    ``(b,)`` (samples behind each bin: its sampling error);
  - ``input_noise``: ``current_sd_A``, ``sample_interval_s`` and
    ``step_instant`` (a step at an unknown instant within its sampling
    interval: current variance ``dI^2/12`` over that interval);
  - ``linear`` -> ``op0``, ``op1``, ... -> ``tavg_C``, ``current_A``,
    ``x0`` ``(n,)``, ``u0`` ``(3,)``, ``y0`` ``(5,)``, ``A`` ``(n, n)``,
    ``B`` ``(n, 3)``, ``C`` ``(5, n)``, ``D`` ``(5, 3)`` and
    ``sensitivity`` -> parameter -> ``A``, ``B``, ``C``, ``D``, ``x0``,
    ``u0``, ``y0`` (derivatives per unit of the parameter; ``x0``, ``u0``,
    ``y0`` with the operating point's T̄ and I held, the water temperature
    solved again).

In ``npz``: ``modules__TEM1__linear__op0__A``,
``modules__TEM1__linear__op0__sensitivity__K_W_per_K__A``, and the name
lists as string arrays.  In ``mat`` (MATLAB v5, ``scipy.io.savemat``):
structs; ``load('x.mat'); x.modules.TEM1.linear.op0.A`` in MATLAB,
``scipy.io.loadmat(f, simplify_cells=True)["modules"]["TEM1"]...`` in
Python.  Module ids that are not MATLAB names are written with
``[^A-Za-z0-9_]`` replaced by ``_`` and prefixed ``m_`` when they start
with a digit; ``meta.module_ids`` maps them back.
"""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np

from tembayes.data.batch import file_stem
from tembayes.data.write import atomic_write_bytes
from tembayes.export.observer import SCHEMA

FORMATS = ("json", "npz", "mat")


def _matlab_name(s):
    s = file_stem(s)
    return s if re.match(r"[A-Za-z]", s) else "m_" + s


def to_tree(exp, *, matlab_names=False):
    """The export as nested dicts of arrays, lists and numbers (the schema above)."""
    name = _matlab_name if matlab_names else (lambda s: s)
    mods, ids = {}, {}
    for mid, m in exp.modules.items():
        ops = {}
        for i, lm in enumerate(m["linear"]):
            ops[f"op{i}"] = {"tavg_C": lm.tavg_C, "current_A": lm.current_A, "x0": lm.x0, "u0": lm.u0,
                             "y0": lm.y0, "A": lm.A, "B": lm.B, "C": lm.C, "D": lm.D,
                             "sensitivity": {name(p): dict(s) for p, s in lm.sensitivity.items()}}
        pn = m["process_noise"]
        mods[name(mid)] = {"mean": m["mean"], "cov": m["cov"], "draws": m["draws"],
                           "measurement_noise_cov": m["measurement_noise_cov"],
                           "process_noise": {k: pn[k] for k in ("sd", "tau_s", "q_continuous", "source", "channels",
                                                                "corr", "sd_by_time_since_step", "step_bins_s",
                                                                "corr_by_time_since_step", "n_by_time_since_step")
                                             if k in pn},
                           "input_noise": dict(m["input_noise"]),
                           "linear": ops, "n_posterior": m["n_posterior"]}
        ids[name(mid)] = mid
    return {"schema": SCHEMA, "parameters": list(exp.parameters), "units": dict(exp.units),
            "states": list(exp.states), "inputs": list(exp.inputs), "outputs": list(exp.outputs),
            "meta": {**exp.meta, "module_ids": ids}, "modules": mods}


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, np.generic):
        return x.item()
    return x


def _flatten(tree, prefix=""):
    out = {}
    for k, v in tree.items():
        key = f"{prefix}__{k}" if prefix else k
        if isinstance(v, dict):
            out.update(_flatten(v, key))
        elif isinstance(v, (list, tuple)):
            out[key] = np.asarray(v, dtype=str) if all(isinstance(s, str) for s in v) else np.asarray(v)
        else:
            out[key] = np.asarray(v)
    return out


def encode(exp, fmt):
    """The export as bytes in ``fmt`` (``json``, ``npz`` or ``mat``)."""
    if fmt == "json":
        return (json.dumps(_jsonable(to_tree(exp)), indent=1) + "\n").encode()
    buf = io.BytesIO()
    if fmt == "npz":
        np.savez_compressed(buf, **_flatten(to_tree(exp)))
    elif fmt == "mat":
        from scipy.io import savemat

        tree = to_tree(exp, matlab_names=True)
        tree["meta"] = {k: (json.dumps(v) if isinstance(v, (dict, list)) else v) for k, v in tree["meta"].items()}
        savemat(buf, tree, long_field_names=True, do_compression=True, oned_as="column")
    else:
        raise ValueError(f"format must be one of {FORMATS}, got {fmt!r}")
    return buf.getvalue()


def write_export(exp, path, fmt):
    """Write the export to ``path`` atomically."""
    atomic_write_bytes(path, encode(exp, fmt))


def is_export_file(path) -> bool:
    """Whether ``path`` is a file this module wrote (any of the three encodings), by its schema entry."""
    import zipfile

    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(4096)
        if head.lstrip().startswith(b"{"):
            return b'"schema": "tembayes-observer-export/' in head
        if zipfile.is_zipfile(path):
            with zipfile.ZipFile(path) as z:
                return "schema.npy" in z.namelist()
        from scipy.io import whosmat

        return any(name == "schema" for name, _, _ in whosmat(path))
    except (OSError, ValueError, NotImplementedError, TypeError):
        return False
