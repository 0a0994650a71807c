"""The two-stage population fit: hyperparameters sampled given each module's posterior draws."""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, replace

import numpy as np

from tembayes.calibrate.population.check import compare_terms
from tembayes.calibrate.population.detectable import smallest_flagged
from tembayes.calibrate.population.deviation import loo_deviation
from tembayes.calibrate.population.hyper import sample_hyper
from tembayes.calibrate.population.inputs import sampler_seed, validate_draws
from tembayes.calibrate.population.membership import batch_membership
from tembayes.calibrate.population.model import N_HYPER, OUTLIER_FRACTION_PRIOR, OUTLIER_SCALE, Population
from tembayes.calibrate.population.result import assemble
from tembayes.calibrate.population.sampling import POPULATION_TARGETS, Budget
from tembayes.calibrate.population.sensitivity import driver, spread_sensitivity
from tembayes.calibrate.population.terms import GaussianTerms, module_summaries
from tembayes.calibrate.priors import law_log_prior, law_priors
from tembayes.common.draws import even_indices
from tembayes.common.provenance import versions
from tembayes.errors import ModelError

#: How a module's likelihood enters (:mod:`.terms`; "auto": Gaussian, checked by :mod:`.check`).
METHODS = ("auto", "gaussian", "importance")
#: Below this many modules the result states the smallest deviation the batch can flag (:mod:`.detectable`).
SMALL_BATCH = 8
#: Importance sums in the sampler use at most this many draws over all modules ...
IMPORTANCE_BUDGET = 20000
#: ... and at least this many per module.
IMPORTANCE_MIN_DRAWS = 32


@dataclass(frozen=True)
class _Sampled:
    """The terms a run ended with, its natural hyper draws (n, W, 11), diagnostics and the auto check."""

    terms: object
    kept: np.ndarray
    diag: dict
    check: object


