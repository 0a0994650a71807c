"""Calibrate a batch: every module, then the population (``tembayes calibrate``).

Modules are independent (each has its own random stream from the run seed
and its id), so the batch is a loop over :func:`calibrate_module` whose
results are written to ``RUN/modules/<id>.nc`` as they finish; a resumed run
reuses finished modules and continues interrupted ones from their sampler
checkpoints.  The population stage
(:func:`tembayes.calibrate.population.fit_population`) reuses the modules'
posterior draws.
"""

from __future__ import annotations

import shlex
import sys
import time
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


def calibrate_batch(batch, out, *, seed=0, options=None, resume=False, population=True, progress=None,
                    progress_bar=False, argv=None, figures=True):
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
    results = []
    t0 = time.perf_counter()
    for i, (mid, module) in enumerate(batch.modules.items()):
        done = out / "modules" / f"{mid}.nc"
        if resume and done.exists():
            say(f"[{i + 1}/{len(batch.modules)}] {mid}: finished earlier, reused")
            results.append(res.read_module(done))
            continue
        say(f"[{i + 1}/{len(batch.modules)}] {mid}")
        r = calibrate_module(module, batch.datasheet, rig_config=batch.rig_config, seed=seed, options=opt,
                             checkpoint=out / "checkpoints" / mid, resume=resume, progress=say,
                             progress_bar=progress_bar)
        res.write_netcdf(res.to_inference_data([r]), done)
        d = r.diagnostics
        say(f"    {mid}: {'converged' if d['converged'] else 'NOT converged'} in {d['steps']} steps "
            f"(R-hat {d['rhat_max']:.4f}, ESS {d['ess_bulk_min']:.0f}, k_hat {d['psis'][-1]['k_hat']:.2f}, "
            f"{d['timings']['total_s']:.0f} s)")
        results.append(r)
    pop = None
    if population and len(results) >= 2:
        from tembayes.calibrate.population import fit_population

        say("population")
        draws = {r.module_id: r.law_draws() for r in results}
        _, rng = module_seed(seed, "__population__")
        pop = fit_population(draws, batch.datasheet, rng=rng)
    elif population:
        say("population: skipped (a single module has no batch)")
    argv = list(argv) if argv is not None else None
    extra = {
        "batch": {"path": str(batch.path), "module_type": batch.datasheet.name, "n_modules": len(results)},
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
