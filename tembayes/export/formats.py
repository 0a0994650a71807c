"""Write an :class:`~tembayes.export.observer.ObserverExport` as JSON, NPZ or MAT.

One layout (:data:`~tembayes.export.schema.SCHEMA`), three encodings; every
field, its shape, unit and meaning is in :data:`tembayes.export.schema.FIELDS`,
written into the file as ``fields`` and listed in docs/outputs.md, 'The export
file (export)'.  ``json`` and ``mat`` nest; ``npz`` cannot, so its keys are
the nested paths joined by ``__`` (``modules__TEM1__linear__op0__A``) and the
name lists are string arrays.  In ``mat`` (MATLAB v5, ``scipy.io.savemat``)
the nesting is structs (``x.modules.TEM1.linear.op0.A`` in MATLAB,
``scipy.io.loadmat(f, simplify_cells=True)["modules"]["TEM1"]...`` in
Python); ``meta``'s lists and tables are JSON text there, and module ids
that are not MATLAB names are written with ``[^A-Za-z0-9_]`` replaced by
``_`` and prefixed ``m_`` when they start with a digit (``meta.module_ids``
maps them back).
"""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import numpy as np

from tembayes.data.batch import file_stem
from tembayes.data.write import atomic_write_bytes
from tembayes.export.schema import SCHEMA, fields_table

FORMATS = ("json", "npz", "mat")


def _matlab_name(s):
    s = file_stem(s)
    return s if re.match(r"[A-Za-z]", s) else "m_" + s


def to_tree(exp, *, matlab_names=False):
    """The export as nested dicts of arrays, lists and numbers (:data:`~tembayes.export.schema.FIELDS`)."""
    name = _matlab_name if matlab_names else (lambda s: s)
    mods = {name(mid): _module_tree(m, name) for mid, m in exp.modules.items()}
    ids = {name(mid): mid for mid in exp.modules}
    return {
        "schema": SCHEMA,
        "fields": fields_table(),
        "parameters": list(exp.parameters),
        "units": dict(exp.units),
        "states": list(exp.states),
        "inputs": list(exp.inputs),
        "input_units": list(exp.input_units),
        "outputs": list(exp.outputs),
        "output_units": list(exp.output_units),
        "meta": {**exp.meta, "module_ids": ids},
        "modules": mods,
    }


def _module_tree(m, name):
    """One :class:`~tembayes.export.observer.ModuleExport` as nested dicts."""
    ops = {}
    for i, lm in enumerate(m.linear):
        ops[f"op{i}"] = {
            "tavg_C": lm.tavg_C,
            "current_A": lm.current_A,
            "x0": lm.x0,
            "u0": lm.u0,
            "y0": lm.y0,
            "A": lm.A,
            "B": lm.B,
            "C": lm.C,
            "D": lm.D,
            "sensitivity": {name(p): dict(s) for p, s in lm.sensitivity.items()},
        }
    return {
        "mean": m.mean,
        "cov": m.cov,
        "draws": m.draws,
        "measurement_noise_cov": m.measurement_noise_cov,
        "process_noise": dict(m.process_noise),
        "input_noise": dict(m.input_noise),
        "linear": ops,
        "n_posterior": m.n_posterior,
    }


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
