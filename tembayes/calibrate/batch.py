"""Calibrate a batch: every module, then the population (``tembayes calibrate``).

Modules are independent (each has its own random stream from the run seed
and its id), so the batch is a loop over
:func:`~tembayes.calibrate.module.calibrate_module` -- in this process, or on
a local or remote Dask cluster (:mod:`tembayes.calibrate.scaleout`), with
identical results -- whose results are written to ``RUN/modules/<id>.nc`` as
they finish; a resumed run reuses finished modules and continues interrupted
ones from their sampler checkpoints.  A module whose calibration fails is
recorded in ``RUN/modules/<id>.failed.json`` and the batch goes on (a resumed
run retries it).

:func:`finish_run` then reads the module files one at a time: their
``summary.json`` entries, and (evenly thinned) law draws of the converged ones
for the population stage
(:func:`tembayes.calibrate.population.fit_population`), under the spreads
``batch.toml``'s optional ``[population]`` table states; modules that did
not converge are left out of it, with the reason in ``summary.json``
(``population_excluded``).  ``posterior.nc`` is assembled from the module
files without holding them all (:func:`~tembayes.calibrate.results.write_run_posterior`),
so memory stays bounded for batches of thousands of modules.
"""

from __future__ import annotations

import glob
import io
import json
import os
import shlex
import sys
import time
import warnings
from pathlib import Path

import numpy as np

import tembayes
from tembayes.calibrate import results as res
from tembayes.calibrate import sampler as smp
from tembayes.calibrate.module import CalibrationOptions, module_seed
from tembayes.calibrate.priors import law_priors
from tembayes.calibrate.runfolder import RunFolder, module_usable
from tembayes.data.digest import batch_inputs
from tembayes.data.write import atomic_write_bytes, to_jsonable, write_json
from tembayes.errors import ModelError
from tembayes.physics.effects import EFFECT_PARAMETERS


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


def _module_line(mid, d):
    return (f"    {mid}: {'converged' if d['converged'] else 'NOT converged'} in {d['steps']} steps "
            f"(R-hat {d['rhat_max']:.4f}, ESS {d['ess_bulk_min']:.0f}, k_hat {d['psis'][-1]['k_hat']:.2f}, "
            f"{d['timings']['total_s']:.0f} s)")


#: Law draws per module (evenly thinned) handed to the population stage: its
#: Gaussian terms need the moments, its importance check 1000 draws at most;
#: 40 kB per module whatever the sampler kept.
POPULATION_DRAWS = 1000


def calibrate_batch(batch, out, *, seed=0, options=None, resume=False, overwrite=False, population=True,
                    progress=None, progress_bar=False, argv=None, figures=True, workers=1, scheduler=None,
                    client=None, jobs=None, keep_unconverged=False):
    """Calibrate every module of a batch and the batch population.

    Parameters
    ----------
    batch : tembayes.data.Batch
        A loaded (hence validated) batch folder; ``load_batch(path, lazy=True)``
        for large batches.
    out : str or Path
        The run folder.  It is built as ``out.partial`` and renamed to
        ``out`` when complete (:mod:`tembayes.calibrate.runfolder`): a
        failed or killed run leaves an existing ``out`` as it was.
    seed : int
        Run seed.
    options : CalibrationOptions, optional
    resume : bool
        Continue ``out.partial`` (or the finished ``out``): reuse finished
        modules and sampler checkpoints; modules that failed before, or whose
        file is damaged, are tried again.  Refused for another seed or a
        changed batch.
    overwrite : bool
        Replace an existing ``out`` (a calibration run holding nothing else)
        when the new run is complete.
    population : bool
        Fit the population (needs >= 2 converged modules).
    progress : callable, optional
        ``progress(message)``.
    progress_bar : bool
        Sampler progress bars (in-process only).
    argv : list of str, optional
        The command line, recorded in the outputs.
    figures : bool
        Write the corner plots to ``RUN/figures``.
    workers : int
        1: in this process, one module after the other (stage messages).
        More: a local Dask cluster of that many single-threaded processes.
        The results do not depend on it.
    scheduler : str, optional
        Address (or scheduler file) of a running ``dask.distributed``
        scheduler to use instead of a local cluster.
    client : distributed.Client, optional
        An open Dask client to use.
    jobs : int, optional
        Old name of ``workers``.
    keep_unconverged : bool
        Let modules that did not converge into the population stage.

    Returns
    -------
    dict
        The summary (also written to ``RUN/summary.json``).
    """
    say = progress or (lambda msg: None)
    workers = int(jobs if jobs is not None else workers)
    folder = RunFolder(out, batch=batch, seed=seed, resume=resume, overwrite=overwrite, workers=workers,
                       progress=say)
    with folder as work:
        summ = _calibrate_in(batch, work, folder.record(), seed=seed, options=options or CalibrationOptions(),
                             resume=resume, population=population, say=say, progress_bar=progress_bar, argv=argv,
                             figures=figures, workers=workers, scheduler=scheduler, client=client,
                             keep_unconverged=keep_unconverged)
        folder.commit()
    return summ


