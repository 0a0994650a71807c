"""Calibrate a batch: every module, then the population (``tembayes calibrate``).

Modules are independent (each has its own random stream from the run seed
and its id), so the batch is a loop over :func:`calibrate_module` -- over
``jobs`` worker processes at once, with identical results -- whose results
are written to ``RUN/modules/<id>.nc`` as they finish; a resumed run reuses
finished modules and continues interrupted ones from their sampler
checkpoints.  The population stage
(:func:`tembayes.calibrate.population.fit_population`) reuses the modules'
posterior draws, under the spreads ``batch.toml``'s optional ``[population]``
table states; ``summary.json`` records them (``population_prior``) and the
spreads this batch learned in that table's format (``population_spreads``).
"""

from __future__ import annotations

import multiprocessing
import shlex
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

import tembayes
from tembayes.calibrate import results as res
from tembayes.calibrate.module import CalibrationOptions, calibrate_module, module_seed
from tembayes.calibrate.priors import law_priors
from tembayes.data.write import write_json


def _versions():
    import arviz
    import emcee
    import numba
    import scipy

    return {"tembayes": tembayes.__version__, "python": sys.version.split()[0], "numpy": np.__version__,
            "scipy": scipy.__version__, "emcee": emcee.__version__, "arviz": arviz.__version__,
            "numba": numba.__version__}


def prior_draws(datasheet, seed, n=4000):
    """Draws of the module parameters from the datasheet prior (negative control, plots)."""
    rng = np.random.default_rng(np.random.SeedSequence(entropy=int(seed), spawn_key=(0x5052,)))
    return {p.name: p.sample(rng, n) for p in law_priors(datasheet)}


def spread_prior(population_table):
    """``batch.toml``'s ``[population]`` spreads -> ``fit_population(spread_prior=...)``
    (``spread_S0_rel`` -> ``tau_S0_rel``); None if none are stated."""
    return {"tau" + k[len("spread"):]: v for k, v in population_table.items()} or None


