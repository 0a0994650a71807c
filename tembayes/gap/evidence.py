"""Held-out evidence: a model's predictive of the held-out data, scored.

Each model predicts a held-out run with the run's own measurement noise; the
log density of a block of :data:`BLOCK_S` seconds is the log density of the
block's residuals summed over channels and samples, averaged over the
posterior draws on the probability scale (``log mean_s exp``).  Blocks are
nearly independent where samples are not (residuals correlate over
minutes), so the ELPD's standard error -- and the paired difference's,
``se = sqrt(n_blocks var(delta_b))`` -- come from the blocks, as the LOO
literature does for pointwise terms (Vehtari et al. 2017).  The
identification run's step windows, each predicted from the others by the
model's refit (:mod:`~tembayes.gap.which`), add their held-out log densities
with their own standard error; the evidence is the sum (:class:`Evidence`).

The gap itself is :data:`GAP_METRIC` on the validation runs and
:data:`ID_GAP_METRIC` on the identification windows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from tembayes.gap.where import gap_map, identification_map
from tembayes.predict.predictive import PredictiveDraws, simulate_predictive, subsample

#: The held-out gap, one unit for every effect (docs/outputs.md, 'gap.json (gap)').
GAP_METRIC = (
    "excess RMSE [K] over the rig's sensors: sqrt(max(0, mean (y - predictive mean)^2 - mean predictive variance)), "
    "the predictive variance being the draws' spread plus the measurement noise; pooled over every "
    "held-out run of every module.  0 when the error is what the model's own uncertainty says"
)
#: The gap on the identification run's held-out step windows, when only they show one.
ID_GAP_METRIC = (
    "excess RMS [sds of the calibration's noise model] of the identification run's step windows, each predicted from the others "
    "(leave-one-window-out, whitened by its predictive covariance under the calibration's noise model: "
    "its noise scale and window offsets): sqrt(max(0, mean z^2 - 1)) over the voltage, sensor dT and "
    "sensor mean; pooled over the modules.  0 when the windows scatter as the calibrated noise says"
)
#: Length of the blocks of the held-out ELPD [s].
BLOCK_S = 300.0
#: Family-wise level of the gap map's cells.
ALPHA = 0.05
#: Least score (RMS standardised residual) of a gap-map cell that counts as a
#: gap, on the validation runs and on the identification windows alike: its
#: systematic part is at least the band (excess RMS >= 1 band sd).  With
#: ~10^4 samples a run's cells are significant a few per cent beyond the band;
#: measured on correctly specified bench modules, with the run's step phase
#: taken from the run, the significant cells score at most 1.16 (idle stretches,
#: where the run's unknown start-up state shows) and the identification
#: windows have none; an effect's gap scores 1.5-40.
SCORE_MIN = 2.0**0.5
#: Standard errors of an ELPD difference that count as evidence.
EVIDENCE_Z = 2.0
#: Predictive draws per held-out run.
N_DRAWS = 200

#: Correlation time [s] that makes the run's measurement noise white in :func:`block_log_density`.
_WHITE_TAU_S = 1e-9


def block_log_density(Y, measured, t, sd, tau, block_s=BLOCK_S):
    """Innovation log density of the residuals per draw and block.

    Parameters
    ----------
    Y : ndarray, shape (M, nch, n)
        The draws' noise-free predictions (SI).
    measured : ndarray, shape (nch, n)
    t : ndarray, shape (n,)
        [s].
    sd, tau : ndarray, shape (nch,)
        The model's residual process per channel (stationary sd, correlation time [s]).
    block_s : float
        Block length [s].

    Returns
    -------
    ndarray, shape (M, n_blocks)
        [nats].
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
    """Block ELPDs ``(n_blocks,)`` [nats] from per-draw block log densities ``(M, n_blocks)``."""
    return logsumexp(L, axis=0) - np.log(L.shape[0])