def _calibrate_in(batch, out, record, *, seed, options, resume, population, say, progress_bar, argv, figures,
                  workers, scheduler, client, keep_unconverged):
    """:func:`calibrate_batch` inside the run folder being built (``out``)."""
    from tembayes.calibrate.scaleout import calibrate_modules

    opt = options
    (out / "modules").mkdir(parents=True, exist_ok=True)
    (out / "checkpoints").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    n = len(batch.modules)
    order = {mid: i for i, mid in enumerate(batch.modules)}
    todo = []
    for mid, module in batch.modules.items():
        nc = out / "modules" / f"{mid}.nc"
        if resume and nc.exists() and not module_usable(nc):
            nc.replace(nc.with_name(nc.name + ".damaged"))
            say(f"[{order[mid] + 1}/{n}] {mid}: {nc} cannot be read (damaged?); kept as {nc.name}.damaged, "
                "calibrated again")
        if resume and nc.exists():
            say(f"[{order[mid] + 1}/{n}] {mid}: finished earlier, reused")
        else:
            todo.append(module)
    inline = client is None and scheduler is None and (workers <= 1 or len(todo) <= 1)
    where = ("in this process" if inline else
             f"on the Dask scheduler {scheduler}" if scheduler else
             "on the given Dask client" if client is not None else f"on {workers} local Dask workers")
    if todo:
        say(f"{len(todo)} module(s) to calibrate {where}")
    done = 0
    for oc in calibrate_modules(todo, batch.datasheet, batch.rig_config, seed=seed, options=opt,
                                checkpoints=out / "checkpoints", resume=resume, workers=workers,
                                scheduler=scheduler, client=client, progress=say if inline else None,
                                progress_bar=progress_bar and inline):
        done += 1
        for msg in oc.warnings:
            warnings.warn(msg, RuntimeWarning, stacklevel=2)
        failed = out / "modules" / f"{oc.module_id}.failed.json"
        head = f"[{order[oc.module_id] + 1}/{n}] {oc.module_id}"
        if oc.error is not None:
            write_json(failed, {"module": oc.module_id, "error": oc.error, "traceback": oc.detail})
            warnings.warn(f"{oc.module_id}: calibration failed ({oc.error}); the batch goes on without it "
                          f"(details in {failed})", RuntimeWarning, stacklevel=2)
            say(f"{head}: FAILED ({oc.error})")
        else:
            nc = res.write_netcdf(res.to_inference_data([oc.result]), out / "modules" / f"{oc.module_id}.nc")
            write_digest(nc, oc.result)
            failed.unlink(missing_ok=True)
            # the module is safe on disk: its sampler checkpoints (up to ~20 MB) are not needed again
            for f in (out / "checkpoints").glob(f"{glob.escape(oc.module_id)}.*"):
                f.unlink(missing_ok=True)
            say(f"{head} done ({done}/{len(todo)} this run, {_eta(t0, done, len(todo))})\n"
                + _module_line(oc.module_id, oc.result.diagnostics))
        oc.result = None  # written: not kept
    return finish_run(batch, out, seed=seed, options=opt, population=population, progress=say, argv=argv,
                      figures=figures, keep_unconverged=keep_unconverged, seconds=time.perf_counter() - t0,
                      executor={"where": where, "workers": workers, "scheduler": scheduler}, batch_record=record)