def _sampler_draws(n_modules, max_draws_per_module):
    """Draws per module of the importance sums the sampler uses."""
    return max(IMPORTANCE_MIN_DRAWS, min(max_draws_per_module, IMPORTANCE_BUDGET // n_modules))


def _importance(summ, max_draws_per_module):
    """The importance terms the sampler uses for these module summaries."""
    return summ.importance_terms(_sampler_draws(len(summ.x), max_draws_per_module))


def _sample(pop, summ, method, max_draws_per_module, run):
    """Sample with the terms ``method`` asks for; "auto" re-runs with importance sums if the check fails.

    ``run(terms, label) -> (kept, diag)`` samples the hyperposterior of one kind of terms.
    """

    def with_importance(check):
        terms = _importance(summ, max_draws_per_module)
        return _Sampled(terms, *run(terms, "population (importance)"), check)

    if method == "importance":
        return with_importance(None)
    gauss = GaussianTerms(summ.mean, summ.cov)
    kept, diag = run(gauss, "population (gaussian)")
    if method == "gaussian":
        return _Sampled(gauss, kept, diag, None)
    check = compare_terms(pop, gauss, summ, kept)
    if check.passed:
        return _Sampled(gauss, kept, diag, check)
    warnings.warn(
        f"the Gaussian approximation of the module posteriors changes the result "
        f"(reweighting ESS {check.reweight_ess_fraction:.2f}, outlier_prob difference "
        f"{check.outlier_prob_diff_max:.3f}); re-running with importance sums",
        UserWarning,
        stacklevel=3,
    )
    return with_importance(check)


def _refitter(pop, summ, ids, terms_name, max_draws_per_module, n_draws, *, seed, nwalkers, budget, started):
    """``refit(i)`` of :func:`.deviation.loo_deviation`: about ``n_draws`` natural hyper draws without module ``i``.

    The same kind of terms as the batch's run, each refit on its own
    stream, so that the rest of the result stays that of a run without
    refits, and within what is left of the fit's wall-clock budget
    (``budget.max_seconds`` from ``started``, :func:`time.perf_counter` seconds).
    None below three modules: one module left is no population.
    """
    if len(ids) < 3:
        return None

    def refit(i):
        rest = summ.without(i)
        terms = (
            _importance(rest, max_draws_per_module)
            if terms_name == "importance"
            else GaussianTerms(rest.mean, rest.cov)
        )
        rng = np.random.default_rng([seed, i])
        label = f"population without {ids[i]}"
        left = budget
        if budget.max_seconds is not None:
            left = replace(budget, max_seconds=max(0.0, started + budget.max_seconds - time.perf_counter()))
        kept, diag = sample_hyper(pop, terms, rest.mean, rest.cov, rng, nwalkers, left, label=label)
        flat = kept.reshape(-1, N_HYPER)
        return flat[even_indices(len(flat), n_draws)], bool(diag["converged"])

    return refit


def _result_diagnostics(pop, ids, summ, sampled, max_draws_per_module):
    """Diagnostics of the draws: method, check, importance-weight ESS at the posterior-median hyperparameters."""
    imp = summ.importance_terms(max_draws_per_module)
    h_med = np.median(sampled.kept.reshape(-1, sampled.kept.shape[2]), axis=0)
    wess = imp.weight_ess(pop, h_med)
    return {
        "method": sampled.terms.name,
        "check": None if sampled.check is None else asdict(sampled.check),
        "weight_ess": {mid: float(v) for mid, v in zip(ids, wess)},
        "weight_ess_min": float(wess.min()),
        "interim_weight_ess_min": float(summ.interim_ess.min()),
        "draws_per_module_importance": int(max(imp.draws_per_module)),
        "versions": versions(),
    }


def fit_population(
    draws,
    datasheet,
    *,
    rng,
    log_interim_prior=None,
    max_steps=40000,
    max_seconds=None,
    progress=False,
    method="auto",
    spread_prior=None,
    outlier_fraction_prior=OUTLIER_FRACTION_PRIOR,
    outlier_scale=OUTLIER_SCALE,
    nwalkers=32,
    max_draws_per_module=256,
    n_predictive=4000,
    n_rao_blackwell=8192,
    convergence=POPULATION_TARGETS,
    design_reach=True,
    loo_refits=True,
):
    """Population (batch-level) posterior from per-module posterior draws.

    Parameters
    ----------
    draws : dict
        Module id -> ndarray (M_i, 5) of posterior draws in SI, order
        :data:`~tembayes.constants.MODULE_PARAMETERS` (R0 [ohm], R1 [ohm/K],
        S0 [V/K], S1 [V/K^2], K [W/K]); at least 2 modules, >= 20 draws each.
    datasheet : tembayes.data.Datasheet
        Sets the coordinates and the hyperprior scales.
    rng : numpy.random.Generator
        The only source of randomness (emcee's RandomState is seeded from it);
        the same generator state gives the same result.
    log_interim_prior : callable, optional
        ``f(theta (n, 5) SI) -> (n,)`` log density the draws were made under;
        default :func:`~tembayes.calibrate.priors.law_log_prior` (datasheet).
    max_steps : int
        Budget of emcee steps.
    max_seconds : float, optional
        Wall-clock budget of the sampling [s], checked at the sampler's
        convergence checks (every 1000 steps); the leave-one-out refits get
        what the batch's sampling left of it.
    progress : bool
        emcee's progress bar.
    method : {"auto", "gaussian", "importance"}
        How a module's likelihood enters (:mod:`.terms`, :mod:`.check`).
    spread_prior : dict, optional
        Spread name (``tau_R0_rel``, ``tau_R1_ohm_per_K``, ``tau_S0_rel``,
        ``tau_S1_V_per_K2``, ``tau_K_rel``) -> ``(median, log_sd)`` of a
        log-normal prior, e.g. :meth:`PopulationResult.spread_prior` of an
        earlier batch; unnamed spreads keep the default.
    outlier_fraction_prior : (float, float)
        Beta(a, b) prior of the module-level outlier fraction.
    outlier_scale : float
        Width of the outlier component in unit-to-unit spreads.
    nwalkers : int
    max_draws_per_module : int
        Draws per module (evenly thinned) in the importance sums.
    n_predictive : int
        Draws of :attr:`PopulationResult.predictive`.
    n_rao_blackwell : int
        Hyper draws averaged for ``outlier_prob``, ``odd_one_prob``,
        ``p_any_outlier`` and the modules' leave-one-out ``deviation`` (a
        module whose reweighting is unreliable, Pareto k above 0.7, is left
        out by sampling the others again: 10-40 s each in a batch of three).
    design_reach : bool
        For batches under :data:`SMALL_BATCH` modules, find the smallest
        deviation this design flags (:mod:`.detectable`; a few seconds).
    loo_refits : bool
        Sample the batch again without each module whose leave-one-out
        reweighting is unreliable (Pareto k above 0.7).  False keeps the
        reweighted deviation for it, its ``k_hat`` saying how far to trust
        it (quicker: 10-40 s a refit in a batch of three).  Each refit has a
        random stream of its own, so the batch's draws stay the same.
    convergence : tembayes.calibrate.sampler.Targets
        Convergence targets; default :data:`~tembayes.calibrate.population.sampling.POPULATION_TARGETS`
        (the modules' rule on a chain of 150 autocorrelation times), looser for quick looks.

    Returns
    -------
    PopulationResult

    Raises
    ------
    ModelError
        Fewer than 2 modules, malformed or non-finite draws (naming the
        module), draws outside the interim prior's support, bad options.
    """
    if method not in METHODS:
        raise ModelError(f"method must be 'auto', 'gaussian' or 'importance', got {method!r}")
    if nwalkers < 2 * N_HYPER + 2 or nwalkers % 2:
        raise ModelError(f"nwalkers must be even and >= {2 * N_HYPER + 2}, got {nwalkers}")
    budget = Budget(max_steps, max_seconds, progress, convergence)
    ids, arrays = validate_draws(draws)
    seed = sampler_seed(rng)
    t0 = time.perf_counter()
    pop = Population(
        datasheet, spread_prior=spread_prior, outlier_fraction_prior=outlier_fraction_prior, outlier_scale=outlier_scale
    )
    interim = law_log_prior(law_priors(datasheet)) if log_interim_prior is None else log_interim_prior
    summ = module_summaries(ids, arrays, pop, interim)

    def run(terms, label):
        return sample_hyper(pop, terms, summ.mean, summ.cov, rng, nwalkers, budget, label=label, seed=seed)

    sampled = _sample(pop, summ, method, max_draws_per_module, run)
    members = batch_membership(pop, sampled.terms, sampled.kept, n_rao_blackwell)

    refit = (
        _refitter(
            pop,
            summ,
            ids,
            sampled.terms.name,
            max_draws_per_module,
            n_rao_blackwell,
            seed=seed,
            nwalkers=nwalkers,
            budget=budget,
            started=t0,
        )
        if loo_refits
        else None
    )
    deviation = loo_deviation(pop, summ.mean, summ.cov, members.hyper, members.log_like, refit)
    i, j = driver(members.odd_one_prob, deviation.p_loo)
    sensitivity = spread_sensitivity(pop, members, i, j, ids[i])

    diag = {
        **sampled.diag,
        **_result_diagnostics(pop, ids, summ, sampled, max_draws_per_module),
        "elapsed_s": float(time.perf_counter() - t0),
    }
    result = assemble(pop, ids, sampled.kept, members, rng, n_predictive, diag, deviation, sensitivity)
    if not (design_reach and len(ids) < SMALL_BATCH):
        return result
    # after the result's own draws, from the same stream: they stay those of a run without it
    reach = smallest_flagged(pop, len(ids), j, summ.cov.mean(axis=0), np.random.default_rng(rng.integers(2**63)))
    return replace(result, smallest_flagged=reach)
