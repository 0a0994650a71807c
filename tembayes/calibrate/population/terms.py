"""How a module enters the population: its marginal likelihood given the hyperparameters.

Module ``i`` contributes

    L_i(alpha) = E_{theta ~ posterior_i} [ p(theta | alpha) / pi_interim(theta) ]
                 / E_{theta ~ posterior_i} [ 1 / pi_interim(theta) ],

the interim prior its draws were made under divided out (Hogg, Myers & Bovy
2010; Foreman-Mackey, Hogg & Morton 2014).  Two ways to compute it:

* :class:`GaussianTerms`: the module likelihood approximated by a Gaussian in
  ``x`` (moments of the draws weighted by ``1 / pi_interim``); the integral
  over the module's parameters is then closed-form for every
  member/moderate/gross pattern (:mod:`.kernels`).  About 1 us per module and
  walker.
* :class:`ImportanceTerms`: importance sums over (evenly thinned) draws;
  consistent for any posterior shape, cost proportional to modules x draws.

Both return, per walker and module, ``log L_i`` and ``log P(member in all
parameters | data_i, alpha)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from scipy import special

from tembayes.calibrate.population import kernels
from tembayes.common.draws import even_indices
from tembayes.errors import ModelError

#: Module x walker evaluations below which the compiled terms run on one
#: thread (on the 2-vCPU development machine threads did not pay off even for
#: 500 modules x 16 walkers).
PARALLEL_MIN = 65536
#: The importance sums go parallel from this many times more evaluations (each sums many draws).
IMPORTANCE_PARALLEL_FACTOR = 16
#: Parallel chunks per numba thread (load balance).
CHUNKS_PER_THREAD = 4
#: A module's weighted draw covariance is singular if its eigenvalues span more than this ratio.
DEGENERATE_EIGEN_RATIO = 1e-14


def _chunks():
    return CHUNKS_PER_THREAD * numba.get_num_threads()


class GaussianTerms:
    """Module likelihoods as Gaussians in ``x``.

    Parameters
    ----------
    m : ndarray (N, 5)
        Means [x units].
    C : ndarray (N, 5, 5)
        Covariances [x units squared].
    """

    name = "gaussian"

    def __init__(self, m, C):
        self.m = np.ascontiguousarray(m)
        self.C = np.ascontiguousarray(C)
        self.n = len(m)

    def __call__(self, pop, mu, tau, logeps, log1m):
        """``log L`` and ``log P(member)`` (W, N) at hyperparameters ``mu, tau`` (W, 5), ``logeps, log1m`` (W,)."""
        W = len(mu)
        ll = np.empty((W, self.n))
        lmem = np.empty((W, self.n))
        args = (
            self.m,
            self.C,
            np.ascontiguousarray(mu),
            np.ascontiguousarray(tau),
            pop.lam,
            pop.component_log_weights(logeps, log1m),
            pop.gross_mean,
            pop.gross_sd,
            ll,
            lmem,
        )
        if ll.size < PARALLEL_MIN:  # thread start-up costs more than it saves
            kernels.gauss_terms_serial(*args)
        else:
            kernels.gauss_terms_parallel(*args, _chunks())
        return ll, lmem


class ImportanceTerms:
    """Importance sums over the draws of each module.

    Parameters
    ----------
    xs : list of ndarray (M_i, 5)
        Each module's draws in ``x``.
    lws : list of ndarray (M_i,)
        Their log weights, self-normalised per module.
    """

    name = "importance"

    def __init__(self, xs, lws):
        self.n = len(xs)
        self.x = np.ascontiguousarray(np.concatenate(xs))
        self.lw0 = np.ascontiguousarray(np.concatenate(lws))
        self.start = np.concatenate([[0], np.cumsum([len(v) for v in xs])]).astype(np.int64)
        self.draws_per_module = [len(v) for v in xs]

    def __call__(self, pop, mu, tau, logeps, log1m):
        """As :meth:`GaussianTerms.__call__`."""
        W = len(mu)
        ll = np.empty((W, self.n))
        lmem = np.empty((W, self.n))
        args = (
            self.x,
            self.lw0,
            self.start,
            np.ascontiguousarray(mu),
            np.ascontiguousarray(tau),
            pop.lam,
            pop.component_log_weights(logeps, log1m),
            pop.gross_mean,
            pop.gross_sd,
            ll,
            lmem,
        )
        if len(self.x) * W < IMPORTANCE_PARALLEL_FACTOR * PARALLEL_MIN:
            kernels.importance_terms_serial(*args)
        else:
            kernels.importance_terms_parallel(*args, _chunks())
        return ll, lmem

    def weight_ess(self, pop, h):
        """Importance-weight ESS per module at one natural hyperparameter point ``h`` (11,)."""
        mu, tau, _, logeps, log1m = pop.unpack(h[None, :])
        out = []
        for i in range(self.n):
            sl = slice(self.start[i], self.start[i + 1])
            lmix, _ = pop.log_density(self.x[sl][None], mu, tau, logeps, log1m)
            lw = self.lw0[sl] + lmix[0]
            w = np.exp(lw - lw.max())
            out.append(float(w.sum() ** 2 / (w * w).sum()))
        return np.array(out)


@dataclass(frozen=True)
class ModuleSummaries:
    """Each module's draws in ``x`` with their likelihood weights, and their Gaussian moments.

    Attributes
    ----------
    x : list of ndarray (M_i, 5)
        Draws in population coordinates.
    log_w : list of ndarray (M_i,)
        Log weights ``1 / pi_interim`` (in ``x``), self-normalised per module.
    mean : ndarray (N, 5)
        Weighted means [x units].
    cov : ndarray (N, 5, 5)
        Weighted covariances [x units squared].
    interim_ess : ndarray (N,)
        Effective sample size of the weights.
    """

    x: list
    log_w: list
    mean: np.ndarray
    cov: np.ndarray
    interim_ess: np.ndarray

    def without(self, i):
        """The summaries of the other modules (module ``i`` left out)."""
        keep = np.delete(np.arange(len(self.x)), i)
        return ModuleSummaries(
            [self.x[k] for k in keep],
            [self.log_w[k] for k in keep],
            self.mean[keep],
            self.cov[keep],
            self.interim_ess[keep],
        )

    def importance_terms(self, per_module):
        """:class:`ImportanceTerms` over at most ``per_module`` evenly thinned draws of each module."""
        tx, tl = [], []
        for x, lw in zip(self.x, self.log_w):
            k = even_indices(len(x), per_module)
            tx.append(x[k])
            tl.append(lw[k] - special.logsumexp(lw[k]))
        return ImportanceTerms(tx, tl)


def _likelihood_weights(mid, a, coords, log_interim_prior):
    """Self-normalised log weights ``1 / pi_interim`` (in ``x``) of one module's SI draws ``a``."""
    lp = np.asarray(log_interim_prior(a), dtype=float).reshape(-1)
    if lp.shape != (len(a),):
        raise ModelError(f"log_interim_prior returned shape {lp.shape} for module '{mid}', expected ({len(a)},)")
    if not np.all(np.isfinite(lp)):
        raise ModelError(
            f"module '{mid}': the interim prior is not finite at {int((~np.isfinite(lp)).sum())} "
            "draws (were these draws made under this prior?)"
        )
    lw = -(lp + coords.log_jacobian(a))
    lw -= special.logsumexp(lw)
    return lw