def _eta(t0, done, total):
    el = time.perf_counter() - t0
    left = el / done * (total - done)
    return f"{el / 60:.1f} min, about {left / 60:.1f} min left"


def exclusion_reason(diagnostics):
    """Why a module is left out of the population (None: it is not).

    A module enters the population only if it converged: the sampler's
    targets (R-hat, bulk ESS, chain length in autocorrelation times) and the
    expansion's PSIS check.
    """
    d = diagnostics
    if d.get("converged"):
        return None
    bits = []
    if d.get("rhat_max") is not None and d["rhat_max"] > smp.RHAT_MAX:
        bits.append(f"R-hat {d['rhat_max']:.3f} > {smp.RHAT_MAX}")
    if d.get("ess_bulk_min") is not None and d["ess_bulk_min"] < smp.ESS_MIN:
        bits.append(f"bulk ESS {d['ess_bulk_min']:.0f} < {smp.ESS_MIN:.0f}")
    if d.get("chain_over_tau") is not None and d["chain_over_tau"] < smp.MIN_TAU_MULTIPLE:
        bits.append(f"chain {d['chain_over_tau']:.0f} autocorrelation times < {smp.MIN_TAU_MULTIPLE:.0f}")
    k = (d.get("psis") or [{}])[-1].get("k_hat")
    if k is not None and k >= 0.7:
        bits.append(f"expansion PSIS k_hat {k:.2f} >= 0.7")
    return "not converged" + (f" ({', '.join(bits)})" if bits else "") + \
        f" after {d.get('steps', '?')} steps; rerun with a larger --max-steps, or --keep-unconverged"


def _thin(x, n):
    return x if len(x) <= n else x[np.linspace(0, len(x) - 1, n).round().astype(int)]


def _digest_path(nc):
    return nc.with_name(nc.stem + ".digest.npz")


def write_digest(nc, r):
    """What the batch stage needs of a module, next to its file: its summary entry, the reason it
    would be left out of the population, its thinned law draws (reading the ``.nc`` back through
    arviz costs ~0.3 s a module, 50 min for 10^4)."""
    entry, why, law, rig = _digest_of(r)
    st = nc.stat()
    buf = io.BytesIO()
    np.savez(buf, entry=json.dumps(to_jsonable(entry)), why=why or "", law=law, rig=rig,
             source=np.array([st.st_size, st.st_mtime_ns]))
    atomic_write_bytes(_digest_path(nc), buf.getvalue())


def _digest_of(r):
    """``(summary entry, exclusion reason or None, thinned law draws, rig name)`` of a module."""
    return res.module_entry(r), exclusion_reason(r.diagnostics), _thin(r.law_draws(), POPULATION_DRAWS), r.rig


def digest_matches(nc) -> bool:
    """Whether the module file ``nc`` is the one its digest was written for (same size and time)."""
    d = _digest_path(Path(nc))
    if not d.exists():
        return False
    st = Path(nc).stat()
    try:
        with np.load(d) as z:
            return list(z["source"]) == [st.st_size, st.st_mtime_ns]
    except (OSError, ValueError, KeyError):
        return False


def _read_digest(nc):
    """``(entry, why, law, rig)`` of a module file: from its digest if it is the file's, else from the file."""
    if digest_matches(nc):
        with np.load(_digest_path(nc)) as z:
            return json.loads(str(z["entry"])), str(z["why"]) or None, z["law"].copy(), str(z["rig"])
    return _digest_of(res.read_module(nc))  # an older run, or a module file replaced since


