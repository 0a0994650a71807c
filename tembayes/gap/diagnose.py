"""The whole diagnosis: where, which effect, how far the gap shrinks (``tembayes gap``).

For every calibrated module with held-out runs (``validation*.csv``):

1. **Where** -- the base posterior's predictive of each held-out run, its
   bands made of the parameter uncertainty and the run's *measurement noise*
   (white, its level read off the run itself: ``RunModel.noise``), and the
   gap map of :mod:`~tembayes.gap.where`; and the rig parameters whose
   posterior sits outside the documented range (:mod:`~tembayes.gap.conflicts`;
   :data:`SUSPECTS` maps them to the effects they can stand for).
2. **Which** -- on the module with the largest gap, the screen of
   :mod:`~tembayes.gap.which`: the base model and every catalogue effect
   refitted on the identification run (posterior mode and Laplace
   approximation, all from the same start), ranked by their Laplace
   evidence against the base refit, each refit's Laplace posterior also
   predicting the held-out runs.
3. **How far** -- the strongest candidates are *recalibrated*: the
   identification run sampled again with the effect's parameters added
   (:func:`~tembayes.calibrate.module.calibrate_module` with ``effects``),
   anchored, and predicted on the held-out runs.  Their held-out evidence is
   the block-wise ELPD (below) against the base model's, the gap is
   :data:`GAP_METRIC` before and after.  On a batch the candidates *race*:
   each is recalibrated first on the module with the largest gap, and only
   those that gain held-out evidence there are recalibrated on the others
   (the rest are reported with their evidence on that module, ``dropped``).
   The effects not recalibrated are ranked after them with their screen's
   held-out evidence (``evidence_kind``: ``heldout_elpd_laplace``).

Held-out data are the validation runs and the identification run's step
windows, each predicted from the others by the model's refit
(:mod:`~tembayes.gap.which`).  A gap is wherever either shows one -- or a rig
parameter outside its range -- and the gap before and after (``gap_before``,
``gap_after``) is measured on the validation runs (:data:`GAP_METRIC`) or,
when only the identification windows show one, on those
(:data:`ID_GAP_METRIC`); ``gaps`` holds both.

Held-out evidence.  Each model predicts a held-out run with the run's own
measurement noise; the log density of a block of :data:`BLOCK_S` seconds is
the log density of the block's residuals summed over channels and samples,
averaged over the posterior draws on the probability scale
(``log mean_s exp``).  Blocks are nearly independent where samples are not
(residuals correlate over minutes), so the ELPD's standard error -- and the
paired difference's, ``se = sqrt(n_blocks var(delta_b))`` -- come from the
blocks, as the LOO literature does for pointwise terms (Vehtari et al. 2017).
The identification windows add their leave-one-window-out log densities,
with their own standard error; the evidence is the sum.

Verdict (the best-ranked candidate ``b``):

- ``no_gap``: no cell of any gap map (validation runs, identification
  windows) is significant (:data:`ALPHA`, Bonferroni over cells and maps)
  and material (:data:`SCORE_MIN`), and no rig parameter is outside its
  range; no effect is screened;
- ``explained``: ``b`` improves the held-out evidence by more than
  :data:`EVIDENCE_Z` standard errors, shrinks the gap by
  :data:`EXPLAINED_SHRINK` or more and leaves no significant cell on every
  dataset that shows one, and leaves the rig in range (a gap hidden in the
  parameters alone: ``b`` puts them back in range and leaves no cell);
- ``partially_explained``: ``b`` improves the ELPD significantly and shrinks
  the gap by :data:`PARTIAL_SHRINK` or more;
- ``unexplained``: otherwise (nothing in the catalogue helps).

Candidates whose ELPD differs from the best's by less than ``EVIDENCE_Z``
paired standard errors are one group: the data cannot tell them apart, and
the report says so (``best_group``).
"""

from __future__ import annotations

import multiprocessing
import os
import time as _time
import warnings
import zlib
from concurrent.futures import (
    FIRST_COMPLETED,
    Future,
    ProcessPoolExecutor,
    as_completed,
    wait,
)
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from scipy.special import logsumexp

from tembayes.calibrate.modelform import get_form
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import DataError
from tembayes.gap.conflicts import range_conflicts
from tembayes.gap.where import gap_map, identification_map
from tembayes.physics import effects as E
from tembayes.predict.predictive import (
    PredictiveDraws,
    module_raw_draws,
    posterior_draws,
    simulate_predictive,
    subsample,
)
from tembayes.predict.runmodel import CHANNELS, RunModel

#: The held-out gap, one unit for every effect (docs/outputs.md, 'gap.json (gap)').
GAP_METRIC = ("excess RMSE [K] over T1..T4: sqrt(max(0, mean (y - predictive mean)^2 - mean predictive variance)), "
              "the predictive variance being the draws' spread plus the measurement noise; pooled over every "
              "held-out run of every module.  0 when the error is what the model's own uncertainty says")