def module_summaries(ids, arrays, pop, log_interim_prior):
    """:class:`ModuleSummaries` of checked SI draws.

    Parameters
    ----------
    ids : tuple of str
    arrays : list of ndarray (M_i, 5)
        Posterior draws in SI, MODULE_PARAMETERS order.
    pop : .model.Population
    log_interim_prior : callable
        ``f(theta (n, 5)) -> (n,)``: the log density the draws were made under.

    Raises
    ------
    ModelError
        The interim prior is not finite at a draw, or a module's draws are degenerate.
    """
    xs, lws, ms, Cs, ess = [], [], [], [], []
    for mid, a in zip(ids, arrays):
        x = pop.coords.to_x(a)
        lw = _likelihood_weights(mid, a, pop.coords, log_interim_prior)
        w = np.exp(lw)
        m = w @ x
        d = x - m
        C = (d * w[:, None]).T @ d
        ev = np.linalg.eigvalsh(C)
        if not ev.min() > DEGENERATE_EIGEN_RATIO * ev.max():
            raise ModelError(
                f"module '{mid}': the draws are degenerate (their covariance is singular); "
                "parameters must not be exact functions of each other"
            )
        xs.append(x)
        lws.append(lw)
        ms.append(m)
        Cs.append(C)
        ess.append(1.0 / (w * w).sum())
    return ModuleSummaries(x=xs, log_w=lws, mean=np.array(ms), cov=np.array(Cs), interim_ess=np.array(ess))
