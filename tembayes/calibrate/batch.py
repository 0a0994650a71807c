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
import json
import math
import os
import shlex
import time
import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from tembayes.calibrate import results as res
from tembayes.calibrate.module import CalibrationOptions, module_seed
from tembayes.calibrate.moduledigest import read_digest, write_digest
from tembayes.calibrate.priors import law_log_prior, module_law_priors
from tembayes.calibrate.runfolder import RunFolder, module_matches, module_usable
from tembayes.calibrate.runsummary import RunSummary
from tembayes.common.provenance import versions
from tembayes.common.seeds import spawned
from tembayes.data.digest import batch_inputs
from tembayes.data.write import write_json
from tembayes.errors import DataError, ModelError
from tembayes.physics.effects import EFFECT_PARAMETERS

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from distributed import Client

    from tembayes.calibrate.priors import ParameterPrior
    from tembayes.data import Batch


def prior_draws(priors: Sequence[ParameterPrior], seed: int, n: int = 4000) -> dict[str, np.ndarray]:
    """Draws of the module parameters from their prior (:func:`~tembayes.calibrate.priors.module_law_priors`; plots)."""
    rng = np.random.default_rng(spawned(seed, 0x5052))
    return {p.name: p.sample(rng, n) for p in priors}


def spread_prior(population_table: Mapping[str, float]) -> dict[str, float] | None:
    """``batch.toml``'s ``[population]`` spreads as ``fit_population(spread_prior=...)``.

    ``spread_S0_rel`` becomes ``tau_S0_rel``; None if none are stated.
    """
    return {"tau" + k[len("spread") :]: v for k, v in population_table.items()} or None


def population_table(spreads: Mapping[str, tuple[float, float]]) -> str:
    """The learned spreads as a ``[population]`` table to paste into the next batch.toml of the type.

    The table states one log-sd for all its spreads: the largest learned, so
    that none is stated more precisely than it was learned.
    """
    lines = ["[population]"] + [f"spread{k[3:]} = {m:.4g}" for k, (m, _) in spreads.items()]
    sd = max(sd for _, sd in spreads.values())
    step = 10.0 ** (math.floor(math.log10(sd)) - 2)  # three significant digits, rounded up
    lines.append(f"spread_log_sd = {math.ceil(sd / step - 1e-9) * step:.3g}")
    return "\n".join(lines) + "\n"


def _merged_spreads(batch, earlier):
    """``[population]`` spreads from an earlier run and batch.toml (a spread given by both is refused)."""
    both = sorted(set(earlier or {}) & set(batch.population))
    if both:
        raise DataError(
            Path(batch.path) / "batch.toml",
            f"[population] states {', '.join(both)}, which --population-prior also gives",
            "Remove them from [population], or leave out --population-prior.",
            column="population",
        )
    return {**(earlier or {}), **batch.population}


def _module_line(mid, d):
    return (
        f"    {mid}: {'converged' if d.converged else 'NOT converged'} in {d.steps} steps "
        f"(R-hat {d.rhat_max:.4f}, ESS {d.ess_bulk_min:.0f}, k_hat {d.psis_k:.2f}, "
        f"{d.timings['total_s']:.0f} s)"
    )


