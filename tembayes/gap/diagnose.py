"""The whole diagnosis: where, which effect, how far the gap shrinks (``tembayes gap``).

For every calibrated module with held-out runs (``validation*.csv``):

1. **Where** -- the base posterior's predictive of each held-out run, its
   bands made of the parameter uncertainty and the run's *measurement noise*
   (white, its level read off the run itself: :func:`sensor_noise`), and the
   gap map of :mod:`~tembayes.gap.where`.  The predictive of ``tembayes
   predict`` carries the identification run's misfit in its bands (honest
   bands for a user); the diagnosis must not, or a misfit would hide itself.
2. **Which** -- the linear screen of :mod:`~tembayes.gap.which` on every
   held-out run, summed over runs and modules, and the rig parameters whose
   posterior sits outside the documented range (:data:`SUSPECTS` maps them to
   the effects they can stand for).
3. **How far** -- the strongest candidates are *recalibrated*: each module's
   identification run sampled again with the effect's parameters added
   (:func:`~tembayes.calibrate.module.calibrate_module` with ``effects``),
   anchored, and predicted on the held-out runs.  Their held-out evidence is
   the block-wise ELPD (below) against the base model's, the gap is
   :data:`GAP_METRIC` before and after.  On a batch the candidates *race*:
   each is recalibrated first on the module with the largest gap, and only
   those that gain held-out evidence there are recalibrated on the others
   (the rest are reported with their evidence on that module, ``dropped``).

Held-out evidence.  Each model predicts a held-out run with its own residual
process (the Ornstein-Uhlenbeck model fitted on its identification run);
the log density of a block of :data:`BLOCK_S` seconds is the innovation
(one-step-ahead) log density of the block's residuals summed over channels
and samples, averaged over the posterior draws on the probability scale
(``log mean_s exp``).  Blocks are nearly independent where samples are not
(residuals correlate over minutes), so the ELPD's standard error -- and the
paired difference's, ``se = sqrt(n_blocks var(delta_b))`` -- come from the
blocks, as the LOO literature does for pointwise terms (Vehtari et al. 2017).

Verdict (the best-ranked candidate ``b``):

- ``no_gap``: no cell of any gap map is significant (:data:`ALPHA`,
  Bonferroni over cells and maps); nothing is recalibrated;
- ``explained``: ``b`` improves the ELPD by more than :data:`EVIDENCE_Z`
  standard errors, shrinks the gap by :data:`EXPLAINED_SHRINK` or more, and
  leaves no significant cell;
- ``partially_explained``: ``b`` improves the ELPD significantly and shrinks
  the gap by :data:`PARTIAL_SHRINK` or more;
- ``unexplained``: otherwise (nothing in the catalogue helps).

Candidates whose ELPD differs from the best's by less than ``EVIDENCE_Z``
paired standard errors are one group: the data cannot tell them apart, and
the report says so (``best_group``).
"""

from __future__ import annotations

import multiprocessing
import time as _time
import warnings
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.special import logsumexp

from tembayes.constants import MODULE_PARAMETERS
from tembayes.data.quality import noise_estimate
from tembayes.errors import DataError
from tembayes.gap.conflicts import range_conflicts
from tembayes.gap.where import gap_map
from tembayes.gap.which import screen_effects
from tembayes.physics import effects as E
from tembayes.predict.anchor import ResidualProcess
from tembayes.predict.predictive import (PredictiveDraws, module_raw_draws, posterior_draws, simulate_predictive,
                                         subsample)
from tembayes.predict.runmodel import CHANNELS, RunModel

#: The held-out gap, one unit for every effect (contract section 4).
GAP_METRIC = ("excess RMSE [K] over T1..T4: sqrt(max(0, mean (y - predictive mean)^2 - mean predictive variance)), "
              "the predictive variance being the draws' spread plus the measurement noise; pooled over every "
              "held-out run of every module.  0 when the error is what the model's own uncertainty says")
