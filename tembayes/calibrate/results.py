"""Calibration results on disk: per-module files, ``posterior.nc``, ``summary.json``.

A run folder::

    RUN/
      summary.json            docs/outputs.md, 'summary.json (calibrate)'
      posterior.nc            arviz InferenceData, all modules
      modules/<id>.nc         one module's posterior, written when it finishes
      modules/<id>.failed.json  a module whose calibration raised (error, traceback)
      checkpoints/<id>.*      sampler checkpoints (resume)
      figures/                corner plots

``posterior.nc`` groups (dims in brackets):

- ``posterior``: every sampled parameter, SI, contract names for the module
  parameters [chain, draw, module]; ``chain`` is the emcee walker.
- ``log_likelihood``: ``step_response`` [chain, draw, module, step], the
  log-likelihood of every step window (NaN where a module has fewer steps).
- ``sample_stats``: ``lp`` [chain, draw, module].
- ``observed_data``: ``voltage_V``, ``dT_K``, ``Tmean_K`` [module, obs]
  (the step windows' samples; NaN padding).
- ``constant_data``: ``obs_time_s``, ``obs_step`` [module, obs];
  ``step_time_s``, ``step_dI_A``, ``step_direction``, ``step_Tavg_C``
  [module, step]; ``noise_sd`` [module, channel].
- ``prior``: draws of the module parameters from the datasheet prior
  [chain, draw, module], shaped like ``posterior`` (every module of a batch
  has the same datasheet prior, so the same draws).
- ``population`` (if fitted): ``R0_ohm``... draws for a new module
  [chain, draw], and the hyperparameters.

Every data variable has a ``units`` attribute (:func:`variable_unit`).

Per-module metadata (names, held names, diagnostics, hysteresis, priors, mode,
seeds, rig, options, the rig parameters' units) is kept as
JSON in the attributes, so a module file alone restores its
:class:`~tembayes.calibrate.module.ModuleCalibration`.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import re
import tempfile
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import xarray as xr

from tembayes.calibrate.diagnostics import ModuleDiagnostics
from tembayes.calibrate.module import ModuleCalibration
from tembayes.calibrate.stepdata import CHANNELS
from tembayes.common.arvizlib import az
from tembayes.constants import KELVIN, MODULE_PARAMETERS, T_REF
from tembayes.data.write import to_jsonable

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from numpy.typing import ArrayLike

    from tembayes.calibrate.population import PopulationResult


def _pad(arrays, fill=np.nan):
    """Stack 1-D/2-D arrays of different last length along a new first axis."""
    n = max(a.shape[-1] for a in arrays)
    out = np.full((len(arrays),) + arrays[0].shape[:-1] + (n,), fill, dtype=np.result_type(arrays[0], type(fill)))
    for i, a in enumerate(arrays):
        out[i, ..., : a.shape[-1]] = a
    return out


# -- units -------------------------------------------------------------------
#: Name tokens that are a unit: the parameter names end in their unit
#: (``R0_ohm``, ``K_W_per_K``, ``step_shift_s``, ``offset_sd_dT_K``).
_UNIT_TOKENS = {
    "ohm": "ohm",
    "V": "V",
    "K": "K",
    "W": "W",
    "A": "A",
    "J": "J",
    "s": "s",
    "m": "m",
    "C": "degC",
    "rel": "1",
    "fraction": "1",
}
#: Variables whose name does not end in a unit.
_FIXED_UNITS = {
    "step_response": "nat",
    "lp": "nat",
    "obs_step": "1",
    "step_direction": "1",
    "noise_sd": "per channel: " + ", ".join(_UNIT_TOKENS[c.rsplit("_", 1)[1]] for c in CHANNELS),
}


@functools.lru_cache(maxsize=1)
def _table_units():
    """Units of the rig's parameters and the effect catalogue's (no suffix: ``g_cooler``, ``tab_share``)."""
    from tembayes.physics.effects import CATALOGUE
    from tembayes.physics.rigread import shipped_rig

    out = {p.name: p.unit for p in shipped_rig("reference").build(layers=True).parameters}
    out.update({p.name: p.unit for e in CATALOGUE.values() for p in e.parameters})
    return out


def _suffix_unit(name):
    """Unit from a name's ending (``_ohm``, ``_V_per_K``, ``_per_K2``), or None."""
    tok = name.split("_")
    if len(tok) >= 2 and tok[-2] == "per":
        m = re.fullmatch(r"([A-Za-z]+?)(\d*)", tok[-1])
        den = _UNIT_TOKENS.get(m.group(1)) if m else None
        if den is None or den in ("1", "degC"):
            return None
        den += f"^{m.group(2)}" if m.group(2) not in ("", "1") else ""
        num = _UNIT_TOKENS.get(tok[-3], "1") if len(tok) >= 3 else "1"  # K1_per_K: 1/K
        return f"{num}/{den}"
    return _UNIT_TOKENS.get(tok[-1]) if len(tok) >= 2 else None