@dataclass
class RunEvaluation:
    """A model's predictive of one held-out run (the summary the diagnosis keeps).

    Attributes
    ----------
    module_id, source : str
    sse, n : float, int
        Sum of squared errors over the rig's sensors [K^2] and its sample count.
    expected : float
        Its expectation under the predictive (draws' variance plus noise) [K^2].
    elpd_blocks : ndarray
        Block ELPDs [nats] (see :func:`block_log_density`).
    significant : list of dict
        The gap map's significant and material cells (``alpha`` already split over the maps).
    gap_map : GapMap or None
        None once the evaluation comes back from a worker (not needed there).
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


def _with_noise(draws, sd):
    """The draws with white noise ``sd`` ``(nch,)`` instead of their residual processes."""
    return PredictiveDraws(
        params=draws.params,
        noise_sd=np.repeat(np.asarray(sd, float)[None], draws.n, axis=0),
        label=draws.label,
        laws=draws.laws,
        anchor=draws.anchor,
        noise_tau=np.zeros((draws.n, len(sd))),
    )


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
    L = block_log_density(Y, pred.measured, pred.time, noise, np.full(len(noise), _WHITE_TAU_S))
    r = pred.residual[:-1]  # the sensors (the voltage last)
    expected = float(np.sum(pred.deviations[:, :-1].astype(float).var(axis=0) + noise[:-1, None] ** 2))
    return RunEvaluation(
        module_id=draws.label,
        source=str(model.exp.path),
        sse=float(np.sum(r * r)),
        n=int(r.size),
        expected=expected,
        elpd_blocks=heldout_elpd(L),
        significant=material(gm.significant(alpha)),
        gap_map=gm,
        prediction=pred if keep_prediction else None,
        phase=phase,
    )


def material(cells):
    """The cells whose score exceeds :data:`SCORE_MIN` (significant *and* large enough to matter)."""
    return [c for c in cells if c["score"] > SCORE_MIN]


def elpd_blocks(evals):
    """The block ELPDs [nats] of some evaluations, end to end."""
    return np.concatenate([e.elpd_blocks for e in evals])


def rmse(evals):
    """Plain RMSE over the rig's sensors [K] of the predictive mean, pooled."""
    return float(np.sqrt(sum(e.sse for e in evals) / max(sum(e.n for e in evals), 1)))


def held_out_gap(evals):
    """:data:`GAP_METRIC` of a model's evaluations [K]."""
    excess = sum(e.sse - e.expected for e in evals) / max(sum(e.n for e in evals), 1)
    return float(np.sqrt(max(excess, 0.0)))


def block_se(d):
    """Standard error of a sum of block terms ``d`` (the blocks nearly independent) [nats]."""
    return float(np.sqrt(len(d)) * np.std(d))


@dataclass(frozen=True)
class WindowCheck:
    """The identification runs' held-out step windows of some refits (one per module), pooled.

    Attributes
    ----------
    gap : float
        :data:`ID_GAP_METRIC` [noise sds].
    lpd : ndarray, shape (n_windows,)
        The windows' held-out log densities [nats].
    cells : list of dict or None
        The significant and material cells of each refit's identification
        map, with their ``module`` (None when not asked for).
    """

    gap: float
    lpd: np.ndarray
    cells: list | None = None


def held_out_windows(refits, *, alpha=None):
    """The identification windows of some refits, pooled.

    Parameters
    ----------
    refits : list of Refit
        One per module.
    alpha : float, optional
        Level of each cell test; without it the cells are not mapped.

    Returns
    -------
    WindowCheck
    """
    z2 = sum(float(np.sum(np.asarray(r.cv_z, float) ** 2)) for r in refits)
    n = sum(r.cv_z.size for r in refits)
    cells = None
    if alpha is not None:
        cells = [
            {**c, "module": r.module_id} for r in refits for c in material(identification_map(r).significant(alpha))
        ]
    return WindowCheck(
        gap=float(np.sqrt(max(z2 / max(n, 1) - 1.0, 0.0))),
        lpd=np.concatenate([r.cv_lpd for r in refits]),
        cells=cells,
    )


@dataclass(frozen=True)
class HeldOut:
    """A model's held-out log densities [nats], the terms of its evidence.

    Attributes
    ----------
    blocks : ndarray
        The validation runs' block ELPDs.
    windows : ndarray
        The identification windows' held-out log densities.
    """

    blocks: np.ndarray
    windows: np.ndarray

    def evidence_over(self, other):
        """The :class:`Evidence` of this model against ``other`` (the same blocks and windows)."""
        return Evidence.of(self.blocks - other.blocks, self.windows - other.windows)


@dataclass(frozen=True)
class Evidence:
    """Held-out evidence of one model against another: the ELPD difference [nats].

    Attributes
    ----------
    value, se : float
        The difference summed over the validation blocks and the
        identification windows, and its standard error.
    validation, identification : tuple of float
        Each dataset's ``(value, se)``.
    """

    value: float
    se: float
    validation: tuple
    identification: tuple

    @classmethod
    def of(cls, v_diff, i_diff):
        """The evidence of the validation blocks' and the identification windows' differences."""
        v, i = ((float(np.sum(d)), block_se(d) if len(d) else 0.0) for d in (v_diff, i_diff))
        return cls(value=v[0] + i[0], se=float(np.hypot(v[1], i[1])), validation=v, identification=i)

    def significant(self):
        """More than :data:`EVIDENCE_Z` standard errors above zero."""
        return self.value > EVIDENCE_Z * self.se

    def indistinct(self):
        """Less than :data:`EVIDENCE_Z` standard errors above zero: the data cannot tell the two apart."""
        return self.value < EVIDENCE_Z * self.se

    def to_json(self):
        """The evidence keys of a ``gap.json`` row."""
        return {
            "evidence": self.value,
            "evidence_se": self.se,
            "evidence_validation": {"value": self.validation[0], "se": self.validation[1]},
            "evidence_identification": {"value": self.identification[0], "se": self.identification[1]},
        }