#: Length of the blocks of the held-out ELPD [s].
BLOCK_S = 300.0
#: Candidates recalibrated (the screen's best; range conflicts may add one).
CANDIDATES = 2
#: Family-wise level of the gap map's cells.
ALPHA = 0.05
#: Least score (RMS standardised residual) of a gap-map cell that counts as a
#: gap: with ~10^4 samples a run's cells are significant a few per cent
#: beyond the band.  Measured on bench runs: correctly specified, the idle
#: stretches (|I| ~ 0, where the run's unknown start-up state shows) score
#: 1.1-1.2; with the true effect recalibrated 1.5-1.7; an effect's gap scores
#: 5-40.  A gap is a residual twice what the band says.
SCORE_MIN = 2.0
#: Standard errors of the ELPD difference that count as evidence.
EVIDENCE_Z = 2.0
#: Shrink of the gap that makes an effect the explanation / a partial one.
EXPLAINED_SHRINK = 0.5
PARTIAL_SHRINK = 0.2
#: Sampler budget of a recalibration [steps]: a candidate's posterior need
#: not be reported to R-hat 1.01 to predict the held-out runs (measured: a
#: correct candidate converges within it; a wrong one does not, and its
#: held-out evidence says so).
RECAL_MAX_STEPS = 20000
#: Predictive draws per held-out run.
N_DRAWS = 200

#: A rig parameter calibrated beyond its documented range (``high`` or
#: ``low``) and the effects it can stand for: an extra leak absorbs more heat
#: exchange with ambient; a plate capacitance the size of a block absorbs a
#: sensor lag or a contact resistance (both delay the blocks' response); a
#: paste conductance below any paste absorbs a contact resistance.
SUSPECTS = {
    ("leak_top", "high"): ("ambient_leak",),
    ("leak_bottom", "high"): ("ambient_leak",),
    ("c_plate_hot", "high"): ("sensor_lag", "contact_resistance"),
    ("c_plate_cold", "high"): ("sensor_lag", "contact_resistance"),
    ("g_paste_hot", "low"): ("contact_resistance",),
    ("g_paste_cold", "low"): ("contact_resistance",),
}


def sensor_noise(exp):
    """White measurement noise of each channel of an experiment, ``(5,)`` (K, V).

    Read off the run (:func:`~tembayes.data.quality.noise_estimate`: second
    differences, robust), so a model's misfit never enters it.
    """
    ys = [np.asarray(exp.sensors[c], float) for c in range(4)] + [np.asarray(exp.voltage, float)]
    sd = np.array([noise_estimate(y) for y in ys])
    return np.where(np.isfinite(sd) & (sd > 0), sd, 1e-4)


def _with_noise(draws, sd):
    """The draws with white noise ``sd`` ``(5,)`` instead of their residual processes."""
    return PredictiveDraws(params=draws.params, noise_sd=np.repeat(np.asarray(sd, float)[None], draws.n, axis=0),
                           label=draws.label, laws=draws.laws, anchor=draws.anchor,
                           noise_tau=np.zeros((draws.n, len(CHANNELS))))


def block_log_density(Y, measured, t, sd, tau, block_s=BLOCK_S):
    """Innovation log density of the residuals per draw and block.

    Parameters
    ----------
    Y : ndarray, shape (M, 5, n)
        The draws' noise-free predictions (SI).
    measured : ndarray, shape (5, n)
    t : ndarray, shape (n,)
        [s].
    sd, tau : ndarray, shape (5,)
        The model's residual process per channel (stationary sd, correlation time [s]).
    block_s : float

    Returns
    -------
    ndarray, shape (M, n_blocks)
    """
    dt = np.diff(t)
    blocks = np.floor((t - t[0]) / block_s).astype(int)
    nb = blocks[-1] + 1
    M = Y.shape[0]
    L = np.zeros((M, nb))
    for c in range(Y.shape[1]):
        r = measured[c][None] - Y[:, c]
        phi = np.exp(-dt / max(tau[c], 1e-9))
        q = np.maximum(1.0 - phi * phi, 1e-12) * sd[c] ** 2
        innov = np.concatenate([r[:, :1], r[:, 1:] - phi[None] * r[:, :-1]], axis=1)
        var = np.concatenate([[sd[c] ** 2], q])
        ll = -0.5 * (innov * innov / var[None] + np.log(2.0 * np.pi * var)[None])
        np.add.at(L.T, blocks, ll.T)
    return L