def variable_unit(name: str, units: Mapping[str, str] | None = None) -> str | None:
    """SI unit of a ``posterior.nc`` variable (its ``units`` attribute), or None if unknown.

    From, in turn: ``units`` (the calibration rig's own parameters, e.g. a
    rig file's ``g_sink``); the log-likelihoods (``"nat"``) and indices
    (``"1"``); the reference rig's and the effect catalogue's parameter tables
    (:class:`~tembayes.physics.rig.RigParameter`,
    :class:`~tembayes.physics.effects.EffectParameter`); the noise scales
    (``"1"``); the population's ``hyper_``/``mu_``/``tau_`` prefixes; the name's
    unit suffix (``R1_ohm_per_K`` -> ``"ohm/K"``, ``S1_V_per_K2`` -> ``"V/K^2"``,
    ``step_Tavg_C`` -> ``"degC"``, ``tau_R0_rel`` -> ``"1"``).

    Parameters
    ----------
    name : str
    units : dict, optional
        ``name -> unit`` of the run's rig parameters (:attr:`ModuleCalibration.units`).
    """
    if units and name in units:
        return units[name]
    if name in _FIXED_UNITS:
        return _FIXED_UNITS[name]
    table = _table_units()
    if name in table:
        return table[name]
    if name.startswith("noise_scale_"):
        return "1"
    for prefix in ("hyper_", "mu_", "tau_"):
        if name.startswith(prefix):
            return variable_unit(name[len(prefix) :], units)
    return _suffix_unit(name)


def _set_units(ds, units=None):
    """Put ``units`` on every data variable of ``ds`` whose unit is known (in place; see :func:`variable_unit`)."""
    for k, v in ds.data_vars.items():
        u = variable_unit(k, units)
        if u is not None:
            v.attrs["units"] = u
    return ds


def _meta(r: ModuleCalibration):
    return json.dumps(
        to_jsonable(
            {
                "module_id": r.module_id,
                "names": list(r.names),
                "held": list(r.held),
                "priors": r.priors,
                "map": r.map,
                "diagnostics": r.diagnostics.to_json(),
                "hysteresis": r.hysteresis,
                "seed": r.seed,
                "rig": r.rig,
                "options": r.options,
                "units": r.units,
            }
        )
    )


