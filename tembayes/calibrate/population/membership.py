"""Outlier probabilities, Rao-Blackwellised over the hyperparameter draws.

``outlier_prob[i] = 1 - mean`` over hyper draws of ``P(module i a member in
all five parameters | its data, alpha)``, which the likelihood terms give in
closed form; its Monte Carlo se comes from the arviz ESS of those per-draw
values.
"""

from __future__ import annotations

import numpy as np

from tembayes.common.arvizlib import az
from tembayes.common.draws import even_indices

#: Hyper draws per call of the likelihood terms.
BATCH_DRAWS = 256
#: At least this many stored iterations are averaged over.
MIN_ITERATIONS = 100


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


def thinned_iterations(n_keep, nwalkers, n_draws):
    """Stored iterations (evenly thinned) that give about ``n_draws`` draws over all walkers."""
    return even_indices(n_keep, max(MIN_ITERATIONS, n_draws // nwalkers))


def _member_prob(pop, terms, hflat):
    """P(member) of each module at each natural hyper draw ``hflat`` (n, 11): (n, N)."""
    out = []
    for sl in np.array_split(np.arange(len(hflat)), max(1, len(hflat) // BATCH_DRAWS)):
        mu, tau, _, logeps, log1m = pop.unpack(hflat[sl])
        _, lmem = terms(pop, mu, tau, logeps, log1m)
        out.append(np.exp(lmem))
    return np.concatenate(out)


def outlier_probabilities(pop, terms, kept, n_draws):
    """Outlier probabilities and their se from about ``n_draws`` of the natural hyper draws ``kept`` (n, W, 11).

    Returns
    -------
    p_out, mcse : ndarray (N,)
    """
    n_keep, W, _ = kept.shape
    sub = kept[thinned_iterations(n_keep, W, n_draws)]  # (n, W, D)
    pm = _member_prob(pop, terms, sub.reshape(-1, sub.shape[2])).reshape(len(sub), W, -1)
    return rao_blackwell(pm)
