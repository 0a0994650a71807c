"""Calibration results on disk: per-module files, ``posterior.nc``, ``summary.json``.

A run folder::

    RUN/
      summary.json            contract section 4
      posterior.nc            arviz InferenceData, all modules
      modules/<id>.nc         one module's posterior, written when it finishes
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
  [chain, draw] (the same for every module).
- ``population`` (if fitted): ``R0_ohm``... draws for a new module
  [chain, draw], and the hyperparameters.

Per-module metadata (diagnostics, hysteresis, priors, mode, seeds) is kept as
JSON in the attributes, so a module file alone restores its
:class:`~tembayes.calibrate.module.ModuleCalibration`.
"""

from __future__ import annotations

import json
import os
import tempfile
import warnings
from pathlib import Path

import arviz as az
import numpy as np
import xarray as xr

from tembayes.calibrate.module import ModuleCalibration
from tembayes.calibrate.stepdata import CHANNELS
from tembayes.constants import KELVIN, MODULE_PARAMETERS, T_REF
from tembayes.data.write import to_jsonable


def _pad(arrays, fill=np.nan):
    """Stack 1-D/2-D arrays of different last length along a new first axis."""
    n = max(a.shape[-1] for a in arrays)
    out = np.full((len(arrays),) + arrays[0].shape[:-1] + (n,), fill, dtype=np.result_type(arrays[0], type(fill)))
    for i, a in enumerate(arrays):
        out[i, ..., : a.shape[-1]] = a
    return out


def _meta(r: ModuleCalibration):
    return json.dumps(to_jsonable({
        "module_id": r.module_id, "names": list(r.names), "priors": r.priors, "map": r.map,
        "diagnostics": r.diagnostics, "hysteresis": r.hysteresis, "seed": r.seed, "rig": r.rig,
        "options": r.options,
    }))


def to_inference_data(results, *, population=None, prior_draws=None, attrs=None):
    """InferenceData of one or more :class:`ModuleCalibration` (same parameters).

    Parameters
    ----------
    results : list of ModuleCalibration
    population : PopulationResult, optional
    prior_draws : dict, optional
        ``name -> ndarray (n,)`` prior draws of the module parameters.
    attrs : dict, optional
        Extra attributes (seed, command, versions).
    """
    names = results[0].names
    for r in results:
        if r.names != names:
            raise ValueError(f"module {r.module_id} has parameters {r.names}, expected {names}")
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
    groups = {"posterior": post, "log_likelihood": loglik, "sample_stats": stats, "observed_data": observed,
              "constant_data": const}
    if prior_draws is not None:
        n = len(next(iter(prior_draws.values())))
        groups["prior"] = xr.Dataset({k: (("chain", "draw"), np.asarray(v)[None, :]) for k, v in prior_draws.items()},
                                     coords={"chain": [0], "draw": np.arange(n)})
    if population is not None:
        groups["population"] = population_dataset(population)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "population" is not one of arviz's standard groups
        idata = az.InferenceData(**groups)
    meta = {f"module_{r.module_id}": _meta(r) for r in results}
    for g in idata.groups():
        getattr(idata, g).attrs.update({"tembayes_tref_C": T_REF - KELVIN})
    idata.posterior.attrs.update(meta)
    idata.posterior.attrs.update({k: json.dumps(to_jsonable(v)) if not isinstance(v, str) else v
                                  for k, v in (attrs or {}).items()})
    return idata


def population_dataset(pop):
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
    ds = xr.Dataset({**data, **hyper})
    ds.attrs["outlier_prob"] = json.dumps(to_jsonable(pop.outlier_prob))
    ds.attrs["diagnostics"] = json.dumps(to_jsonable(pop.diagnostics))
    return ds


def write_netcdf(idata, path):
    """Write an InferenceData atomically (temporary file, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            idata.to_netcdf(tmp, engine="h5netcdf")
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def read_module(path):
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
    draws = {n: post[n].sel(module=mid).values for n in names}
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
        module_id=mid, names=names, draws=draws, log_prob=idata.sample_stats["lp"].sel(module=mid).values,
        step_loglike=ll[:, :, :ns], priors=meta["priors"], map=meta["map"], diagnostics=meta["diagnostics"],
        steps=steps,
        observed={"time_s": time_s, "step": step, "since_s": time_s - steps["t_s"][step], "obs": obs,
                  "noise": const["noise_sd"].sel(module=mid).values},
        hysteresis=meta["hysteresis"], seed=meta["seed"], rig=meta["rig"], options=meta.get("options", {}),
    )


def stats(x):
    """``{"mean", "sd", "q05", "q95"}`` of draws."""
    x = np.asarray(x, dtype=float).ravel()
    q05, q95 = np.quantile(x, [0.05, 0.95])
    return {"mean": float(np.mean(x)), "sd": float(np.std(x, ddof=1)), "q05": float(q05), "q95": float(q95)}


def summary(results, population=None, *, extra=None):
    """``summary.json`` content (contract section 4, plus documented extras).

    Per module: the five parameters, ``outlier_prob`` (null without a
    population fit), ``diagnostics`` (``rhat_max``, ``ess_bulk_min``,
    ``converged`` plus ``tau_max_steps``, ``steps``, ``psis_k``); extras:
    ``hysteresis``, ``nuisance`` (rig parameters, step shift, noise).
    """
    mods = {}
    for r in results:
        d = r.diagnostics
        entry = {k: stats(r.draws[k]) for k in MODULE_PARAMETERS}
        entry["outlier_prob"] = None if population is None else float(population.outlier_prob[r.module_id])
        entry["diagnostics"] = {
            "rhat_max": d["rhat_max"], "ess_bulk_min": d["ess_bulk_min"], "converged": bool(d["converged"]),
            "tau_max_steps": d["tau_max_steps"], "chain_over_tau": d["chain_over_tau"], "steps": d["steps"],
            "psis_k": d["psis"][-1]["k_hat"], "sampler_converged": d["sampler_converged"],
            "seconds": d["timings"]["total_s"],
        }
        entry["hysteresis"] = r.hysteresis
        entry["nuisance"] = {k: stats(r.draws[k]) for k in r.names if k not in MODULE_PARAMETERS}
        mods[r.module_id] = entry
    out = {"tref_C": T_REF - KELVIN, "modules": mods}
    if population is not None:
        out["population"] = population.summary()
        out["population_diagnostics"] = population.diagnostics
    else:
        out["population"] = None
    out["converged"] = bool(all(m["diagnostics"]["converged"] for m in mods.values()) and
                            (population is None or bool(population.diagnostics.get("converged", True))))
    if extra:
        out.update(extra)
    return to_jsonable(out)