def to_inference_data(
    results: Sequence[ModuleCalibration],
    *,
    population: PopulationResult | None = None,
    prior_draws: Mapping[str, ArrayLike] | None = None,
    attrs: Mapping | None = None,
) -> az.InferenceData:
    """InferenceData of one or more :class:`ModuleCalibration` (same parameters).

    Parameters
    ----------
    results : list of ModuleCalibration
    population : PopulationResult, optional
    prior_draws : dict, optional
        ``name -> ndarray (n,)`` prior draws of the module parameters (the
        datasheet prior the modules share; repeated for each module).
    attrs : dict, optional
        Extra attributes (seed, command, versions).
    """
    names = results[0].names + results[0].held
    for r in results:
        if r.names + r.held != names:
            raise ValueError(f"module {r.module_id} has parameters {r.names + r.held}, expected {names}")
    mods = [r.module_id for r in results]
    nw, nk = results[0].draws[names[0]].shape
    for r in results:
        if r.draws[names[0]].shape != (nw, nk):
            raise ValueError(f"module {r.module_id}: draws {r.draws[names[0]].shape}, expected {(nw, nk)}")
    coords = {"chain": np.arange(nw), "draw": np.arange(nk), "module": mods}
    cd = ("chain", "draw", "module")
    post = xr.Dataset({n: (cd, np.stack([r.draws[n] for r in results], axis=-1)) for n in names}, coords=coords)
    ns = max(r.step_loglike.shape[-1] for r in results)
    ll = np.full((nw, nk, len(mods), ns), np.nan)
    for i, r in enumerate(results):
        ll[:, :, i, : r.step_loglike.shape[-1]] = r.step_loglike
    loglik = xr.Dataset({"step_response": (cd + ("step",), ll)}, coords={**coords, "step": np.arange(ns)})
    stats = xr.Dataset({"lp": (cd, np.stack([r.log_prob for r in results], axis=-1))}, coords=coords)
    obs = _pad([r.observed["obs"] for r in results])  # (module, 3, n)
    nobs = obs.shape[-1]
    oc = {"module": mods, "obs": np.arange(nobs)}
    observed = xr.Dataset({c: (("module", "obs"), obs[:, j]) for j, c in enumerate(CHANNELS)}, coords=oc)
    steps = {
        "step_time_s": _pad([np.asarray(r.steps["t_s"], float) for r in results]),
        "step_dI_A": _pad([np.asarray(r.steps["dI_A"], float) for r in results]),
        "step_direction": _pad([np.asarray(r.steps["direction"], float) for r in results], 0.0),
        "step_Tavg_C": _pad([np.asarray(r.steps["Tavg_K"], float) - KELVIN for r in results]),
    }
    const = xr.Dataset(
        {
            "obs_time_s": (("module", "obs"), _pad([r.observed["time_s"] for r in results])),
            "obs_step": (("module", "obs"), _pad([r.observed["step"].astype(float) for r in results], -1.0)),
            **{k: (("module", "step"), v) for k, v in steps.items()},
            "noise_sd": (("module", "channel"), np.stack([r.observed["noise"] for r in results])),
        },
        coords={**oc, "step": np.arange(ns), "channel": list(CHANNELS)},
    )
    groups = {
        "posterior": post,
        "log_likelihood": loglik,
        "sample_stats": stats,
        "observed_data": observed,
        "constant_data": const,
    }
    if prior_draws is not None:
        groups["prior"] = prior_dataset(prior_draws, mods)
    if population is not None:
        groups["population"] = population_dataset(population)
    units = {k: u for r in results for k, u in r.units.items()}
    for ds in groups.values():
        _set_units(ds, units)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "population" is not one of arviz's standard groups
        idata = az.InferenceData(**groups)
    meta = {f"module_{r.module_id}": _meta(r) for r in results}
    for g in idata.groups():
        getattr(idata, g).attrs.update({"tembayes_tref_C": T_REF - KELVIN})
    idata.posterior.attrs.update(meta)
    idata.posterior.attrs.update(
        {k: json.dumps(to_jsonable(v)) if not isinstance(v, str) else v for k, v in (attrs or {}).items()}
    )
    return idata


def prior_dataset(prior_draws: Mapping[str, ArrayLike], modules: Sequence[str]) -> xr.Dataset:
    """The ``prior`` group: ``name -> (n,)`` draws as one chain, with units.

    The same draws for every module (they share the datasheet prior), on
    the dimensions [chain, draw, module].
    """
    n = len(next(iter(prior_draws.values())))
    data = {
        k: (("chain", "draw", "module"), np.repeat(np.asarray(v, dtype=float)[None, :, None], len(modules), axis=2))
        for k, v in prior_draws.items()
    }
    return _set_units(xr.Dataset(data, coords={"chain": [0], "draw": np.arange(n), "module": list(modules)}))


def _json_or_none(result):
    """A typed population result as its ``summary.json`` entry (None stays None)."""
    return None if result is None else to_jsonable(result.to_json())


