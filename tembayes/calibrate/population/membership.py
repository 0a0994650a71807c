"""Who is off: outlier probabilities, the odd one, and whether there is one, Rao-Blackwellised.

Given the hyperparameters ``alpha`` the modules are independent, and the
likelihood terms give each one's ``P(member in all five parameters | data_i,
alpha) = pm_i`` in closed form.  Averaged over the hyper draws:

* ``outlier_prob[i] = 1 - mean pm_i``, with its Monte Carlo se from the
  arviz ESS of the per-draw values;
* ``p_any_outlier = 1 - mean prod_j pm_j``: the batch holds at least one;
* ``odd_one_prob[i] = mean q_i / sum_k mean q_k`` with
  ``q_i = (1 - pm_i) prod_(j != i) pm_j``: the probability that module ``i``
  is the outlier given that the batch holds exactly one.  Where "is there
  one" depends on the spread a small batch cannot learn, "which one" is set
  by which unit breaks the symmetry: at the spreads where any unit is off,
  it is the same one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import logsumexp

from tembayes.common.arvizlib import az
from tembayes.common.draws import even_indices

#: Hyper draws per call of the likelihood terms.
BATCH_DRAWS = 256
#: At least this many stored iterations are averaged over.
MIN_ITERATIONS = 100


@dataclass(frozen=True)
class Membership:
    """The batch's membership answers (module docstring), modules in input order.

    Attributes
    ----------
    outlier_prob, mcse : ndarray, shape (N,)
        Each module's outlier probability and its Monte Carlo se.
    odd_one_prob : ndarray, shape (N,)
        Each module's probability of being the outlier, given exactly one (sums to 1).
    p_any_outlier : float
        Probability that the batch holds at least one outlier.
    hyper : ndarray, shape (S, 11) or None
        The natural hyper draws averaged over (None from the joint fit).
    log_like : ndarray, shape (S, N) or None
        ``log L_i(alpha)`` at those draws: what leaving module ``i`` out
        reweights them by (:mod:`.deviation`).
    log_member : ndarray, shape (S, N) or None
        ``log pm_i`` at those draws (:mod:`.sensitivity`).
    """

    outlier_prob: np.ndarray
    mcse: np.ndarray
    odd_one_prob: np.ndarray
    p_any_outlier: float
    hyper: np.ndarray | None = None
    log_like: np.ndarray | None = None
    log_member: np.ndarray | None = None


def rao_blackwell(pm):
    """Outlier probabilities and their Monte Carlo se from P(member) ``pm`` (n, W, N) at draws.

    Returns
    -------
    p_out, mcse : ndarray (N,)
    """
    p_out = 1.0 - pm.mean(axis=(0, 1))
    ess = np.asarray(az.ess(az.convert_to_dataset({"p": np.swapaxes(pm, 0, 1)}))["p"].values, dtype=float)
    sd = pm.reshape(-1, pm.shape[2]).std(axis=0)
    ess = np.maximum(np.nan_to_num(ess, nan=1.0), 1.0)  # nan: constant draws
    return p_out, np.where(sd > 0, sd / np.sqrt(ess), 0.0)


def odd_one(lmem):
    """``odd_one_prob`` and ``p_any_outlier`` from membership log probabilities.

    Parameters
    ----------
    lmem : ndarray, shape (S, N)
        ``log P(member | data_i, alpha)`` of N modules at S hyper draws.

    Returns
    -------
    odd : ndarray, shape (N,)
        Each module's probability of being the outlier given exactly one (uniform
        when no draw allows exactly one).
    p_any : float
    """
    lmem = np.minimum(np.asarray(lmem, float), 0.0)
    sure_off = np.isneginf(lmem)  # a module surely off at that draw (P(member) = 0)
    finite_sum = np.where(sure_off, 0.0, lmem).sum(axis=1, keepdims=True)
    n_off = sure_off.sum(axis=1, keepdims=True)
    # log prod_(k != i) pm_k: -inf if another module is surely off at that draw
    others = np.where(n_off - sure_off > 0, -np.inf, finite_sum - np.where(sure_off, 0.0, lmem))
    with np.errstate(divide="ignore"):
        log_off = np.log(-np.expm1(lmem))  # log(1 - pm)
    log_mean_q = logsumexp(others + log_off, axis=0)  # module i the only one off, summed over the draws
    total = logsumexp(log_mean_q)
    odd = np.exp(log_mean_q - total) if np.isfinite(total) else np.full(lmem.shape[1], 1.0 / lmem.shape[1])
    all_members = np.where(n_off[:, 0] > 0, -np.inf, finite_sum[:, 0])
    return odd, float(1.0 - np.mean(np.exp(all_members)))


def thinned_iterations(n_keep, nwalkers, n_draws):
    """Stored iterations (evenly thinned) that give about ``n_draws`` draws over all walkers."""
    return even_indices(n_keep, max(MIN_ITERATIONS, n_draws // nwalkers))


def _terms_at(pop, terms, hflat):
    """``log L`` and ``log P(member)`` of each module at each natural hyper draw ``hflat`` (n, 11): (n, N) each."""
    ll, lm = [], []
    for sl in np.array_split(np.arange(len(hflat)), max(1, len(hflat) // BATCH_DRAWS)):
        mu, tau, _, logeps, log1m = pop.unpack(hflat[sl])
        a, b = terms(pop, mu, tau, logeps, log1m)
        ll.append(a)
        lm.append(b)
    return np.concatenate(ll), np.concatenate(lm)


def batch_membership(pop, terms, kept, n_draws):
    """The :class:`Membership` of about ``n_draws`` of the natural hyper draws ``kept`` (n, W, 11)."""
    n_keep, W, _ = kept.shape
    sub = kept[thinned_iterations(n_keep, W, n_draws)]  # (n, W, D)
    hflat = sub.reshape(-1, sub.shape[2])
    ll, lmem = _terms_at(pop, terms, hflat)
    p_out, mcse = rao_blackwell(np.exp(lmem).reshape(len(sub), W, -1))
    odd, p_any = odd_one(lmem)
    return Membership(p_out, mcse, odd, p_any, hyper=hflat, log_like=ll, log_member=lmem)