def heldout_elpd(L):
    """Block ELPDs ``(n_blocks,)`` from per-draw block log densities ``(M, n_blocks)``."""
    return logsumexp(L, axis=0) - np.log(L.shape[0])


@dataclass
class RunEvaluation:
    """A model's predictive of one held-out run (the summary the diagnosis keeps).

    Attributes
    ----------
    module_id, source : str
    sse, n : float, int
        Sum of squared errors over T1..T4 [K^2] and its sample count.
    expected : float
        Its expectation under the predictive (draws' variance plus noise) [K^2].
    elpd_blocks : ndarray
        Block ELPDs (see :func:`block_log_density`).
    significant : list of dict
        The gap map's significant cells (``alpha`` already split over the maps).
    gap_map : GapMap
    prediction : Prediction or None
        Kept for the base model (figures).
    """

    module_id: str
    source: str
    sse: float
    n: int
    expected: float
    elpd_blocks: np.ndarray
    significant: list
    gap_map: object
    prediction: object = None


def evaluate_run(model, draws, rng_draws, rng_run, *, n_draws=N_DRAWS, alpha=ALPHA, keep_prediction=False):
    """Predict one held-out run with a model's draws and score it.

    Parameters
    ----------
    model : RunModel
    draws : PredictiveDraws
    rng_draws : numpy.random.Generator
        Picks the draws.
    rng_run : numpy.random.Generator
        The run's step phases, noise and replicates: seeded by the run alone,
        so every model compared on it sees the same ones (common random
        numbers: their differences are the models', not the Monte Carlo's).
    n_draws : int
    alpha : float
        Level of each gap-map cell test (already divided by the number of maps).
    keep_prediction : bool

    Returns
    -------
    RunEvaluation
    """
    sub = subsample(draws, rng_draws, n_draws)
    noise = sensor_noise(model.exp)
    pred = simulate_predictive(model, _with_noise(sub, noise), rng_run, keep_draws=True)
    gm = gap_map(pred, rng_run)
    Y = pred.mean[None] + pred.deviations
    # every model is scored with the run's own measurement noise (white): the
    # evidence compares what the models predict, not how much misfit each
    # one learnt to expect on its identification run
    L = block_log_density(Y, pred.measured, pred.time, noise, np.full(len(noise), 1e-9))
    r = pred.residual[:4]
    expected = float(np.sum(pred.deviations[:, :4].astype(float).var(axis=0) + noise[:4, None] ** 2))
    return RunEvaluation(module_id=draws.label, source=str(model.exp.path), sse=float(np.sum(r * r)),
                         n=int(r.size), expected=expected, elpd_blocks=heldout_elpd(L), significant=material(gm.significant(alpha)),
                         gap_map=gm, prediction=pred if keep_prediction else None)


def material(cells, score_min=None):
    """The cells whose score exceeds :data:`SCORE_MIN` (significant *and* large enough to matter)."""
    s = SCORE_MIN if score_min is None else score_min
    return [c for c in cells if c["score"] > s]


def _rmse(evals):
    """Plain RMSE over T1..T4 [K] of the predictive mean, pooled."""
    return float(np.sqrt(sum(e.sse for e in evals) / max(sum(e.n for e in evals), 1)))


def held_out_gap(evals):
    """:data:`GAP_METRIC` of a model's evaluations [K]."""
    excess = sum(e.sse - e.expected for e in evals) / max(sum(e.n for e in evals), 1)
    return float(np.sqrt(max(excess, 0.0)))


def _block_se(d):
    """Standard error of a sum of block terms ``d`` (the blocks nearly independent) [nats]."""
    return float(np.sqrt(len(d)) * np.std(d))


def _seed(seed, *keys):
    return np.random.default_rng([int(seed), *(zlib.crc32(str(k).encode()) for k in keys)])