def population_dataset(pop: PopulationResult) -> xr.Dataset:
    """The ``population`` group: predictive draws [chain, draw] and hyperparameters."""
    pred = np.asarray(pop.predictive)
    first = next(iter(pop.hyper.values())) if pop.hyper else None
    if first is not None:
        nw, nd = np.shape(first)
    else:
        nw, nd = 1, len(pred)
    if pred.shape[0] == nw * nd:
        shaped = pred.reshape(nw, nd, -1)
    else:
        shaped = pred[None]
        nw, nd = 1, len(pred)
    data = {k: (("chain", "draw"), shaped[:, :, j]) for j, k in enumerate(MODULE_PARAMETERS)}
    hyper = {f"hyper_{k}": (("hyper_chain", "hyper_draw"), np.asarray(v)) for k, v in pop.hyper.items()}
    ds = _set_units(xr.Dataset({**data, **hyper}))
    ds.attrs["outlier_prob"] = json.dumps(to_jsonable(pop.outlier_prob))
    ds.attrs["odd_one_prob"] = json.dumps(to_jsonable(pop.odd_one_prob))
    ds.attrs["p_any_outlier"] = json.dumps(to_jsonable(pop.p_any_outlier))
    ds.attrs["deviation"] = json.dumps(to_jsonable(pop.deviation))
    ds.attrs["outlier_vs_spread"] = json.dumps(_json_or_none(pop.outlier_vs_spread))
    ds.attrs["smallest_flagged_deviation"] = json.dumps(_json_or_none(pop.smallest_flagged))
    ds.attrs["diagnostics"] = json.dumps(to_jsonable(pop.diagnostics))
    return ds


@contextlib.contextmanager
def _atomic(path):
    """A temporary file next to ``path`` (yielded), renamed onto it if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def write_netcdf(idata: az.InferenceData, path: Path | str) -> Path:
    """Write an InferenceData atomically (temporary file, then rename)."""
    with _atomic(path) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        idata.to_netcdf(tmp, engine="h5netcdf")
    return Path(path)


def read_module(path: Path | str) -> ModuleCalibration:
    """Restore a :class:`ModuleCalibration` from a per-module ``.nc`` file."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        idata = az.from_netcdf(path, engine="h5netcdf")
    post = idata.posterior
    keys = [k for k in post.attrs if k.startswith("module_")]
    if len(keys) != 1:
        raise ValueError(f"{path}: expected one module, found {len(keys)}")
    meta = json.loads(post.attrs[keys[0]])
    mid = meta["module_id"]
    names = tuple(meta["names"])
    held = tuple(meta.get("held", ()))  # runs that predate it kept no held draws
    draws = {n: post[n].sel(module=mid).values for n in names + held}
    ll = idata.log_likelihood["step_response"].sel(module=mid).values
    ns = int(np.sum(~np.isnan(idata.constant_data["step_time_s"].sel(module=mid).values)))
    const = idata.constant_data
    nobs = int(np.sum(~np.isnan(idata.observed_data[CHANNELS[0]].sel(module=mid).values)))
    obs = np.stack([idata.observed_data[c].sel(module=mid).values[:nobs] for c in CHANNELS])
    steps = {
        "t_s": const["step_time_s"].sel(module=mid).values[:ns],
        "dI_A": const["step_dI_A"].sel(module=mid).values[:ns],
        "direction": const["step_direction"].sel(module=mid).values[:ns].astype(int),
        "Tavg_K": const["step_Tavg_C"].sel(module=mid).values[:ns] + KELVIN,
    }
    time_s = const["obs_time_s"].sel(module=mid).values[:nobs]
    step = const["obs_step"].sel(module=mid).values[:nobs].astype(int)
    return ModuleCalibration(
        module_id=mid,
        names=names,
        draws=draws,
        log_prob=idata.sample_stats["lp"].sel(module=mid).values,
        step_loglike=ll[:, :, :ns],
        priors=meta["priors"],
        map=meta["map"],
        diagnostics=ModuleDiagnostics.from_json(meta["diagnostics"]),
        steps=steps,
        observed={
            "time_s": time_s,
            "step": step,
            "since_s": time_s - steps["t_s"][step],
            "obs": obs,
            "noise": const["noise_sd"].sel(module=mid).values,
        },
        hysteresis=meta["hysteresis"],
        seed=meta["seed"],
        rig=meta["rig"],
        options=meta.get("options", {}),
        held=held,
        units=meta.get("units", {}),
    )