def finish_run(batch, out, *, seed=0, options=None, population=True, progress=None, argv=None, figures=True,
               keep_unconverged=False, seconds=None, executor=None, batch_record=None):
    """The batch stage of a run whose modules are in ``RUN/modules``.

    Reads the module files one at a time (their summary entries and thinned
    law draws), fits the population on the converged modules, writes
    ``summary.json``, ``posterior.nc`` (all calibrated modules) and the figures.
    ``batch_record`` (:meth:`RunFolder.record`: the batch's absolute path
    and the digests of its files) goes into ``summary.json``'s ``batch``;
    computed here when not given.

    Returns
    -------
    dict
        The summary.

    Raises
    ------
    ModelError
        No module of the batch has a result.
    """
    say = progress or (lambda msg: None)
    opt = options or CalibrationOptions()
    out = Path(out)
    t0 = time.perf_counter()
    entries, law, excluded, failed, files, rig = {}, {}, {}, {}, [], None
    for mid in batch.modules:
        f = out / "modules" / f"{mid}.nc"
        if not f.exists():
            rec = out / "modules" / f"{mid}.failed.json"
            failed[mid] = (json.loads(rec.read_text()).get("error") if rec.exists() else None) or "no result"
            continue
        entries[mid], why, draws, r_rig = _read_digest(f)
        rig = rig or r_rig
        files.append(f)
        if why and not keep_unconverged:
            excluded[mid] = why
        else:
            law[mid] = draws
    if not files:
        raise ModelError(f"no module of the batch {batch.path} could be calibrated: "
                         + "; ".join(f"{m}: {e}" for m, e in failed.items()))
    for mid, why in failed.items():
        excluded[mid] = f"calibration failed: {why}"
    pop = None
    if population and len(law) >= 2:
        from tembayes.calibrate.population import fit_population

        say(f"population ({len(law)} modules"
            + (f"; left out: {', '.join(excluded)}" if excluded and len(excluded) <= 10 else
               f"; {len(excluded)} left out" if excluded else "") + ")")
        _, rng = module_seed(seed, "__population__")
        pop = fit_population(law, batch.datasheet, rng=rng, spread_prior=spread_prior(batch.population))
    elif population:
        say(f"population: skipped ({len(law)} module(s) to fit it on; it needs 2)")
    del law
    argv = list(argv) if argv is not None else None
    extra = {
        "batch": {**(batch_record or {"path": os.path.abspath(batch.path), "inputs": batch_inputs(batch)}),
                  "module_type": batch.datasheet.name, "n_modules": len(batch.modules), "n_calibrated": len(files)},
        # the spreads stated in batch.toml, and those learned here, in the
        # [population] table's format for the next batch of the type
        "population_prior": {k: {"median": m, "log_sd": sd} for k, (m, sd) in batch.population.items()},
        "population_spreads": None if pop is None else {
            "spread" + k[3:]: {"median": m, "log_sd": sd} for k, (m, sd) in pop.spread_prior().items()},
        "population_excluded": excluded,
        "failed_modules": failed,
        "calibration": {
            "seed": int(seed), "rig": rig, "options": dict(opt.__dict__), "versions": _versions(),
            "model": opt.model,
            "discrepancy": opt.discrepancy,
            # the catalogue effects in the model: sampled, or at a fixed value
            # (docs/outputs.md, 'summary.json (calibrate)')
            "effects": sorted({*opt.effects, *(EFFECT_PARAMETERS[k] for k in opt.effect_values)}),
            "effect_values": dict(opt.effect_values),
            "command": None if argv is None else "tembayes " + " ".join(shlex.quote(a) for a in argv),
            "seconds": (seconds or 0.0) + time.perf_counter() - t0, "executor": executor,
        },
    }
    summ = res.summary([], pop, entries=entries, extra=extra)
    if failed:
        summ["converged"] = False
    say(f"posterior.nc ({len(files)} modules)")
    res.write_run_posterior(out / "posterior.nc", files, population=pop, prior_draws=prior_draws(batch.datasheet, seed),
                            attrs={"tembayes_seed": int(seed), "tembayes_versions": _versions(),
                                   "tembayes_command": extra["calibration"]["command"] or ""},
                            progress=say)
    write_json(out / "summary.json", summ)
    if figures:
        from tembayes.plots.calibrate import save_calibration_figures

        say("figures")
        save_calibration_figures(out)
    return summ
