"""The ``method="auto"`` check: the Gaussian terms against the importance sums.

Where a parameter's population spread is smaller than a module's posterior sd
(typically S1), few draws fall where the population density is and the
importance sums are noisy, while the Gaussian approximation of a
near-Gaussian module posterior is exact in that limit; hence Gaussian terms
by default, checked here at hyperparameter draws.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special

from tembayes.common.draws import even_indices

#: Minimum ESS fraction left by reweighting the hyper draws from the Gaussian
#: to the importance likelihood.
CHECK_ESS_FRACTION = 0.8
#: Maximum outlier_prob difference, on top of three standard errors.
CHECK_OUTLIER_DIFF = 0.03
#: A module enters at a hyper draw only where its sums have at least this weight ESS.
CHECK_MIN_ESS = 50.0
#: Hyper draws and draws per module the check uses.
CHECK_HYPER_DRAWS = 64
CHECK_DRAWS_PER_MODULE = 1000


@dataclass(frozen=True)
class TermsCheck:
    """Gaussian vs importance likelihood at hyper draws.

    Attributes
    ----------
    reweight_ess_fraction : float
        ``exp(-v)``, v the variance over hyper draws of the summed
        log-likelihood difference minus the sums' own variance: the effective
        sample size left if the Gaussian-based hyper draws were reweighted to
        the importance sums.
    loglike_diff_var : float
        That variance before subtracting the sums' noise [nat^2].
    importance_noise_var : float
        The sums' own variance [nat^2].
    usable_fraction : float
        Share of (hyper draw, module) pairs with enough weight ESS to enter.
    outlier_prob_diff_max : float
        Largest difference of a module's membership probability.
    outlier_prob_diff_minus_3se_max : float
        The same minus three standard errors of the sums.
    passed : bool
        Reweighting ESS >= :data:`CHECK_ESS_FRACTION` and every difference
        minus 3 se <= :data:`CHECK_OUTLIER_DIFF`.
    """

    reweight_ess_fraction: float
    loglike_diff_var: float
    importance_noise_var: float
    usable_fraction: float
    outlier_prob_diff_max: float
    outlier_prob_diff_minus_3se_max: float
    passed: bool


def _module_sums(x, lw, pop, mu, tau, logeps, log1m):
    """One module's importance sums at hyper draws, with their Monte Carlo variance.

    Returns
    -------
    ok : ndarray of bool
        Weight ESS >= :data:`CHECK_MIN_ESS` (a population much narrower than
        the module's posterior leaves few draws where it matters: there the
        sum, not the Gaussian, is unreliable).
    log_like : ndarray
    noise : ndarray
        Variance of the log of the self-normalised sum, ``1/ESS - 1/M``.
    p_member, se : ndarray
        Membership probability and its delta-method se.
    """
    lmix, lmem = pop.log_density(np.broadcast_to(x, (len(mu),) + x.shape), mu, tau, logeps, log1m)
    a = lw + lmix  # (S, M)
    lli = special.logsumexp(a, axis=1)
    wn = np.exp(a - lli[:, None])  # normalised weights of the mixture sum
    ess = 1.0 / (wn**2).sum(axis=1)
    r = np.exp(lmem)  # P(member | x_m, alpha) per draw
    p = (wn * r).sum(axis=1)
    # self-normalised IS: var(ratio) ~ sum wn^2 (r - ratio)^2
    se = np.sqrt((wn**2 * (r - p[:, None]) ** 2).sum(axis=1))
    return ess >= CHECK_MIN_ESS, lli, 1.0 / ess - 1.0 / len(x), p, se


def compare_terms(pop, gauss, summaries, kept):
    """Gaussian terms vs importance sums at :data:`CHECK_HYPER_DRAWS` hyper draws.

    Parameters
    ----------
    pop : .model.Population
    gauss : .terms.GaussianTerms
    summaries : .terms.ModuleSummaries
    kept : ndarray (n, W, 11)
        Natural hyperparameter draws of the Gaussian run.

    Returns
    -------
    TermsCheck
    """
    flat = kept.reshape(-1, kept.shape[2])
    h = flat[even_indices(len(flat), CHECK_HYPER_DRAWS)]
    mu, tau, _, logeps, log1m = pop.unpack(h)
    llg, lmg = gauss(pop, mu, tau, logeps, log1m)
    dll, noise, se = np.zeros_like(llg), np.zeros_like(llg), np.zeros_like(llg)
    pmg = np.exp(lmg)
    pmi = pmg.copy()
    usable = np.zeros(llg.shape, dtype=bool)
    for i, (xi, lwi) in enumerate(zip(summaries.x, summaries.log_w)):
        k = even_indices(len(xi), CHECK_DRAWS_PER_MODULE)
        ok, lli, noise_i, p, se_i = _module_sums(xi[k], lwi[k] - special.logsumexp(lwi[k]), pop, mu, tau, logeps, log1m)
        usable[:, i] = ok
        dll[ok, i] = lli[ok] - llg[ok, i]
        noise[ok, i] = noise_i[ok]
        pmi[ok, i] = p[ok]
        se[ok, i] = se_i[ok]
    d = dll.sum(axis=1)
    excess = max(float(d.var() - noise.sum(axis=1).mean()), 0.0)
    ess_frac = math.exp(-excess)
    diff = np.abs(pmg.mean(axis=0) - pmi.mean(axis=0))
    over = diff - 3.0 * se.mean(axis=0)
    passed = ess_frac >= CHECK_ESS_FRACTION and np.all(over <= CHECK_OUTLIER_DIFF)
    return TermsCheck(
        reweight_ess_fraction=ess_frac,
        loglike_diff_var=float(d.var()),
        importance_noise_var=float(noise.sum(axis=1).mean()),
        usable_fraction=float(usable.mean()),
        outlier_prob_diff_max=float(diff.max()),
        outlier_prob_diff_minus_3se_max=float(over.max()),
        passed=bool(passed),
    )