def stats(x: ArrayLike) -> dict[str, float]:
    """``{"mean", "sd", "q05", "q95"}`` of draws."""
    x = np.asarray(x, dtype=float).ravel()
    q05, q95 = np.quantile(x, [0.05, 0.95])
    return {"mean": float(np.mean(x)), "sd": float(np.std(x, ddof=1)), "q05": float(q05), "q95": float(q95)}


def module_entry(r: ModuleCalibration, outlier_prob: float | None = None) -> dict:
    """One module's ``summary.json`` entry (docs/outputs.md, 'summary.json (calibrate)').

    The five parameters, ``outlier_prob``, ``odd_one_prob`` and ``deviation``
    (null without a population fit or for a module left out of it; filled in
    by :func:`summary`), ``diagnostics`` (``rhat_max``,
    ``ess_bulk_min``, ``converged`` plus ``tau_max_steps``, ``steps``,
    ``psis_k``; ``psis_draws``, ``psis_effective_draws`` and
    ``psis_law_shift_sd`` where the record has them); extras: ``hysteresis``, ``nuisance`` (rig parameters, step
    shift, noise), ``held`` (with ``--discrepancy robust``: the held rig
    parameters' carried-over draws).
    """
    d = r.diagnostics
    entry = {k: stats(r.draws[k]) for k in MODULE_PARAMETERS}
    entry["outlier_prob"] = None if outlier_prob is None else float(outlier_prob)
    entry["odd_one_prob"] = None
    entry["deviation"] = None
    entry["diagnostics"] = {
        "rhat_max": d.rhat_max,
        "ess_bulk_min": d.ess_bulk_min,
        "converged": d.converged,
        "tau_max_steps": d.tau_max_steps,
        "chain_over_tau": d.chain_over_tau,
        "steps": d.steps,
        "psis_k": d.psis_k,
        "sampler_converged": d.sampler_converged,
        "seconds": d.timings["total_s"],
    }
    for k in ("rhat_walkers_max", "discrepancy", "adequacy"):  # runs that predate them have none
        if getattr(d, k) is not None:
            entry["diagnostics"][k] = getattr(d, k)
    last = d.psis[-1]
    if last.draws is not None:
        entry["diagnostics"]["psis_draws"] = last.draws
        entry["diagnostics"]["psis_effective_draws"] = last.effective_draws
        entry["diagnostics"]["psis_law_shift_sd"] = last.law_shift_sd
    entry["hysteresis"] = r.hysteresis
    entry["nuisance"] = {k: stats(r.draws[k]) for k in r.names if k not in MODULE_PARAMETERS}
    if r.held:
        entry["held"] = {k: stats(r.draws[k]) for k in r.held}
    return entry


def summary(
    results: Sequence[ModuleCalibration],
    population: PopulationResult | None = None,
    *,
    extra: Mapping | None = None,
    entries: Mapping[str, dict] | None = None,
) -> dict:
    """``summary.json`` content (docs/outputs.md, 'summary.json (calibrate)').

    Parameters
    ----------
    results : list of ModuleCalibration
        Modules held in memory (small batches); or empty with ``entries``.
    population : PopulationResult, optional
    extra : dict, optional
        Top-level keys added (batch, calibration, ...).
    entries : dict, optional
        ``module id -> module_entry(...)`` made one module at a time (large
        batches); their ``outlier_prob`` is filled from ``population``.
    """
    mods = dict(entries or {})
    for r in results:
        mods[r.module_id] = module_entry(r)
    if population is not None:
        for mid, p in population.outlier_prob.items():
            if mid in mods:
                mods[mid]["outlier_prob"] = float(p)
                mods[mid]["odd_one_prob"] = population.odd_one_prob.get(mid)
                mods[mid]["deviation"] = population.deviation.get(mid)
    out = {"tref_C": T_REF - KELVIN, "modules": mods}
    out["p_any_outlier"] = None if population is None else population.p_any_outlier
    out["outlier_vs_spread"] = None if population is None else _json_or_none(population.outlier_vs_spread)
    out["smallest_flagged_deviation"] = None if population is None else _json_or_none(population.smallest_flagged)
    if population is not None:
        out["population"] = population.summary()
        out["population_diagnostics"] = population.diagnostics
    else:
        out["population"] = None
    out["converged"] = bool(
        all(m["diagnostics"]["converged"] for m in mods.values())
        and (population is None or bool(population.diagnostics.get("converged", True)))
    )
    if extra:
        out.update(extra)
    return to_jsonable(out)


