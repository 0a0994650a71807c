"""How far each module sits from the population of the *other* modules (leave-one-out).

Leaving module ``i`` out reweights the hyper draws by ``1 / L_i(alpha)``
(its likelihood term, :mod:`.terms`), Pareto-smoothed (PSIS, Vehtari et al.
2017).  Its ``k_hat`` says whether the reweighting can be trusted: above 0.7
the module is so far from the others that the batch's posterior rarely
visits the hyperparameters of the rest alone -- typical of the odd one, and
of three-module batches -- and, as PSIS-LOO practice has it, the rest is
refitted without the module (given a ``refit``) and its draws used as they are.
Under those weights, per parameter, with the module's likelihood mean ``m``
(its posterior with the datasheet prior divided out) and variance ``v`` in the
population coordinates (levels in log, slopes linear):

* ``rel``: the offset from the others' population centre, relative
  (levels ``exp(m - mu) - 1``, slopes ``(m - mu) / |mu|``);
* ``spreads``: the offset in unit-to-unit spreads, ``(m - mu) / tau``;
* ``p_loo``: the two-sided tail probability of the module's value under the
  others' population, measured as precisely as this module,
  ``2 Phi(-|m - mu| / sqrt(tau^2 + v))``: how often a member of that
  population lies at least this far out.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from tembayes.calibrate.population.model import LEVEL
from tembayes.common.arvizlib import az
from tembayes.constants import MODULE_PARAMETERS

#: Above this Pareto k the leave-one-out reweighting is unreliable (Vehtari et al. 2017).
K_HAT_MAX = 0.7


@dataclass(frozen=True)
class Deviation:
    """Each module's leave-one-out deviation (module docstring), modules and parameters in input order.

    Attributes
    ----------
    rel, spreads, p_loo : ndarray, shape (N, 5)
    k_hat : ndarray, shape (N,)
        Pareto k of each module's leave-one-out weights.
    refit : ndarray of bool, shape (N,)
        The module's row comes from a refit of the other modules, not from
        the reweighting (``k_hat`` above :data:`K_HAT_MAX`).
    refit_converged : ndarray of bool, shape (N,)
        That refit met its convergence targets (False where there was none):
        an unconverged refit's row is an approximation too.
    """

    rel: np.ndarray
    spreads: np.ndarray
    p_loo: np.ndarray
    k_hat: np.ndarray
    refit: np.ndarray
    refit_converged: np.ndarray

    def entry(self, i: int) -> dict[str, dict[str, float]]:
        """Module ``i``'s ``deviation`` entry of ``summary.json``: parameter -> ``{"rel", "spreads", "p_loo"}``."""
        return {
            p: {"rel": float(self.rel[i, j]), "spreads": float(self.spreads[i, j]), "p_loo": float(self.p_loo[i, j])}
            for j, p in enumerate(MODULE_PARAMETERS)
        }


def _psis_weights(log_like_i):
    """Normalised PSIS weights that leave a module out (``1 / L_i``), and their Pareto k."""
    with warnings.catch_warnings():  # its k is reported (deviation_k_hat), not warned about
        warnings.simplefilter("ignore", UserWarning)
        lw, k = az.psislw(-log_like_i + log_like_i.max(), reff=1.0)
    w = np.exp(np.asarray(lw, float) - np.max(lw))
    return w / w.sum(), float(k)


def _offsets(pop, m, v, hyper, w):
    """``rel``, ``spreads``, ``p_loo`` (5,) of likelihood mean ``m`` and variances ``v`` under weighted hyper draws."""
    mu, tau, *_ = pop.unpack(hyper)
    d = m[None] - mu  # (S, 5)
    slope_rel = np.divide(d, np.abs(mu), out=np.full_like(d, np.nan), where=mu != 0)  # a centre at 0: none
    rel_draws = np.where(LEVEL[None], np.expm1(d), slope_rel)
    sd = np.sqrt(tau**2 + v[None])
    return w @ rel_draws, w @ (d / tau), w @ (2.0 * ndtr(-np.abs(d) / sd))


def loo_deviation(pop, mean, cov, hyper, log_like, refit=None) -> Deviation:
    """The :class:`Deviation` of every module.

    Parameters
    ----------
    pop : .model.Population
    mean : ndarray, shape (N, 5)
        The modules' likelihood means in population coordinates (their
        posteriors with the datasheet prior divided out, :mod:`.terms`).
    cov : ndarray, shape (N, 5, 5)
        Their covariances [x units^2].
    hyper : ndarray, shape (S, 11)
        Natural hyper draws of the batch's posterior.
    log_like : ndarray, shape (S, N)
        Each module's ``log L_i`` at those draws.
    refit : callable, optional
        ``refit(i) -> (draws (S', 11), converged)``: natural hyper draws of
        the batch without module ``i`` and whether their sampler met its
        targets; called for the modules whose ``k_hat`` exceeds
        :data:`K_HAT_MAX`.

    Returns
    -------
    Deviation
    """
    N = len(mean)
    rel, spreads, p_loo = (np.empty((N, mean.shape[1])) for _ in range(3))
    k_hat, refitted, converged = np.empty(N), np.zeros(N, bool), np.zeros(N, bool)
    for i in range(N):
        w, k_hat[i] = _psis_weights(log_like[:, i])
        draws = hyper
        if refit is not None and k_hat[i] > K_HAT_MAX:
            (draws, converged[i]), refitted[i] = refit(i), True
            w = np.full(len(draws), 1.0 / len(draws))
        rel[i], spreads[i], p_loo[i] = _offsets(pop, mean[i], np.diag(cov[i]), draws, w)
    return Deviation(rel=rel, spreads=spreads, p_loo=p_loo, k_hat=k_hat, refit=refitted, refit_converged=converged)