def _candidate_job(module, datasheet, rig_config, leg_cells, block_cells, effect, seed, options, n_draws, alpha,
                   start):
    """One module recalibrated with ``effect`` and scored on its held-out runs (a worker's job).

    A recalibration whose model fails (the effect drives the rig somewhere
    it cannot be simulated) is a candidate that does not help: it comes back
    with ``"failed"`` and the reason, not as an exception.
    """
    from threadpoolctl import threadpool_limits

    from tembayes.calibrate.module import calibrate_module
    from tembayes.errors import TembayesError
    from tembayes.physics.rig import rig_from_config

    t0 = _time.perf_counter()
    rig = rig_from_config(rig_config, leg_cells, block_cells)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            cal = calibrate_module(module, datasheet, rig_config=rig_config, seed=seed, options=options,
                                   effects=(effect,), start=start)
            raw = {k: np.asarray(v).ravel() for k, v in cal.draws.items()}
            with threadpool_limits(limits=1, user_api="blas"):
                draws = posterior_draws(raw, cal.priors, module.id, module.identification, rig)
                evals = [evaluate_run(RunModel(exp, rig), draws, _seed(seed, module.id, effect, exp.path),
                                      _seed(seed, module.id, exp.path), n_draws=n_draws, alpha=alpha)
                         for exp in module.validations]
        except TembayesError as err:
            return {"module": module.id, "effect": effect, "failed": str(err), "seconds": _time.perf_counter() - t0,
                    "warnings": [], "converged": False}
    for e in evals:
        e.gap_map = None  # not needed back in the parent
    conflicting = [r["parameter"] for r in range_conflicts(raw, rig) if r["conflict"]]
    size = {}
    for p in E.get(effect).parameters:
        x = np.asarray(draws.params[p.name], float)
        size[p.name] = {"median": float(np.median(x)), "q05": float(np.quantile(x, 0.05)),
                        "q95": float(np.quantile(x, 0.95)), "unit": p.unit}
    return {"module": module.id, "effect": effect, "evals": evals, "size": size,
            "converged": bool(cal.diagnostics["converged"]), "seconds": _time.perf_counter() - t0, "failed": None,
            "conflicts": conflicting,
            "warnings": [str(w.message) for w in caught]}


def _race(first, follow, job, jobs, cache, say, work=_candidate_job):
    """Run the recalibrations ``first`` and, as each finishes, those ``follow(result)`` asks for (first).

    ``first`` and ``follow``'s return are lists of ``(module_id, effect)``;
    ``work(*job(module_id, effect))`` is one recalibration (a picklable
    top-level function with ``jobs > 1``).  Results already in
    ``cache`` (a dict keyed by ``(module_id, effect)``) are not run again;
    new ones are added to it.  Returns ``{(module_id, effect): result}``.
    """
    from concurrent.futures import FIRST_COMPLETED, wait

    out, pending = {}, list(first)
    queued = set(first)

    def record(key, r):
        out[key] = r
        if cache is not None:
            cache[key] = r
        say(f"  recalibrated {key[0]} with {key[1]} ({len(out)} done, {r['seconds']:.0f} s)")
        new = [k for k in follow(r) if k not in queued]
        queued.update(new)
        pending[:0] = new  # a candidate carried on goes first: it is the one likely to be reported

    if jobs <= 1:
        while pending:
            key = pending.pop(0)
            record(key, cache[key] if cache is not None and key in cache else work(*job(*key)))
        return out
    ctx = multiprocessing.get_context("spawn")  # the compiled kernels' OpenMP runtime is not fork-safe
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx) as ex:
        running = {}
        while pending or running:
            while pending and len(running) < jobs:  # submit no further ahead: carried jobs jump the queue
                key = pending.pop(0)
                if cache is not None and key in cache:
                    record(key, cache[key])
                else:
                    running[ex.submit(work, *job(*key))] = key
            if running:
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for f in finished:
                    record(running.pop(f), f.result())
    return out


