"""The batch-level posterior: hyperparameter draws, outlier probabilities, predictive of a new unit."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tembayes.calibrate.population.detectable import FlaggedDeviation
from tembayes.calibrate.population.model import GROSS_SHARE, N_PARAMS, TAU_NAMES
from tembayes.calibrate.population.sensitivity import SpreadSensitivity
from tembayes.constants import MODULE_PARAMETERS

#: Quantiles :meth:`PopulationResult.summary` reports.
SUMMARY_QUANTILES = (0.05, 0.95)


@dataclass(frozen=True)
class PopulationResult:
    """The batch-level posterior.

    Attributes
    ----------
    module_ids : tuple of str
        Modules in input order.
    outlier_prob : dict
        Module id -> posterior probability that the module does not belong to
        the population (off in at least one parameter), averaged over the
        hyperparameter draws.
    predictive : ndarray, shape (n, 5)
        Draws of the parameters of a new module of the type that is a
        *member* (outlier component excluded), SI, MODULE_PARAMETERS order.
    hyper : dict
        ``HYPER_NAMES`` -> ndarray (nwalkers, ndraws), the stored draws after
        burn-in (every ``diagnostics["thin_by"]``-th step):
        ``mu_<param>`` [SI; population median for R0, S0, K], ``tau_R0_rel``,
        ``tau_S0_rel``, ``tau_K_rel`` [-] (relative sd), ``tau_R1_ohm_per_K``
        [ohm/K], ``tau_S1_V_per_K2`` [V/K^2], ``outlier_fraction`` [-].
    diagnostics : dict
        ``converged``, ``rhat_max`` (nested R-hat), ``rhat_walkers_max``
        (per-walker R-hat, reported), ``ess_bulk_min``, ``tau_max`` [steps],
        ``n_steps``, ``n_burn`` [steps], ``thin_by``, ``nwalkers``, ``acceptance_min``,
        ``weight_ess`` (module -> importance-weight ESS at the posterior-median
        hyperparameters), ``weight_ess_min``, ``interim_weight_ess_min``,
        ``outlier_prob_mcse`` (module -> Monte Carlo se), ``method``,
        ``check`` (Gaussian vs importance, if run), ``emcee_seed`` (the
        RandomState seed drawn from the caller's Generator), ``versions``,
        ``targets`` (the convergence targets used), ``elapsed_s`` [s].
    predictive_with_outliers : ndarray, shape (n, 5)
        The same as :attr:`predictive` including the outlier component (a new
        unit may be off).
    odd_one_prob : dict
        Module id -> probability that the module is the outlier, given that
        the batch holds exactly one (sums to 1; :mod:`.membership`).
    p_any_outlier : float or None
        Probability that the batch holds at least one outlier.
    deviation : dict
        Module id -> parameter -> ``{"rel", "spreads", "p_loo"}``: how far the
        module sits from the population of the other modules
        (:mod:`.deviation`; empty from the joint fit).
    outlier_vs_spread : .sensitivity.SpreadSensitivity or None
        The odd one's outlier probability against an assumed largest spread
        of its most deviating parameter (None from the joint fit).
    smallest_flagged : .detectable.FlaggedDeviation or None
        Batches under 8 modules: the deviation of the odd one's most
        deviating parameter at which a unit of a batch of this design is
        flagged (None otherwise, and from the joint fit).
    """

    module_ids: tuple
    outlier_prob: dict
    predictive: np.ndarray
    hyper: dict
    diagnostics: dict
    predictive_with_outliers: np.ndarray = None
    odd_one_prob: dict = field(default_factory=dict)
    p_any_outlier: float | None = None
    deviation: dict = field(default_factory=dict)
    outlier_vs_spread: SpreadSensitivity | None = None
    smallest_flagged: FlaggedDeviation | None = None

    def summary(self) -> dict:
        """Mean, sd, 5 % and 95 % quantiles of :attr:`predictive` (SI).

        Returns
        -------
        dict
            Contract parameter name -> ``{"mean", "sd", "q05", "q95"}``.
        """
        out = {}
        for j, name in enumerate(MODULE_PARAMETERS):
            v = self.predictive[:, j]
            q05, q95 = np.quantile(v, SUMMARY_QUANTILES)
            out[name] = {"mean": float(v.mean()), "sd": float(v.std(ddof=1)), "q05": float(q05), "q95": float(q95)}
        return out

    def spread_prior(self, widen=1.0) -> dict:
        """The spreads learned here as a prior for another batch of the type.

        Parameters
        ----------
        widen : float
            Factor on the log-sd (>= 1 to allow for batch-to-batch change).

        Returns
        -------
        dict
            Spread name (``tau_...``, see :attr:`hyper`) -> ``(median, log_sd)``,
            the format of ``fit_population(spread_prior=...)``.
        """
        out = {}
        for k in TAU_NAMES:
            lv = np.log(self.hyper[k].ravel())
            out[k] = (float(np.exp(np.median(lv))), float(widen * lv.std(ddof=1)))
        return out


def predictive(pop, kept, rng, n):
    """Draws of a new module from natural hyper draws ``kept`` (..., 11).

    Returns
    -------
    member, with_outliers : ndarray (n, 5)
        SI parameters of a new member, and of a new unit drawn from the whole
        mixture (outlier components included).
    """
    flat = kept.reshape(-1, kept.shape[-1])
    h = flat[rng.integers(0, len(flat), n)]
    mu, tau, _, logeps, _ = pop.unpack(h)
    z = rng.standard_normal((n, N_PARAMS))
    member = pop.coords.to_theta(mu + tau * z)
    u = rng.random((n, N_PARAMS))
    eps = np.exp(logeps)[:, None]
    moderate = u < (1.0 - GROSS_SHARE) * eps
    gross = (u >= (1.0 - GROSS_SHARE) * eps) & (u < eps)
    x = np.where(moderate, mu + pop.lam * tau * z, mu + tau * z)
    x = np.where(gross, pop.gross_mean + pop.gross_sd * z, x)
    return member, pop.coords.to_theta(x)


def assemble(pop, ids, kept, membership, rng, n_predictive, diag, deviation=None, sensitivity=None):
    """The :class:`PopulationResult` of natural hyper draws ``kept`` (n, W, 11).

    Parameters
    ----------
    pop : .model.Population
    ids : tuple of str
    kept : ndarray (n, W, 11)
    membership : .membership.Membership
    rng : numpy.random.Generator
        Draws the predictive.
    n_predictive : int
    diag : dict
        Diagnostics so far; the outlier probabilities' se, the leave-one-out
        Pareto k (``deviation_k_hat``), the modules whose deviation comes
        from a refit without them (``deviation_refit``), those of them whose
        refit did not converge (``deviation_refit_unconverged``) and the
        number of modules are added.
    deviation : .deviation.Deviation, optional
    sensitivity : .sensitivity.SpreadSensitivity, optional
    """
    member, mixed = predictive(pop, kept, rng, n_predictive)
    hyper_si = pop.to_si(kept)  # each (n_keep, W)
    hyper = {k: np.ascontiguousarray(v.T) for k, v in hyper_si.items()}
    diag = dict(diag)
    diag["outlier_prob_mcse"] = {mid: float(s) for mid, s in zip(ids, membership.mcse)}
    if deviation is not None:
        diag["deviation_k_hat"] = {mid: float(k) for mid, k in zip(ids, deviation.k_hat)}
        diag["deviation_refit"] = [mid for mid, r in zip(ids, deviation.refit) if r]
        diag["deviation_refit_unconverged"] = [
            mid for mid, r, c in zip(ids, deviation.refit, deviation.refit_converged) if r and not c
        ]
    diag["n_modules"] = len(ids)
    return PopulationResult(
        module_ids=ids,
        outlier_prob={mid: float(p) for mid, p in zip(ids, membership.outlier_prob)},
        predictive=member,
        hyper=hyper,
        diagnostics=diag,
        predictive_with_outliers=mixed,
        odd_one_prob={mid: float(p) for mid, p in zip(ids, membership.odd_one_prob)},
        p_any_outlier=float(membership.p_any_outlier),
        deviation={} if deviation is None else {mid: deviation.entry(i) for i, mid in enumerate(ids)},
        outlier_vs_spread=sensitivity,
    )