#: The gap on the identification run's held-out step windows, when only they show one.
ID_GAP_METRIC = ("excess RMS [noise sds] of the identification run's step windows, each predicted from the others "
                 "(leave-one-window-out, whitened by its predictive covariance): sqrt(max(0, mean z^2 - 1)) over "
                 "the voltage, sensor dT and sensor mean; pooled over the modules.  0 when the windows scatter as the "
                 "noise says")
#: Length of the blocks of the held-out ELPD [s].
BLOCK_S = 300.0
#: Candidates recalibrated (the screen's best; range conflicts may add one).
CANDIDATES = 2
#: Family-wise level of the gap map's cells.
ALPHA = 0.05
#: Least score (RMS standardised residual) of a gap-map cell that counts as a
#: gap, on the validation runs and on the identification windows alike: its
#: systematic part is at least the band (excess RMS >= 1 band sd).  With
#: ~10^4 samples a run's cells are significant a few per cent beyond the band;
#: measured on correctly specified bench modules, with the run's step phase
#: taken from the run, the significant cells score at most 1.16 (idle stretches,
#: where the run's unknown start-up state shows) and the identification
#: windows have none; an effect's gap scores 1.5-40.  (Before the phase was
#: taken from the run, correct models' transients sat ~90 mK/A off and this
#: was 2.)
SCORE_MIN = 2.0 ** 0.5
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
#: Screen log evidence [nats] by which the screen's best beats a candidate
#: decisively: not recalibrated, ranked by its refit's held-out evidence.
#: On a 4-hour 5 Hz identification run (~2e5 samples) that is ~0.01 in chi2
#: per sample; measured margins: effects that can stand in for each other
#: 100 nats apart (a Thomson heat and quadratic laws), the rest 1600-190000.
SCREEN_DECISIVE = 1000.0
#: Predictive draws per held-out run.
N_DRAWS = 200
#: Predictive draws per held-out run of a screen refit (its Laplace posterior).
SCREEN_DRAWS = 100

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
    phase : float
        The run's step phase the model was compared at [s] (:meth:`RunModel.fit_phase`).
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
    phase: float = 0.0


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
    noise = model.noise
    # the run's step phase is its clocks', not the model's: every model is
    # compared at the phase that fits it best (unconditioned, the phase's
    # heat impulse alone leaves a correct model ~90 mK/A off for minutes)
    phase = model.fit_phase({k: np.median(np.asarray(v, float)) for k, v in sub.params.items()})
    pred = simulate_predictive(model, _with_noise(sub, noise), rng_run, keep_draws=True, shift=phase)
    gm = gap_map(pred, rng_run)
    Y = pred.mean[None] + pred.deviations
    # every model is scored with the run's own measurement noise (white): the
    # evidence compares what the models predict, not how much misfit each
    # one learnt to expect on its identification run
    L = block_log_density(Y, pred.measured, pred.time, noise, np.full(len(noise), 1e-9))
    r = pred.residual[:4]
    expected = float(np.sum(pred.deviations[:, :4].astype(float).var(axis=0) + noise[:4, None] ** 2))
    return RunEvaluation(module_id=draws.label, source=str(model.exp.path), sse=float(np.sum(r * r)),
                         n=int(r.size), expected=expected, elpd_blocks=heldout_elpd(L),
                         significant=material(gm.significant(alpha)), gap_map=gm,
                         prediction=pred if keep_prediction else None, phase=phase)


def material(cells):
    """The cells whose score exceeds :data:`SCORE_MIN` (significant *and* large enough to matter)."""
    return [c for c in cells if c["score"] > SCORE_MIN]


def _blocks(evals):
    """The block ELPDs of some evaluations, end to end."""
    return np.concatenate([e.elpd_blocks for e in evals])


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



def _score(module, raw, priors, rig, tag, seed, n_draws, alpha):
    """A posterior (draws and priors) anchored on the identification run and scored on the held-out runs.

    Returns ``(draws, evals, conflicting)``: the anchored
    :class:`~tembayes.predict.predictive.PredictiveDraws`, a
    :class:`RunEvaluation` per held-out run (without its gap map) and the rig
    parameters outside their range.
    """
    draws = posterior_draws(raw, priors, module.id, module.identification, rig)
    evals = [evaluate_run(RunModel(exp, rig, start="data"), draws, _seed(seed, module.id, tag, exp.path),
                          _seed(seed, module.id, exp.path), n_draws=n_draws, alpha=alpha)
             for exp in module.validations]
    for e in evals:
        e.gap_map = None  # not needed back in the parent
    return draws, evals, [r["parameter"] for r in range_conflicts(raw, rig) if r["conflict"]]