def _calibrate_to_file(module, datasheet, rig_config, seed, options, checkpoint, resume, done):
    """One module in a worker process: calibrate, write ``done``, return the
    diagnostics and the warnings raised (re-issued by the parent)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        r = calibrate_module(module, datasheet, rig_config=rig_config, seed=seed, options=options,
                             checkpoint=checkpoint, resume=resume)
    res.write_netcdf(res.to_inference_data([r]), done)
    return r.diagnostics, [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]


def _module_line(mid, d):
    return (f"    {mid}: {'converged' if d['converged'] else 'NOT converged'} in {d['steps']} steps "
            f"(R-hat {d['rhat_max']:.4f}, ESS {d['ess_bulk_min']:.0f}, k_hat {d['psis'][-1]['k_hat']:.2f}, "
            f"{d['timings']['total_s']:.0f} s)")


def calibrate_batch(batch, out, *, seed=0, options=None, resume=False, population=True, progress=None,
                    progress_bar=False, argv=None, figures=True, jobs=1):
    """Calibrate every module of a batch and the batch population.

    Parameters
    ----------
    batch : tembayes.data.Batch
        A loaded (hence validated) batch folder.
    out : str or Path
        The run folder (created).
    seed : int
        Run seed.
    options : CalibrationOptions, optional
    resume : bool
        Reuse finished modules and sampler checkpoints in ``out``.
    population : bool
        Fit the population (needs >= 2 modules).
    progress : callable, optional
        ``progress(message)``.
    progress_bar : bool
        Sampler progress bars.
    argv : list of str, optional
        The command line, recorded in the outputs.
    figures : bool
        Write the corner plots to ``RUN/figures``.
    jobs : int
        Modules calibrated at once, in worker processes (stage messages and
        progress bars only with 1); the results do not depend on it.

    Returns
    -------
    dict
        The summary (also written to ``RUN/summary.json``).
    """
    say = progress or (lambda msg: None)
    opt = options or CalibrationOptions()
    out = Path(out)
    (out / "modules").mkdir(parents=True, exist_ok=True)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    n = len(batch.modules)
    todo = []
    for i, (mid, module) in enumerate(batch.modules.items()):
        if resume and (out / "modules" / f"{mid}.nc").exists():
            say(f"[{i + 1}/{n}] {mid}: finished earlier, reused")
        else:
            todo.append((i, mid, module))
    if jobs > 1 and len(todo) > 1:
        # spawn, not fork: the compiled kernels' OpenMP runtime is not fork-safe
        ctx = multiprocessing.get_context("spawn")
        workers = min(jobs, len(todo))
        say(f"{len(todo)} modules in {workers} worker processes (per-module stage messages and bars off)")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as ex:
            futures = {ex.submit(_calibrate_to_file, module, batch.datasheet, batch.rig_config, seed, opt,
                                 out / "checkpoints" / mid, resume, out / "modules" / f"{mid}.nc"): (i, mid)
                       for i, mid, module in todo}
            for fut in as_completed(futures):
                i, mid = futures[fut]
                d, caught = fut.result()
                for msg in caught:
                    warnings.warn(msg, RuntimeWarning, stacklevel=2)
                say(f"[{i + 1}/{n}] {mid} done")
                say(_module_line(mid, d))
    else:
        for i, mid, module in todo:
            say(f"[{i + 1}/{n}] {mid}")
            r = calibrate_module(module, batch.datasheet, rig_config=batch.rig_config, seed=seed, options=opt,
                                 checkpoint=out / "checkpoints" / mid, resume=resume, progress=say,
                                 progress_bar=progress_bar)
            res.write_netcdf(res.to_inference_data([r]), out / "modules" / f"{mid}.nc")
            say(_module_line(mid, r.diagnostics))
    results = [res.read_module(out / "modules" / f"{mid}.nc") for mid in batch.modules]
    pop = None
    if population and len(results) >= 2:
        from tembayes.calibrate.population import fit_population

        say("population")
        draws = {r.module_id: r.law_draws() for r in results}
        _, rng = module_seed(seed, "__population__")
        pop = fit_population(draws, batch.datasheet, rng=rng, spread_prior=spread_prior(batch.population))
    elif population:
        say("population: skipped (a single module has no batch)")
    argv = list(argv) if argv is not None else None
    extra = {
        "batch": {"path": str(batch.path), "module_type": batch.datasheet.name, "n_modules": len(results)},
        # the spreads stated in batch.toml, and those learned here, in the
        # [population] table's format for the next batch of the type
        "population_prior": {k: {"median": m, "log_sd": sd} for k, (m, sd) in batch.population.items()},
        "population_spreads": None if pop is None else {
            "spread" + k[3:]: {"median": m, "log_sd": sd} for k, (m, sd) in pop.spread_prior().items()},
        "calibration": {
            "seed": int(seed), "rig": results[0].rig, "options": dict(opt.__dict__), "versions": _versions(),
            "command": None if argv is None else "tembayes " + " ".join(shlex.quote(a) for a in argv),
            "seconds": time.perf_counter() - t0,
        },
    }
    summ = res.summary(results, pop, extra=extra)
    idata = res.to_inference_data(results, population=pop, prior_draws=prior_draws(batch.datasheet, seed),
                                  attrs={"tembayes_seed": int(seed), "tembayes_versions": _versions(),
                                         "tembayes_command": extra["calibration"]["command"] or ""})
    res.write_netcdf(idata, out / "posterior.nc")
    write_json(out / "summary.json", summ)
    if figures:
        try:
            from tembayes.plots.calibrate import save_calibration_figures
        except ImportError:  # the plotting module arrives with its own change
            save_calibration_figures = None
        if save_calibration_figures is not None:
            say("figures")
            save_calibration_figures(out)
    return summ