def calibrate_batch(
    batch: Batch,
    out: Path | str,
    *,
    seed: int = 0,
    options: CalibrationOptions | None = None,
    resume: bool = False,
    overwrite: bool = False,
    population: bool = True,
    progress: Callable[[str], None] | None = None,
    progress_bar: bool = False,
    argv: Sequence[str] | None = None,
    workers: int = 1,
    scheduler: str | None = None,
    client: Client | None = None,
    keep_unconverged: bool = False,
    population_prior: Mapping[str, tuple[float, float]] | None = None,
) -> RunSummary:
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
    workers : int
        1: in this process, one module after the other (stage messages).
        More: a local Dask cluster of that many single-threaded processes.
        The results do not depend on it.
    scheduler : str, optional
        Address (or scheduler file) of a running ``dask.distributed``
        scheduler to use instead of a local cluster.
    client : distributed.Client, optional
        An open Dask client to use.
    keep_unconverged : bool
        Let modules that did not converge into the population stage.
    population_prior : mapping, optional
        ``spread_... -> (median, log_sd)``: spreads learned by an earlier run of
        the type (:func:`~tembayes.calibrate.earlier.population_prior_of_run`), combined with ``[population]``.

    Returns
    -------
    RunSummary
        ``RUN/summary.json``, typed.
    """
    say = progress or (lambda msg: None)
    workers = int(workers)
    _merged_spreads(batch, population_prior)  # a conflict is refused before anything is written
    opt = options or CalibrationOptions()
    law_prior = None if opt.law_prior is None else opt.law_prior.to_json()
    folder = RunFolder(
        out, batch=batch, seed=seed, resume=resume, overwrite=overwrite, workers=workers, progress=say,
        law_prior=law_prior,
    )  # fmt: skip
    with folder as work:
        summ = _calibrate_in(
            batch,
            work,
            folder.record(),
            seed=seed,
            options=opt,
            resume=resume,
            population=population,
            say=say,
            progress_bar=progress_bar,
            argv=argv,
            workers=workers,
            scheduler=scheduler,
            client=client,
            keep_unconverged=keep_unconverged,
            population_prior=population_prior,
        )
        folder.commit()
    return summ


def _calibrate_in(
    batch,
    out,
    record,
    *,
    seed,
    options,
    resume,
    population,
    say,
    progress_bar,
    argv,
    workers,
    scheduler,
    client,
    keep_unconverged,
    population_prior,
):
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
            say(
                f"[{order[mid] + 1}/{n}] {mid}: {nc} cannot be read (damaged?); kept as {nc.name}.damaged, "
                "calibrated again"
            )
        if resume and nc.exists() and not module_matches(nc, opt):
            nc.replace(nc.with_name(nc.name + ".stale"))
            say(
                f"[{order[mid] + 1}/{n}] {mid}: {nc} was calibrated with another --model or --discrepancy (or "
                f"before the runs kept the held values); kept as {nc.name}.stale, calibrated again"
            )
        if resume and nc.exists():
            say(f"[{order[mid] + 1}/{n}] {mid}: finished earlier, reused")
        else:
            todo.append(module)
    inline = client is None and scheduler is None and (workers <= 1 or len(todo) <= 1)
    where = (
        "in this process"
        if inline
        else f"on the Dask scheduler {scheduler}"
        if scheduler
        else "on the given Dask client"
        if client is not None
        else f"on {workers} local Dask workers"
    )
    if todo:
        say(f"{len(todo)} module(s) to calibrate {where}")
    done = 0
    for oc in calibrate_modules(
        todo,
        batch.datasheet,
        batch.rig_config,
        seed=seed,
        options=opt,
        checkpoints=out / "checkpoints",
        resume=resume,
        workers=workers,
        scheduler=scheduler,
        client=client,
        progress=say if inline else None,
        progress_bar=progress_bar and inline,
    ):
        done += 1
        for msg in oc.warnings:
            warnings.warn(msg, RuntimeWarning, stacklevel=2)
        failed = out / "modules" / f"{oc.module_id}.failed.json"
        head = f"[{order[oc.module_id] + 1}/{n}] {oc.module_id}"
        if oc.error is not None:
            write_json(failed, {"module": oc.module_id, "error": oc.error, "traceback": oc.detail})
            warnings.warn(
                f"{oc.module_id}: calibration failed ({oc.error}); the batch goes on without it (details in {failed})",
                RuntimeWarning,
                stacklevel=2,
            )
            say(f"{head}: FAILED ({oc.error})")
        else:
            nc = res.write_netcdf(res.to_inference_data([oc.result]), out / "modules" / f"{oc.module_id}.nc")
            write_digest(nc, oc.result)
            failed.unlink(missing_ok=True)
            # the module is safe on disk: its sampler checkpoints (up to ~20 MB) are not needed again
            for f in (out / "checkpoints").glob(f"{glob.escape(oc.module_id)}.*"):
                f.unlink(missing_ok=True)
            say(
                f"{head} done ({done}/{len(todo)} this run, {_eta(t0, done, len(todo))})\n"
                + _module_line(oc.module_id, oc.result.diagnostics)
            )
        oc.result = None  # written: not kept
    return finish_run(
        batch,
        out,
        seed=seed,
        options=opt,
        population=population,
        progress=say,
        argv=argv,
        keep_unconverged=keep_unconverged,
        population_prior=population_prior,
        seconds=time.perf_counter() - t0,
        executor={"where": where, "workers": workers, "scheduler": scheduler},
        batch_record=record,
    )


def _eta(t0, done, total):
    el = time.perf_counter() - t0
    left = el / done * (total - done)
    return f"{el / 60:.1f} min, about {left / 60:.1f} min left"


def finish_run(
    batch: Batch,
    out: Path | str,
    *,
    seed: int = 0,
    options: CalibrationOptions | None = None,
    population: bool = True,
    progress: Callable[[str], None] | None = None,
    argv: Sequence[str] | None = None,
    keep_unconverged: bool = False,
    seconds: float | None = None,
    executor: dict | None = None,
    batch_record: dict | None = None,
    population_prior: Mapping[str, tuple[float, float]] | None = None,
) -> RunSummary:
    """The batch stage of a run whose modules are in ``RUN/modules``.

    Reads the module files one at a time (their summary entries and thinned
    law draws), fits the population on the converged modules, writes
    ``summary.json`` and ``posterior.nc`` (all calibrated modules); the
    figures are drawn from the finished run folder by the caller
    (:func:`tembayes.plots.calibrate.save_calibration_figures`).
    ``batch_record`` (:meth:`RunFolder.record`: the batch's absolute path
    and the digests of its files) goes into ``summary.json``'s ``batch``;
    computed here when not given.

    Returns
    -------
    RunSummary
        ``summary.json``, typed.

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
        entries[mid], why, draws, r_rig = read_digest(f)
        rig = rig or r_rig
        files.append(f)
        if why and not keep_unconverged:
            excluded[mid] = why
        else:
            law[mid] = draws
    if not files:
        raise ModelError(
            f"no module of the batch {batch.path} could be calibrated: "
            + "; ".join(f"{m}: {e}" for m, e in failed.items())
        )
    for mid, why in failed.items():
        excluded[mid] = f"calibration failed: {why}"
    spreads = _merged_spreads(batch, population_prior)
    module_priors = module_law_priors(batch.datasheet, opt.law_prior)
    pop = None
    if population and len(law) >= 2:
        from tembayes.calibrate.population import fit_population

        say(
            f"population ({len(law)} modules"
            + (
                f"; left out: {', '.join(excluded)}"
                if excluded and len(excluded) <= 10
                else f"; {len(excluded)} left out"
                if excluded
                else ""
            )
            + ")"
        )
        _, rng = module_seed(seed, "__population__")
        pop = fit_population(
            law,
            batch.datasheet,
            rng=rng,
            spread_prior=spread_prior(spreads),
            log_interim_prior=law_log_prior(module_priors),  # the prior the modules were sampled under
        )
    elif population:
        say(f"population: skipped ({len(law)} module(s) to fit it on; it needs 2)")
    del law
    argv = list(argv) if argv is not None else None
    learned = None if pop is None else pop.spread_prior()
    extra = {
        "batch": {
            **(batch_record or {"path": os.path.abspath(batch.path), "inputs": batch_inputs(batch)}),
            "module_type": batch.datasheet.name,
            "n_modules": len(batch.modules),
            "n_calibrated": len(files),
        },
        # the spreads stated (batch.toml, an earlier run), and those learned
        # here, in the [population] table's format for the next batch of the type
        "population_prior": {k: {"median": m, "log_sd": sd} for k, (m, sd) in spreads.items()},
        "population_spreads": None
        if learned is None
        else {"spread" + k[3:]: {"median": m, "log_sd": sd} for k, (m, sd) in learned.items()},
        "population_table": None if learned is None else population_table(learned),
        "population_excluded": excluded,
        "failed_modules": failed,
        "calibration": {
            "seed": int(seed),
            "rig": rig,
            "options": opt.to_json(),
            "law_prior": "datasheet" if opt.law_prior is None else opt.law_prior.source,
            "versions": versions(),
            "model": opt.model,
            "discrepancy": opt.discrepancy,
            # the catalogue effects in the model: sampled, or at a fixed value
            # (docs/outputs.md, 'summary.json (calibrate)')
            "effects": sorted({*opt.effects, *(EFFECT_PARAMETERS[k] for k in opt.effect_values)}),
            "effect_values": dict(opt.effect_values),
            "command": None if argv is None else "tembayes " + " ".join(shlex.quote(a) for a in argv),
            "seconds": (seconds or 0.0) + time.perf_counter() - t0,
            "executor": executor,
        },
    }
    summ = res.summary([], pop, entries=entries, extra=extra)
    if failed:
        summ["converged"] = False
    say(f"posterior.nc ({len(files)} modules)")
    res.write_run_posterior(
        out / "posterior.nc",
        files,
        population=pop,
        prior_draws=prior_draws(module_priors, seed),
        attrs={
            "tembayes_seed": int(seed),
            "tembayes_versions": versions(),
            "tembayes_command": extra["calibration"]["command"] or "",
        },
        progress=say,
    )
    write_json(out / "summary.json", summ)
    return RunSummary.from_json(summ)