def _refit_job(module, datasheet, rig_config, base, effect, start, seed, n_draws, alpha, heldout):
    """One refit (:func:`~tembayes.gap.which.refit`) and, with ``heldout``, its Laplace posterior's
    held-out scores and range conflicts (a worker's job).

    A refit whose model fails comes back with ``"failed"`` and the reason.
    """
    from threadpoolctl import threadpool_limits

    from tembayes.calibrate.module import calibration_rig
    from tembayes.errors import TembayesError
    from tembayes.gap.which import refit

    t0 = _time.perf_counter()
    out = {"module": module.id, "effect": effect, "failed": None, "evals": None, "conflicts": None}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a wrong effect's refit may probe where the rig strains
        try:
            rf = refit(module, datasheet, effect, rig_config=rig_config, start=start,
                       options=base)
            out["refit"] = rf
            if heldout:
                raw = rf.draws(_seed(seed, module.id, "laplace", effect), 4 * n_draws)
                with threadpool_limits(limits=1, user_api="blas"):
                    _, out["evals"], out["conflicts"] = _score(module, raw, rf.priors,
                                                               calibration_rig(rig_config, base),
                                                               f"screen:{effect}", seed, n_draws, alpha)
        except TembayesError as err:
            out["failed"] = str(err)
    return {**out, "seconds": _time.perf_counter() - t0}


def _candidate_job(module, datasheet, rig_config, base, effect, seed, options, n_draws, alpha,
                   start, refitted=None):
    """One module recalibrated with ``effect`` and scored on its held-out runs (a worker's job).

    The sampler starts at the refit's mode (``refitted``, the screen's, or
    one made here); the identification run's share of the evidence are the
    held-out step windows of the refit polished from the recalibration's
    posterior median.  A recalibration whose model
    fails (the effect drives the rig somewhere it cannot be simulated) is a
    candidate that does not help: it comes back with ``"failed"`` and the
    reason, not as an exception.
    """
    from threadpoolctl import threadpool_limits

    from tembayes.calibrate.module import calibrate_module, calibration_rig
    from tembayes.errors import TembayesError
    from tembayes.gap.which import refit

    t0 = _time.perf_counter()
    rig = calibration_rig(rig_config, base)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            rf = refitted or refit(module, datasheet, effect, rig_config=rig_config, start=start,
                                   options=base)
            cal = calibrate_module(module, datasheet, rig_config=rig_config, seed=seed, options=options,
                                   effects=(effect,), start={**start, **rf.mode()})
            raw = {k: np.asarray(v).ravel() for k, v in cal.draws.items()}
            # the identification windows judged at the recalibration's own fit: the mode search
            # again, from its posterior median (a screen refit may have stopped short of the mode)
            rf = refit(module, datasheet, effect, rig_config=rig_config, start={k: float(np.median(v))
                                                                                for k, v in raw.items()},
                       options=base)
            with threadpool_limits(limits=1, user_api="blas"):
                draws, evals, conflicting = _score(module, raw, cal.priors, rig, effect, seed, n_draws, alpha)
        except TembayesError as err:
            return {"module": module.id, "effect": effect, "failed": str(err), "seconds": _time.perf_counter() - t0,
                    "warnings": [], "converged": False}
    size = {}
    for p in E.get(effect).parameters:
        x = np.asarray(draws.params[p.name], float)  # anchored, where the step likelihood left it open
        size[p.name] = {"median": float(np.median(x)), "q05": float(np.quantile(x, 0.05)),
                        "q95": float(np.quantile(x, 0.95)), "unit": p.unit}
    return {"module": module.id, "effect": effect, "evals": evals, "size": size, "refit": rf,
            "converged": bool(cal.diagnostics["converged"]), "seconds": _time.perf_counter() - t0, "failed": None,
            "conflicts": conflicting, "warnings": [str(w.message) for w in caught], "calibration": cal}


class _Serial:
    """The executor interface in this process (``jobs=1``): a job runs when submitted."""

    def submit(self, fn, *args):
        f = Future()
        f.set_result(fn(*args))
        return f

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def _executor(jobs):
    """Worker processes for the refits and recalibrations (this process with ``jobs <= 1``)."""
    if jobs <= 1:
        return _Serial()
    # spawn: the compiled kernels' OpenMP runtime is not fork-safe
    return ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"))


def _submit_all(ex, jobs, cache):
    """Submit ``{key: (fn, args)}`` (the cache's results reused); ``{key: Future}``."""
    out = {}
    for key, (fn, args) in jobs.items():
        if cache is not None and key in cache:
            out[key] = Future()
            out[key].set_result(cache[key])
        else:
            out[key] = ex.submit(fn, *args)
    return out


def _collect(futures, cache, say, label):
    """Wait for ``{key: Future}`` as they finish (saying so); ``{key: result}``, the cache filled."""
    out = {}
    keys = {f: k for k, f in futures.items()}
    for f in as_completed(futures.values()):
        key = keys[f]
        out[key] = f.result()
        if cache is not None and key not in cache:
            cache[key] = out[key]
            say(f"  {label} {key[-2]} with {key[-1] or 'the base model'} ({out[key]['seconds']:.0f} s)")
    return out