# -- posterior.nc for any number of modules -----------------------------------
#: Padding of the ragged (step, obs) variables other than NaN, as
#: :func:`to_inference_data` writes it.
_PADDING = {"obs_step": -1.0, "step_direction": 0.0}


def _module_layout(path):
    """Shapes and names of one per-module file, without reading its arrays."""
    import h5netcdf

    with h5netcdf.File(path, "r") as f:
        post = f["posterior"]
        names = [k for k in post.variables if k not in ("chain", "draw", "module")]
        ns = int(np.sum(np.isfinite(f["constant_data"]["step_time_s"][0, :])))
        nobs = int(np.sum(np.isfinite(f["observed_data"][CHANNELS[0]][0, :])))
        mid = post["module"][0]
        return {
            "names": names,
            "units": {k: post[k].attrs["units"] for k in names if "units" in post[k].attrs},
            "nw": post.dimensions["chain"].size,
            "nk": post.dimensions["draw"].size,
            "ns": ns,
            "nobs": nobs,
            "module": mid.decode() if isinstance(mid, bytes) else str(mid),
        }


def write_run_posterior(
    path: Path | str,
    module_files: Sequence[Path],
    *,
    population: PopulationResult | None = None,
    prior_draws: Mapping[str, ArrayLike] | None = None,
    attrs: Mapping | None = None,
    progress: Callable[[str], None] | None = None,
) -> Path:
    """Write ``posterior.nc`` of a batch from its per-module files, one module at a time.

    The result is the file :func:`to_inference_data` of all the modules would
    give (same groups, variables, padding and attributes), but memory holds
    one module's arrays at a time, so it scales to thousands of modules.
    Written to a temporary file, then renamed.

    Parameters
    ----------
    path : str or Path
        ``RUN/posterior.nc``.
    module_files : list of Path
        ``RUN/modules/<id>.nc`` in the batch's order; same parameters and
        draws per module.
    population : PopulationResult, optional
    prior_draws : dict, optional
        ``name -> ndarray (n,)``, the datasheet prior all the modules share
        (written for each module, [chain, draw, module]).
    attrs : dict, optional
        Run attributes on the posterior group (seed, command, versions).
    progress : callable, optional
        ``progress(message)`` every 500 modules.
    """
    import h5netcdf

    path = Path(path)
    lay = [_module_layout(p) for p in module_files]
    if not lay:
        raise ValueError("no module files to write")
    names, nw, nk = lay[0]["names"], lay[0]["nw"], lay[0]["nk"]
    units = {k: u for m in lay for k, u in m["units"].items()}
    for p, m in zip(module_files, lay):
        if m["names"] != names or (m["nw"], m["nk"]) != (nw, nk):
            raise ValueError(
                f"{p}: parameters {m['names']} and draws {(m['nw'], m['nk'])} differ from "
                f"the first module's {names}, {(nw, nk)}"
            )
    mods = [m["module"] for m in lay]
    n, ns, nobs = len(mods), max(m["ns"] for m in lay), max(m["nobs"] for m in lay)
    tref = T_REF - KELVIN
    with _atomic(path) as tmp:
        with h5netcdf.File(tmp, "w") as f:
            sizes = {"chain": nw, "draw": nk, "module": n, "step": ns, "obs": nobs, "channel": len(CHANNELS)}
            coord = {
                "chain": np.arange(nw),
                "draw": np.arange(nk),
                "module": mods,
                "step": np.arange(ns),
                "obs": np.arange(nobs),
                "channel": list(CHANNELS),
            }
            layout = {  # group -> variable -> dims (the to_inference_data layout)
                "posterior": {k: ("chain", "draw", "module") for k in names},
                "log_likelihood": {"step_response": ("chain", "draw", "module", "step")},
                "sample_stats": {"lp": ("chain", "draw", "module")},
                "observed_data": {c: ("module", "obs") for c in CHANNELS},
                "constant_data": {
                    "obs_time_s": ("module", "obs"),
                    "obs_step": ("module", "obs"),
                    "step_time_s": ("module", "step"),
                    "step_dI_A": ("module", "step"),
                    "step_direction": ("module", "step"),
                    "step_Tavg_C": ("module", "step"),
                    "noise_sd": ("module", "channel"),
                },
            }
            groups = {}
            for g, variables in layout.items():
                grp = f.create_group(g)
                used = [d for d in sizes if any(d in dims for dims in variables.values())]
                grp.dimensions = {d: sizes[d] for d in used}
                for d in used:
                    data = coord[d]
                    if d in ("module", "channel"):
                        grp.create_variable(d, (d,), dtype=_vlen_str(), data=np.array(data, dtype=object))
                    else:
                        grp.create_variable(d, (d,), data=np.asarray(data, dtype=np.int64))
                for k, dims in variables.items():
                    chunks = tuple(1 if d == "module" else sizes[d] for d in dims)
                    v = grp.create_variable(k, dims, dtype="f8", chunks=chunks, fillvalue=np.nan)
                    v.attrs["_FillValue"] = np.nan
                    unit = variable_unit(k, units)
                    if unit is not None:
                        v.attrs["units"] = unit
                grp.attrs["tembayes_tref_C"] = tref
                groups[g] = grp
            if prior_draws is not None:  # prior_dataset's layout, written a module at a time
                prior = {k: np.asarray(v, dtype=float) for k, v in prior_draws.items()}
                nd = len(next(iter(prior.values())))
                grp = f.create_group("prior")
                grp.dimensions = {"chain": 1, "draw": nd, "module": n}
                grp.create_variable("chain", ("chain",), data=np.zeros(1, dtype=np.int64))
                grp.create_variable("draw", ("draw",), data=np.arange(nd, dtype=np.int64))
                grp.create_variable("module", ("module",), dtype=_vlen_str(), data=np.array(mods, dtype=object))
                for k in prior:
                    v = grp.create_variable(
                        k, ("chain", "draw", "module"), dtype="f8", chunks=(1, nd, 1), fillvalue=np.nan
                    )
                    v.attrs["_FillValue"] = np.nan
                    unit = variable_unit(k, units)
                    if unit is not None:
                        v.attrs["units"] = unit
                grp.attrs["tembayes_tref_C"] = tref
            for i, (p, m) in enumerate(zip(module_files, lay)):
                with h5netcdf.File(p, "r") as src:
                    for g, variables in layout.items():
                        for k, dims in variables.items():
                            a = np.asarray(src[g][k][...], dtype=float)
                            tgt = groups[g][k]
                            mi = dims.index("module")
                            a = np.take(a, 0, axis=mi)  # the file's single module
                            if dims[-1] in ("step", "obs"):  # ragged: pad to the batch's longest
                                full = np.full(a.shape[:-1] + (sizes[dims[-1]],), _PADDING.get(k, np.nan))
                                full[..., : a.shape[-1]] = a
                                a = full
                            tgt[tuple(i if d == "module" else slice(None) for d in dims)] = a
                    groups["posterior"].attrs[f"module_{m['module']}"] = src["posterior"].attrs[f"module_{m['module']}"]
                if prior_draws is not None:
                    for k, a in prior.items():
                        f["prior"][k][0, :, i] = a
                if progress and (i + 1) % 500 == 0:
                    progress(f"posterior.nc: {i + 1}/{n} modules")
            for k, v in (attrs or {}).items():
                groups["posterior"].attrs[k] = v if isinstance(v, str) else json.dumps(to_jsonable(v))
        extra = {}
        if population is not None:
            extra["population"] = population_dataset(population)
        for g, ds in extra.items():
            ds.attrs["tembayes_tref_C"] = tref
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ds.to_netcdf(tmp, mode="a", group=g, engine="h5netcdf")
    return path


def _vlen_str():
    import h5py

    return h5py.string_dtype()