@dataclass(frozen=True)
class GapDiagnosis:
    """Result of :func:`diagnose` (a plain result object; ``to_json`` is ``gap.json``).

    Attributes
    ----------
    verdict : str
    where : list of dict
        Significant gap-map cells of the base model, worst first:
        ``{"channel", "regime", "score", "module", "run", "p"}``.
    ranking : list of dict
        Recalibrated candidates, best first: ``{"effect", "evidence",
        "evidence_se", "gap_before", "gap_after", "shrink", "size",
        "remaining_cells", "converged"}`` (evidence: held-out ELPD difference
        to the base model [nats]); without a gap the screen's ranking.
    best : str or None
    best_group : list of str
        The candidates the data cannot tell from the best.
    screen : list of dict
        The linear screen summed over the held-out runs, best first.
    conflicts : dict
        Module -> rig parameters outside their documented range.
    suspects : list of str
        Effects the conflicts point at.
    base : dict
        The base model's held-out gap, ELPD and residual tests per run.
    excluded : list of str
        Effects withheld from the diagnosis.
    seconds : float
    seed : int
    evaluations : dict
        ``"base"`` -> list of RunEvaluation (with the predictions, for figures).
    """

    verdict: str
    where: list
    ranking: list
    best: str | None
    best_group: list
    screen: list
    conflicts: dict
    suspects: list
    base: dict
    excluded: list
    seconds: float
    seed: int
    evaluations: dict

    def to_json(self):
        """``gap.json``: the contract's keys and the diagnosis's details."""
        return {
            "verdict": self.verdict,
            "where": self.where,
            "ranking": self.ranking,
            "best": self.best,
            "best_group": self.best_group,
            "metric": GAP_METRIC,
            "evidence": "held-out block ELPD difference to the base model [nats], blocks of "
                        f"{BLOCK_S:.0f} s; evidence_se from the blocks",
            "screen": self.screen,
            "conflicts": self.conflicts,
            "suspects": self.suspects,
            "base": self.base,
            "excluded": self.excluded,
            "settings": {"alpha": ALPHA, "evidence_z": EVIDENCE_Z, "explained_shrink": EXPLAINED_SHRINK,
                         "partial_shrink": PARTIAL_SHRINK, "block_s": BLOCK_S},
            "seed": self.seed,
            "seconds": self.seconds,
        }


def _where(evals):
    out = []
    for e in evals:
        for c in e.significant:
            out.append({"channel": c["channel"], "regime": f"{c['family']}: {c['regime']}", "score": c["score"],
                        "module": e.module_id, "run": Path(e.source).name, "p": c["p"],
                        "outside90": c["outside90"]})
    return sorted(out, key=lambda c: -c["score"])


def _parameter_gaps(conflicts):
    out = []
    for mid, rows in conflicts.items():
        for r in rows:
            if r["conflict"]:
                out.append({"channel": r["parameter"], "kind": "parameter", "module": mid,
                            "regime": f"calibrated {r['median']:.4g} {r['unit']}, documented range "
                                      f"{r['low']:.4g}-{r['high']:.4g} {r['unit']}",
                            "score": r["outside_sd"]})
    return sorted(out, key=lambda c: -c["score"])


def _suspects(conflicts, allowed):
    out = []
    for rows in conflicts.values():
        for r in rows:
            if not r["conflict"]:
                continue
            side = "high" if r["median"] > r["high"] else "low"
            for e in SUSPECTS.get((r["parameter"], side), ()):
                if e in allowed and e not in out:
                    out.append(e)
    return out