def _in_order(order, lead, decide):
    """A ``follow`` for :func:`_race` that decides on the ``lead`` module's results in the candidates'
    ``order``, not in the order they finish: ``decide(result)`` (the jobs to carry on) runs for a candidate
    once it and every candidate before it are in, so the same seed gives the same diagnosis on any machine."""
    arrived, done = {}, set()

    def follow(r):
        if r["module"] != lead:
            return []
        arrived[r["effect"]] = r
        out = []
        for e in order:
            if e not in arrived:
                break
            if e not in done:
                done.add(e)
                out += decide(arrived[e])
        return out

    return follow


def _race(first, follow, job, jobs, cache, say, work=_candidate_job, ex=None):
    """Run the recalibrations ``first`` and, as each finishes, those ``follow(result)`` asks for (first).

    ``first`` and ``follow``'s return are lists of ``(module_id, effect)``;
    ``work(*job(module_id, effect))`` is one recalibration (a picklable
    top-level function with ``jobs > 1``), submitted to the executor ``ex``
    (default: a new one of ``jobs`` workers) never more than ``jobs`` ahead,
    so that a carried job jumps the queue.  Results already in ``cache`` (a
    dict keyed by ``(module_id, effect)``) are not run again; new ones are
    added to it.  Returns ``{(module_id, effect): result}``.
    """
    if ex is None:
        with _executor(jobs) as pool:
            return _race(first, follow, job, jobs, cache, say, work, pool)
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

    running = {}
    while pending or running:
        while pending and len(running) < max(jobs, 1):  # submit no further ahead: carried jobs jump the queue
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
    primary : str
        The held-out data whose gap ``gap_before``/``gap_after`` report:
        ``"validation"`` or ``"identification"``.
    gap_in : tuple of str
        Where the base model shows a gap: ``"validation"`` (runs),
        ``"identification"`` (windows held out), ``"parameters"`` (range
        conflicts); empty for ``no_gap``.
    recalibration : dict
        Module id -> the best effect's recalibrated
        :class:`~tembayes.calibrate.module.ModuleCalibration` (empty without
        a best effect); :func:`tembayes.gap.recalibrated.write_recalibrated_run`
        writes them as a run folder.
    recalibration_options : CalibrationOptions or None
        The options they were calibrated with (the run's, the effect added).
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
    primary: str = "validation"
    gap_in: tuple = ()
    recalibration: dict = field(default_factory=dict)
    recalibration_options: object = None

    def to_json(self):
        """``gap.json`` (docs/outputs.md, 'gap.json (gap)'): the verdict and the diagnosis's details."""
        return {
            "verdict": self.verdict,
            "where": self.where,
            "ranking": self.ranking,
            "best": self.best,
            "best_group": self.best_group,
            "metric": GAP_METRIC if self.primary == "validation" else ID_GAP_METRIC,
            "metric_data": self.primary,
            "gap_in": list(self.gap_in),
            "metrics": {"validation": GAP_METRIC, "identification": ID_GAP_METRIC},
            "evidence": "held-out ELPD difference to the base model [nats]: the validation runs in blocks of "
                        f"{BLOCK_S:.0f} s plus the identification run's step windows each left out; evidence_se "
                        "from the blocks and windows",
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


def _suspect_start(effect, rows):
    """Where a range-conflict suspect's refit starts: the conflicting parameters at their documented
    edge and the excess moved into the effect (an extra leak takes what the enclosure's leaks have
    beyond their range; a contact resistance what the paste lacks).  From the base posterior's
    values instead the refit stays on the conductance side of the ridge the two share (measured on
    an ambient-leak bench module: 3.1-3.9 nats below the mode this start reaches)."""
    out = {}
    for r in rows:
        if not r["conflict"]:
            continue
        p, med = r["parameter"], r["median"]
        if effect == "ambient_leak" and p in ("leak_top", "leak_bottom") and med > r["high"]:
            out[p] = r["high"]
            out["extra_leak_W_per_K"] = out.get("extra_leak_W_per_K", 0.0) + med - r["high"]
        elif effect == "contact_resistance" and p in ("g_paste_hot", "g_paste_cold") and med < r["low"]:
            out[p] = r["low"]
            out[f"contact_R_{p.rsplit('_', 1)[1]}_K_per_W"] = 1.0 / med - 1.0 / r["low"]
    return out


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

def _identification(refits, alpha=None):
    """The identification runs' held-out windows of some refits (one per module), pooled.

    Returns ``{"gap", "lpd", "cells"}``: :data:`ID_GAP_METRIC`, the windows'
    held-out log densities ``(n_windows,)`` and, with ``alpha``, the
    significant and material cells of each refit's map.
    """
    z2 = sum(float(np.sum(np.asarray(r.cv_z, float) ** 2)) for r in refits)
    n = sum(r.cv_z.size for r in refits)
    out = {"gap": float(np.sqrt(max(z2 / max(n, 1) - 1.0, 0.0))), "lpd": np.concatenate([r.cv_lpd for r in refits])}
    if alpha is not None:
        out["cells"] = [{**c, "module": r.module_id} for r in refits
                        for c in material(identification_map(r).significant(alpha))]
    return out


def _shrink(before, after):
    return 1.0 - after / before if before > 0 else 0.0


def _evidence(v_diff, i_diff):
    """Held-out evidence of the validation blocks' and the identification windows' differences [nats]."""
    v, i = ({"value": float(np.sum(d)), "se": _block_se(d) if len(d) else 0.0} for d in (v_diff, i_diff))
    return {"evidence": v["value"] + i["value"], "evidence_se": float(np.hypot(v["se"], i["se"])),
            "evidence_validation": v, "evidence_identification": i}


def default_jobs():
    """Worker processes of a diagnosis by default: one more than the cores this process may use.

    The parent mostly waits, and the jobs are uneven (a recalibration takes
    2-4 min, and three modules on two workers leave one core idle for the
    last): one worker more keeps every core busy.  Measured on the 3-module
    speed case, 2 cores: 9:37 with three workers, 10:39 with two, the
    same numbers in ``gap.json`` (every job's seed is its own).
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return cores + 1


def diagnose(run, batch, *, exclude=(), candidates=CANDIDATES, n_draws=N_DRAWS, seed=0, options=None, jobs=None,
             progress=None, cache=None):
    """Diagnose the sim-to-real gap of a calibrated batch on its held-out data.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
        The base calibration.
    batch : tembayes.data.Batch
        The calibrated batch; its ``validation*.csv`` runs are held out, and
        each identification run's step windows are held out one at a time.
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
    jobs : int, optional
        Refits and recalibrations at once, in worker processes (default
        :func:`default_jobs`; 1: in this process).
    progress : callable, optional
    cache : dict, optional
        Refits and recalibrations kept between calls on the same run, batch,
        seed and settings, keyed by ``("refit", module_id, effect)`` and
        ``(module_id, effect)``: a diagnosis with an effect withheld reuses
        the others' (filled in place).

    Returns
    -------
    GapDiagnosis
    """
    t_start = _time.perf_counter()
    jobs = default_jobs() if jobs is None else int(jobs)
    say = progress or (lambda msg: None)
    unknown = [e for e in exclude if e not in E.CATALOGUE]
    if unknown:
        raise DataError("--exclude", f"names no catalogue effect: {unknown}", f"Choose from {list(E.CATALOGUE)}.")
    base_opt = run.calibration_options()
    # the effects the run's model already contains are no candidates
    inside = {*get_form(base_opt.model).includes, *base_opt.effects,
              *(E.EFFECT_PARAMETERS[k] for k in base_opt.effect_values)}
    allowed = [e for e in E.CATALOGUE if e not in set(exclude) and e not in inside]
    rig = run.rig_for(batch)
    ids = [m for m in run.module_ids if batch.modules[m].validations]
    if not ids:
        raise DataError(batch.path, "has no validation*.csv in any module folder",
                        "The diagnosis needs held-out runs: add at least one validation experiment per module.")
    if options is None:
        options = replace(base_opt, max_steps=min(base_opt.max_steps, RECAL_MAX_STEPS),
                          stage_steps=min(base_opt.stage_steps, RECAL_MAX_STEPS))
    # the family-wise level split over every map: each validation run and each identification run
    alpha = ALPHA / (sum(len(batch.modules[m].validations) for m in ids) + len(ids))
    raws = {mid: module_raw_draws(run, mid) for mid in ids}  # read once: anchoring, conflicts, the refits' start
    starts = {mid: {k: float(np.median(raws[mid][k])) for k in MODULE_PARAMETERS} for mid in ids}

    def start(mid, e):
        return {**starts[mid], **_suspect_start(e, conflicts.get(mid, ()))}

    def refit_job(mid, e, heldout=False):
        return _refit_job, (batch.modules[mid], batch.datasheet, batch.rig_config, base_opt, e, start(mid, e), seed,
                            min(n_draws, SCREEN_DRAWS), alpha, heldout)

    with _executor(jobs) as ex:
        # 1. where: every module's base refit (the identification run's held-out windows) in the
        # workers while this process predicts the validation runs with the base posterior
        conflicts = {}
        base_futs = _submit_all(ex, {("refit", mid, None): refit_job(mid, None) for mid in ids}, cache)
        base_evals = []
        for mid in ids:
            module = batch.modules[mid]
            say(f"{mid}: base model, anchoring on the identification run")
            d = posterior_draws(raws[mid], run.priors(mid), mid, module.identification, rig)
            conflicts[mid] = [r for r in range_conflicts(raws[mid], rig) if r["outside_sd"] > 0]
            for exp in module.validations:
                say(f"{mid}: held-out {Path(str(exp.path)).name}: predictive and gap map")
                base_evals.append(evaluate_run(RunModel(exp, rig, start="data"), d, _seed(seed, mid, "base", exp.path),
                                               _seed(seed, mid, exp.path), n_draws=n_draws, alpha=alpha,
                                               keep_prediction=True))
        say("refitting the base model on the identification runs (each step window held out in turn)")
        base_refits = _collect(base_futs, cache, say, "refitted")
        broken = [f"{k[1]}: {r['failed']}" for k, r in base_refits.items() if r["failed"]]
        if broken:
            raise DataError(batch.path, f"the base model cannot be refitted on the identification run ({broken[0]})",
                            "Check the run with tembayes inspect; the diagnosis needs the base model to simulate it.")
        base_rf = {mid: base_refits[("refit", mid, None)]["refit"] for mid in ids}
        ident = {mid: _identification([base_rf[mid]], alpha) for mid in ids}
        suspects = _suspects(conflicts, allowed)
        gap_before = held_out_gap(base_evals)
        base_elpd = _blocks(base_evals)
        id_before = _identification(list(base_rf.values()))["gap"]
        where_v = _where(base_evals)
        where_i = sorted(({"channel": c["channel"], "regime": f"{c['family']}: {c['regime']}", "score": c["score"],
                           "module": mid, "run": "identification (step windows held out)", "p": c["p"],
                           "outside90": c["outside90"]} for mid in ids for c in ident[mid]["cells"]),
                         key=lambda c: -c["score"])
        base = {"gap": gap_before, "rmse_T": _rmse(base_evals), "elpd": float(base_elpd.sum()),
                "elpd_se": _block_se(base_elpd), "identification_gap": id_before,
                "runs": [{"module": e.module_id, "run": Path(e.source).name, "rmse_T": float(np.sqrt(e.sse / e.n)),
                      "phase_s": e.phase,
                          "significant_cells": len(e.significant), "channels": e.gap_map.channels}
                         for e in base_evals],
                "refits": {mid: {**base_rf[mid].summary(), "significant_cells": len(ident[mid]["cells"])}
                           for mid in ids}}
        param_gaps = _parameter_gaps(conflicts)
        where = where_v + where_i
        if not where and not param_gaps:
            say("no gap: the held-out runs and step windows lie within the base model's bands and its rig within "
                "the documented ranges")
            return GapDiagnosis("no_gap", [], [], None, [], [], conflicts, suspects, base, list(exclude),
                                _time.perf_counter() - t_start, int(seed), {"base": base_evals})
        # the datasets that show a gap, the first one giving the reported gap_before/gap_after
        gapped = [d for d, w in (("validation", where_v), ("identification", where_i)) if w]
        primary = gapped[0] if gapped else "validation"
        # the module with the largest gap leads: the screen runs there, and every
        # candidate is recalibrated there first
        if where_v:
            score = {mid: held_out_gap([e for e in base_evals if e.module_id == mid]) for mid in ids}
        elif where_i:
            score = {mid: ident[mid]["gap"] for mid in ids}
        else:
            score = {mid: sum(r["conflict"] for r in conflicts[mid]) for mid in ids}
        lead = max(ids, key=lambda m: score[m])
        rest = [m for m in ids if m != lead]
        lead_evals = [e for e in base_evals if e.module_id == lead]
        lead_base = _blocks(lead_evals)
        base_conflicting = {mid: {r["parameter"] for r in conflicts[mid] if r["conflict"]} for mid in ids}

        # 2. which: every allowed effect refitted on the lead's identification run, the base refit the control
        say(f"gap in {', '.join(gapped + (['rig parameters'] if param_gaps else []))}; screening {len(allowed)} "
            f"effects on {lead}'s identification run")
        screened = _collect(_submit_all(ex, {("refit", lead, e): refit_job(lead, e, heldout=True) for e in allowed},
                                        cache), cache, say, "refitted")
        screened[("refit", lead, None)] = base_refits[("refit", lead, None)]
        screen = _screen_rows(screened, ("refit", lead, None), lead_base)
        ok = [r for r in screen if r["log_bayes_factor"] is not None]
        if gapped:
            # the screen's best, and those it does not beat decisively; a suspect
            # too unless the best's refit already puts the rig back in range
            lbf = {r["effect"]: r["log_bayes_factor"] for r in ok}
            near = {e for e, b in lbf.items() if ok and b >= ok[0]["log_bayes_factor"] - SCREEN_DECISIVE}
            chosen = [r["effect"] for r in ok if r["log_bayes_factor"] > 0 and r["effect"] in near][:candidates]
            top_fixes = bool(ok) and not base_conflicting[lead] & set(ok[0]["conflicts"])
            chosen += [e for e in suspects if e not in chosen and (e in near or not top_fixes)][:1]
        else:
            # a gap in the parameters: the effects whose refit puts them back in range
            fix = [r["effect"] for r in ok if not base_conflicting[lead] & set(r["conflicts"])]
            chosen = ([e for e in fix if e in suspects] + [e for e in fix if e not in suspects])[:candidates]
        say(f"recalibrating with {', '.join(chosen) or 'nothing (no catalogue effect helps on the identification run)'}")

        # 3. how far: the candidates recalibrated and predicted; racing: every
        # candidate on the lead module first, only those that gain held-out
        # evidence there go on to the other modules
        def job(mid, e):
            r = screened.get(("refit", mid, e)) if mid == lead else None
            return (batch.modules[mid], batch.datasheet, batch.rig_config, base_opt, e, seed, options, n_draws, alpha,
                    start(mid, e), None if r is None or r["failed"] else r["refit"])

        lead_done, why = {}, {}

        def decide(r):
            """The other modules for a lead result that gains evidence and is not beaten by an earlier candidate."""
            lead_done[r["effect"]] = r
            if r["failed"]:
                return []
            if not gapped:
                why[r["effect"]] = f"its range conflicts stay on {lead}"
                return [(m, r["effect"]) for m in rest] if not r["conflicts"] else []
            terms = {e: (_blocks(x["evals"]), x["refit"].cv_lpd)
                     for e, x in lead_done.items() if not x["failed"]}
            v, i = terms[r["effect"]]
            ev = _evidence(v - lead_base, i - base_rf[lead].cv_lpd)
            if ev["evidence"] <= EVIDENCE_Z * ev["evidence_se"]:
                why[r["effect"]] = f"no significant held-out gain on {lead}"
                return []
            for e, (v2, i2) in terms.items():  # beaten by an earlier candidate: the race is lost
                d = _evidence(v2 - v, i2 - i)
                if e != r["effect"] and d["evidence"] > EVIDENCE_Z * d["evidence_se"]:
                    why[r["effect"]] = f"beaten by {e} on {lead}"
                    return []
            return [(m, r["effect"]) for m in rest]

        # one candidate: no race to run, every module at once (the cores would idle)
        first = [(m, e) for e in chosen for m in ([lead] + rest if len(chosen) == 1 else [lead])]
        results = _race(first, _in_order(chosen, lead, decide), job, jobs, cache, say, ex=ex)
    dropped = {e for e in chosen if any((m, e) not in results for m in rest)}
    results = list(results.values())
    for r in results:
        for msg in r["warnings"]:
            warnings.warn(f"recalibration with {r['effect']}: {msg}", RuntimeWarning, stacklevel=2)

    order = [(e.module_id, e.source) for e in base_evals]
    per_effect, ranking, failed = {}, [], []
    lead_before = held_out_gap(lead_evals)
    lead_id_before = ident[lead]["gap"]
    for e in chosen:
        rs = [r for r in results if r["effect"] == e]
        bad = [f"{r['module']}: {r['failed']}" for r in rs if r["failed"]]
        if e in dropped and not bad:
            (r,) = rs
            after = held_out_gap(r["evals"])
            id_after = _identification([r["refit"]])["gap"]
            failed.append({"effect": e, **_evidence(_blocks(r["evals"]) - lead_base,
                                                    r["refit"].cv_lpd - base_rf[lead].cv_lpd),
                           "evidence_kind": "heldout_elpd_lead_module", "module": lead,
                           **_gaps(primary, lead_before, after, lead_id_before, id_after),
                           "size": {lead: r["size"]}, "converged": r["converged"],
                           "dropped": f"{why.get(e, 'lost the race on ' + lead)} (the module with the largest gap): "
                                      "not recalibrated on the other modules"})
            continue
        if bad:
            failed.append({"effect": e, "evidence": None, "evidence_kind": "heldout_elpd", "gap_before": gap_before,
                           "gap_after": None, "shrink": None, "failed": "; ".join(bad)})
            continue
        by = {r["module"]: r for r in rs}
        evs = {(ev.module_id, ev.source): ev for r in rs for ev in r["evals"]}
        evs = [evs[k] for k in order]
        refits = [by[mid]["refit"] for mid in ids]
        id_after = _identification(refits, alpha)
        v = _blocks(evs)
        per_effect[e] = (v, id_after["lpd"])
        after = held_out_gap(evs)
        ranking.append({"effect": e, **_evidence(v - base_elpd,
                                                 id_after["lpd"] - np.concatenate([base_rf[m].cv_lpd for m in ids])),
                        "evidence_kind": "heldout_elpd",
                        **_gaps(primary, gap_before, after, id_before, id_after["gap"]),
                        "remaining_cells": int(sum(len(ev.significant) for ev in evs)) + len(id_after["cells"]),
                        "remaining": sorted(_where(evs) + [{"channel": c["channel"], "score": c["score"],
                                                            "regime": f"identification {c['family']}: {c['regime']}",
                                                            "module": c["module"]} for c in id_after["cells"]],
                                            key=lambda c: -c["score"])[:5],
                        "cells_left": {"validation": int(sum(len(ev.significant) for ev in evs)),
                                       "identification": len(id_after["cells"])},
                        "rmse_T_before": base["rmse_T"], "rmse_T_after": _rmse(evs),
                        "size": {r["module"]: r["size"] for r in rs},
                        "conflicts_left": {r["module"]: r["conflicts"] for r in rs},
                        "conflicts_resolved": all(not r["conflicts"] for r in rs),
                        "converged": all(r["converged"] for r in rs),
                        "seconds": float(sum(r["seconds"] for r in rs))})
    if gapped:
        ranking.sort(key=lambda r: -r["evidence"])
    else:
        # a gap in the parameters: the effect that puts them back in range,
        # at no significant loss of held-out evidence, best first
        ranking.sort(key=lambda r: (not r["conflicts_resolved"], r["remaining_cells"] > 0, -r["evidence"]))
    ranking += failed
    # the effects only screened, with their refit's held-out evidence on the lead module
    ranking += sorted(({"effect": r["effect"], "evidence": r["evidence"], "evidence_se": r["evidence_se"],
                        "evidence_validation": r["evidence_validation"],
                        "evidence_identification": r["evidence_identification"],
                        "evidence_kind": "heldout_elpd_laplace", "module": lead,
                        **_gaps(primary, lead_before, r["gap_after"], lead_id_before, r["identification_gap_after"]),
                        "size": {lead: r["size"]}, "screen_log_bayes_factor": r["log_bayes_factor"]}
                       for r in ok if r["effect"] not in chosen), key=lambda r: -r["evidence"])
    ranking += [{"effect": r["effect"], "evidence": None, "evidence_kind": "screen", "gap_before": gap_before,
                 "gap_after": None, "shrink": None, "failed": r["failed"]} for r in screen if r.get("failed")]
    all_where = where + param_gaps
    gap_in = tuple(gapped) + (("parameters",) if param_gaps else ())
    if not per_effect:
        return GapDiagnosis("unexplained", all_where, ranking, None, [], screen, conflicts, suspects, base,
                            list(exclude), _time.perf_counter() - t_start, int(seed), {"base": base_evals},
                            primary, gap_in)
    top = ranking[0]
    group = [top["effect"]]
    for r in ranking[1:len(per_effect)]:
        (v1, i1), (v2, i2) = per_effect[top["effect"]], per_effect[r["effect"]]
        d = _evidence(v1 - v2, i1 - i2)
        same = d["evidence"] < EVIDENCE_Z * d["evidence_se"]
        if same and (gapped or r["conflicts_resolved"]):
            group.append(r["effect"])
    if gapped:
        evident = top["evidence"] > EVIDENCE_Z * top["evidence_se"]
        closed = all(top["gaps"][d]["shrink"] >= EXPLAINED_SHRINK and top["cells_left"][d] == 0 for d in gapped)
        if evident and closed and (top["conflicts_resolved"] or not param_gaps):
            verdict = "explained"
        elif evident and top["shrink"] >= PARTIAL_SHRINK:
            verdict = "partially_explained"
        else:
            verdict = "unexplained"
    else:
        # the parameters back in range and the held-out data still within the bands
        verdict = "explained" if top["conflicts_resolved"] and top["remaining_cells"] == 0 else "unexplained"
    best = top["effect"] if verdict in ("explained", "partially_explained") else None
    recal = {}
    if best:  # the best explanation's recalibrated modules: the run gap hands back
        recal = {r["module"]: r["calibration"] for r in results if r["effect"] == best and not r["failed"]}
    return GapDiagnosis(verdict, all_where, ranking, best, group if best else [], screen, conflicts, suspects, base,
                        list(exclude), _time.perf_counter() - t_start, int(seed), {"base": base_evals},
                        primary, gap_in, recal, replace(options, effects=(*options.effects, best)) if best else None)


def _gaps(primary, before, after, id_before, id_after):
    """The gap before/after on both held-out datasets; ``gap_before``/``gap_after``/``shrink`` the primary's."""
    g = {"validation": {"before": before, "after": after, "shrink": _shrink(before, after)},
         "identification": {"before": id_before, "after": id_after, "shrink": _shrink(id_before, id_after)}}
    p = g[primary]
    return {"gap_before": p["before"], "gap_after": p["after"], "shrink": p["shrink"], "gaps": g}


def _screen_rows(results, base_key, lead_base):
    """The screen's refits as ``gap.json`` rows, best (Laplace evidence against the base refit) first."""
    base = results[base_key]["refit"]
    rows = []
    for (_, _, effect), r in results.items():
        if effect is None:
            continue
        if r["failed"]:
            rows.append({"effect": effect, "log_bayes_factor": None, "failed": r["failed"]})
            continue
        rf = r["refit"]
        rows.append({**rf.summary(), "module": rf.module_id, "log_bayes_factor": rf.log_evidence - base.log_evidence,
                     "conflicts": r["conflicts"],
                     **_evidence(_blocks(r["evals"]) - lead_base,
                                 rf.cv_lpd - base.cv_lpd),
                     "gap_after": held_out_gap(r["evals"]), "identification_gap_after": _identification([rf])["gap"]})
    return sorted(rows, key=lambda r: (r["log_bayes_factor"] is None, -(r["log_bayes_factor"] or 0.0)))