def diagnose(run, batch, *, exclude=(), candidates=CANDIDATES, n_draws=N_DRAWS, seed=0, options=None, jobs=2,
             progress=None, cache=None):
    """Diagnose the sim-to-real gap of a calibrated batch on its held-out runs.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
        The base calibration.
    batch : tembayes.data.Batch
        The calibrated batch; its ``validation*.csv`` runs are the held-out data.
    exclude : sequence of str
        Effects withheld from the diagnosis (it neither screens nor names them).
    candidates : int
        Candidates recalibrated.
    n_draws : int
        Predictive draws per held-out run.
    seed : int
    options : CalibrationOptions, optional
        For the recalibrations (default the run's own, the budget cut to
        :data:`RECAL_MAX_STEPS`).
    jobs : int
        Recalibrations at once, in worker processes.
    progress : callable, optional
    cache : dict, optional
        Recalibrations kept between calls on the same run, batch, seed and
        settings, keyed by ``(module_id, effect)``: a diagnosis with an effect
        withheld reuses the other candidates' (filled in place).

    Returns
    -------
    GapDiagnosis
    """
    from tembayes.calibrate.module import CalibrationOptions

    t_start = _time.perf_counter()
    say = progress or (lambda msg: None)
    unknown = [e for e in exclude if e not in E.CATALOGUE]
    if unknown:
        raise DataError("--exclude", f"names no catalogue effect: {unknown}", f"Choose from {list(E.CATALOGUE)}.")
    allowed = [e for e in E.CATALOGUE if e not in set(exclude)]
    rig = run.rig_for(batch)
    ids = [m for m in run.module_ids if batch.modules[m].validations]
    if not ids:
        raise DataError(batch.path, "has no validation*.csv in any module folder",
                        "The diagnosis needs held-out runs: add at least one validation experiment per module.")
    opts = run.options()
    leg, blk = opts.get("leg_cells", 4), opts.get("block_cells", 6)
    if options is None:
        known = CalibrationOptions.__dataclass_fields__
        options = CalibrationOptions(**{k: v for k, v in opts.items() if k in known})
        options = replace(options, max_steps=min(options.max_steps, RECAL_MAX_STEPS),
                          stage_steps=min(options.stage_steps, RECAL_MAX_STEPS))
    n_maps = sum(len(batch.modules[m].validations) for m in ids)
    alpha = ALPHA / n_maps

    # 1-2. the base model: predictive, gap map, screen, range conflicts
    base_evals, screen_sum, screen_rows, conflicts, starts = [], {}, {}, {}, {}
    for mid in ids:
        module = batch.modules[mid]
        say(f"{mid}: base model, anchoring on the identification run")
        raw = module_raw_draws(run, mid)  # read once: anchoring, conflicts and the recalibrations' start
        d = posterior_draws(raw, run.priors(mid), mid, module.identification, rig)
        conflicts[mid] = [r for r in range_conflicts(raw, rig) if r["outside_sd"] > 0]
        starts[mid] = {k: float(np.median(raw[k])) for k in MODULE_PARAMETERS}
        procs = {ch: ResidualProcess(float(d.noise_sd[0, c]), float(d.noise_tau[0, c]), 0.0)
                 for c, ch in enumerate(CHANNELS)}
        for exp in module.validations:
            say(f"{mid}: held-out {Path(str(exp.path)).name}: predictive, gap map, effect screen")
            model = RunModel(exp, rig)
            base_evals.append(evaluate_run(model, d, _seed(seed, mid, "base", exp.path), _seed(seed, mid, exp.path),
                                           n_draws=n_draws, alpha=alpha, keep_prediction=True))
            sc = screen_effects(model, d.params, model.shift_bound / np.sqrt(3.0), procs, exclude=exclude)
            for r in sc.ranking:
                screen_sum[r["effect"]] = screen_sum.get(r["effect"], 0.0) + r["log_bayes_factor"]
                screen_rows.setdefault(r["effect"], []).append(
                    {"module": mid, "run": Path(str(exp.path)).name, "log_bayes_factor": r["log_bayes_factor"],
                     "size": {k: list(v) for k, v in r["size"].items()}, "rmse_before": r["rmse_before"],
                     "rmse_after": r["rmse_after"]})
    screen = sorted(({"effect": e, "log_bayes_factor": screen_sum[e], "runs": screen_rows[e]} for e in screen_sum),
                    key=lambda r: -r["log_bayes_factor"])
    suspects = _suspects(conflicts, allowed)
    gap_before = held_out_gap(base_evals)
    base_elpd = np.concatenate([e.elpd_blocks for e in base_evals])
    where = _where(base_evals)
    base = {"gap": gap_before, "rmse_T": _rmse(base_evals), "elpd": float(base_elpd.sum()),
            "elpd_se": _block_se(base_elpd),
            "runs": [{"module": e.module_id, "run": Path(e.source).name, "rmse_T": float(np.sqrt(e.sse / e.n)),
                      "significant_cells": len(e.significant), "channels": e.gap_map.channels}
                     for e in base_evals]}

    param_gaps = _parameter_gaps(conflicts)
    if not where and not param_gaps:
        say("no gap: the held-out runs lie within the base model's bands and its rig within the documented ranges")
        # without a gap nothing is recalibrated: the screen's linear fits stand in
        ranking = []
        for r in screen:
            before = float(np.sqrt(np.mean([x["rmse_before"] ** 2 for x in r["runs"]])))
            after = float(np.sqrt(np.mean([x["rmse_after"] ** 2 for x in r["runs"]])))
            ranking.append({"effect": r["effect"], "evidence": r["log_bayes_factor"], "evidence_kind": "screen",
                            "gap_before": before, "gap_after": after,
                            "shrink": 1.0 - after / before if before > 0 else 0.0})
        return GapDiagnosis("no_gap", [], ranking, None, [], screen, conflicts, suspects, base, list(exclude),
                            _time.perf_counter() - t_start, int(seed), {"base": base_evals})

    # 3. recalibrate the strongest candidates: the screen's on a held-out gap,
    # the conflicts' suspects on a gap hidden in the rig parameters
    if where:
        chosen = [r["effect"] for r in screen if r["log_bayes_factor"] > 0][:candidates]
        chosen += [e for e in suspects if e not in chosen][:1]
        say(f"gap found ({len(where)} cells); recalibrating with {', '.join(chosen)}")
    else:
        chosen = suspects[:candidates]
        say(f"no held-out gap, but {len(param_gaps)} rig parameter(s) outside their documented range; "
            f"recalibrating with {', '.join(chosen) or 'nothing (no catalogue effect stands for them)'}")
    in_runs = bool(where)
    where = where + param_gaps
    # each search for the mode starts at the base posterior's laws (the rig at
    # its nominal, the effect at zero): a rig the base model distorted to
    # absorb the effect is no place to start
    # racing: every candidate on the module with the largest gap first; only
    # those that gain held-out evidence there go on to the other modules
    if in_runs:
        score = {mid: held_out_gap([e for e in base_evals if e.module_id == mid]) for mid in ids}
    else:
        score = {mid: sum(r["conflict"] for r in conflicts[mid]) for mid in ids}
    lead = max(ids, key=lambda m: score[m])
    rest = [m for m in ids if m != lead]
    lead_evals = [e for e in base_evals if e.module_id == lead]
    lead_base = np.concatenate([e.elpd_blocks for e in lead_evals])

    def job(mid, e):
        return (batch.modules[mid], batch.datasheet, batch.rig_config, leg, blk, e, seed, options, n_draws, alpha,
                starts[mid])

    lead_done, why = {}, {}

    def carry(r):
        """The other modules for a lead result that gains evidence and is not beaten so far."""
        if r["module"] != lead:
            return []
        lead_done[r["effect"]] = r
        if r["failed"]:
            return []
        if not in_runs:
            why[r["effect"]] = f"its range conflicts stay on {lead}"
            return [(m, r["effect"]) for m in rest] if not r["conflicts"] else []
        blocks = {e: np.concatenate([ev.elpd_blocks for ev in x["evals"]])
                  for e, x in lead_done.items() if not x["failed"]}
        d = blocks[r["effect"]] - lead_base
        if d.sum() <= EVIDENCE_Z * _block_se(d):
            why[r["effect"]] = f"no significant held-out gain on {lead}"
            return []
        for e, b in blocks.items():  # beaten by a candidate already in: the race is lost
            d = b - blocks[r["effect"]]
            if e != r["effect"] and d.sum() > EVIDENCE_Z * _block_se(d):
                why[r["effect"]] = f"beaten by {e} on {lead}"
                return []
        return [(m, r["effect"]) for m in rest]

    results = _race([(lead, e) for e in chosen], carry, job, jobs, cache, say)
    dropped = {e for e in chosen if any((m, e) not in results for m in rest)}
    results = list(results.values())
    for r in results:
        for msg in r["warnings"]:
            warnings.warn(f"recalibration with {r['effect']}: {msg}", RuntimeWarning, stacklevel=2)

    order = [(e.module_id, e.source) for e in base_evals]
    per_effect, ranking, failed = {}, [], []
    for e in chosen:
        rs = [r for r in results if r["effect"] == e]
        bad = [f"{r['module']}: {r['failed']}" for r in rs if r["failed"]]
        if e in dropped and not bad:
            (r,) = rs
            diff = np.concatenate([ev.elpd_blocks for ev in r["evals"]]) - lead_base
            lead_before = held_out_gap(lead_evals)
            after = held_out_gap(r["evals"])
            failed.append({"effect": e, "evidence": float(diff.sum()),
                           "evidence_se": _block_se(diff),
                           "evidence_kind": "heldout_elpd_lead_module", "module": lead,
                           "gap_before": lead_before, "gap_after": after,
                           "shrink": 1.0 - after / lead_before if lead_before > 0 else 0.0,
                           "size": {lead: r["size"]}, "converged": r["converged"],
                           "dropped": f"{why.get(e, 'lost the race on ' + lead)} (the module with the largest gap): "
                                      "not recalibrated on the other modules"})
            continue
        if bad:
            failed.append({"effect": e, "evidence": None, "evidence_kind": "heldout_elpd", "gap_before": gap_before,
                           "gap_after": None, "shrink": None, "failed": "; ".join(bad)})
            continue
        evs = {(ev.module_id, ev.source): ev for r in rs for ev in r["evals"]}
        evs = [evs[k] for k in order]
        v = {"evals": evs, "blocks": np.concatenate([ev.elpd_blocks for ev in evs])}
        per_effect[e] = v
        diff = v["blocks"] - base_elpd
        after = held_out_gap(evs)
        ranking.append({"effect": e, "evidence": float(diff.sum()),
                        "evidence_se": _block_se(diff), "evidence_kind": "heldout_elpd",
                        "gap_before": gap_before, "gap_after": after,
                        "shrink": 1.0 - after / gap_before if gap_before > 0 else 0.0,
                        "remaining_cells": int(sum(len(ev.significant) for ev in evs)),
                        "remaining": _where(evs)[:5],
                        "rmse_T_before": base["rmse_T"], "rmse_T_after": _rmse(evs),
                        "size": {r["module"]: r["size"] for r in rs},
                        "conflicts_left": {r["module"]: r["conflicts"] for r in rs},
                        "conflicts_resolved": all(not r["conflicts"] for r in rs),
                        "converged": all(r["converged"] for r in rs),
                        "seconds": float(sum(r["seconds"] for r in rs))})
    if in_runs:
        ranking.sort(key=lambda r: -r["evidence"])
    else:
        # a gap in the parameters: the effect that puts them back in range,
        # at no significant loss of held-out evidence, best first
        ranking.sort(key=lambda r: (not r["conflicts_resolved"], r["remaining_cells"] > 0, -r["evidence"]))
    ranking += failed
    if not per_effect:
        return GapDiagnosis("unexplained", where, ranking, None, [], screen, conflicts, suspects, base,
                            list(exclude), _time.perf_counter() - t_start, int(seed), {"base": base_evals})
    top = ranking[0]
    group = [top["effect"]]
    for r in ranking[1:len(per_effect)]:
        d = per_effect[top["effect"]]["blocks"] - per_effect[r["effect"]]["blocks"]
        same = d.sum() < EVIDENCE_Z * _block_se(d)
        if same and (in_runs or r["conflicts_resolved"]):
            group.append(r["effect"])
    if in_runs:
        evident = top["evidence"] > EVIDENCE_Z * top["evidence_se"]
        if evident and top["shrink"] >= EXPLAINED_SHRINK and top["remaining_cells"] == 0:
            verdict = "explained"
        elif evident and top["shrink"] >= PARTIAL_SHRINK:
            verdict = "partially_explained"
        else:
            verdict = "unexplained"
    else:
        # the parameters back in range and the held-out runs still within the bands
        verdict = "explained" if top["conflicts_resolved"] and top["remaining_cells"] == 0 else "unexplained"
    best = top["effect"] if verdict in ("explained", "partially_explained") else None
    return GapDiagnosis(verdict, where, ranking, best, group if best else [], screen, conflicts, suspects, base,
                        list(exclude), _time.perf_counter() - t_start, int(seed), {"base": base_evals})
