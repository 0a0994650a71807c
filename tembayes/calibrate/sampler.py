"""emcee until converged, with an HDF checkpoint that survives ``kill -9``.

The moves are differential evolution (80 %) and DE snooker (20 %): on the
correlated ~20-dimensional posteriors here their autocorrelation time is
about a third of the stretch move's (``api-notes``).  The first fifth of the
chain is discarded as burn-in.  The run length is set by convergence, checked
every ``check_every`` stored iterations at *fixed* iteration counts (so a resumed run stops exactly where
an uninterrupted one would):

- the chain after burn-in is at least ``min_tau_multiple`` (50) integrated
  autocorrelation times long, for every coordinate;
- rank-normalised split R-hat <= 1.01 and bulk ESS >= 1000 for every
  monitored parameter (the five module parameters), computed by arviz with
  the walkers as chains.  Ensemble walkers are not independent chains, so
  R-hat is a heuristic here (arviz#2156); it does catch stuck walkers.

A budget (``max_steps``) ends a run that does not converge, with a warning
and ``converged = False``.

Every stored iteration is written to an :class:`emcee.backends.HDFBackend`
(``thin_by`` steps per stored iteration, so the file is written every
``thin_by`` steps, not every step): a killed run loses at most ``thin_by``
steps and ``resume=True`` continues from the stored walkers and random
state, bit-identically.  Seeding follows ``shared/notes/api-notes.md``: the
sampler's private ``RandomState`` is set from the run's seed, never from the
global one.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass

import arviz as az
import emcee
import numpy as np
from threadpoolctl import threadpool_limits

#: Convergence targets (issue 4).
MIN_TAU_MULTIPLE = 50.0
RHAT_MAX = 1.01
ESS_MIN = 1000.0


@dataclass(frozen=True)
class SamplerRun:
    """Result of :func:`sample`.

    Attributes
    ----------
    chain : ndarray, shape (n, nw, p)
        Stored iterations after burn-in (coordinates).
    log_prob : ndarray, shape (n, nw)
    acceptance : ndarray, shape (nw,)
        Acceptance fraction of every walker.
    tau : ndarray, shape (p,)
        Integrated autocorrelation time of every coordinate [steps].
    rhat, ess_bulk, ess_tail : ndarray, shape (p,)
        arviz diagnostics over the stored chain (walkers as chains).
    steps : int
        Total sampler steps (including burn-in).
    burn : int
        Discarded stored iterations.
    thin_by : int
    converged : bool
    resumed : bool
    """

    chain: np.ndarray
    log_prob: np.ndarray
    acceptance: np.ndarray
    tau: np.ndarray
    rhat: np.ndarray
    ess_bulk: np.ndarray
    ess_tail: np.ndarray
    steps: int
    burn: int
    thin_by: int
    converged: bool
    resumed: bool


def random_state(seed):
    """A legacy ``RandomState`` state tuple for emcee from an integer seed."""
    return np.random.RandomState(int(seed) % (2 ** 32)).get_state()


def diagnostics(chain, monitor):
    """R-hat, bulk and tail ESS of coordinates of a ``(n, nw, p)`` chain.

    Only the ``monitor`` coordinates are computed; the others are NaN.
    """
    p = chain.shape[2]
    rhat = np.full(p, np.nan)
    ess_b = np.full(p, np.nan)
    ess_t = np.full(p, np.nan)
    # arviz wants (chain, draw): walkers are the chains
    for j in monitor:
        x = np.ascontiguousarray(chain[:, :, j].T)
        rhat[j] = float(az.rhat(x))
        ess_b[j] = float(az.ess(x, method="bulk"))
        ess_t[j] = float(az.ess(x, method="tail"))
    return rhat, ess_b, ess_t


def _burn(n):
    """Burn-in of a chain of ``n`` stored iterations: the first fifth."""
    return n // 5


def sample(log_prob, p0, *, seed, monitor, backend=None, resume=False, thin_by=10, check_every=100,
           max_steps=60000, progress=False, label=""):
    """Run emcee until the convergence targets are met or the budget runs out.

    Parameters
    ----------
    log_prob : callable
        ``f(X (nw, p)) -> (nw,)`` log posterior density (vectorised).
    p0 : ndarray, shape (nw, p)
        Initial walkers.
    seed : int
        Seed of the sampler's random state.
    monitor : sequence of int
        Coordinates that must reach the R-hat and ESS targets.
    backend : str or Path, optional
        HDF5 checkpoint file (one per module); in memory if None.
    resume : bool
        Continue the run stored in ``backend`` (its walkers and random
        state); start afresh if it holds none.
    thin_by : int
        Steps per stored iteration (and per checkpoint write).
    check_every : int
        Stored iterations between convergence checks.
    max_steps : int
        Budget of sampler steps.
    progress : bool
        tqdm progress bar.
    label : str
        Name shown on the progress bar.

    Returns
    -------
    SamplerRun
    """
    p0 = np.asarray(p0, dtype=float)
    nw, p = p0.shape
    de = [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    resumed = False
    if backend is not None:
        be = emcee.backends.HDFBackend(os.fspath(backend))
        if resume and os.path.exists(backend) and be.initialized and be.iteration > 0:
            if be.shape != (nw, p):
                raise ValueError(f"checkpoint {backend} holds {be.shape} walkers x parameters, expected {(nw, p)}")
            resumed = True
        else:
            be.reset(nw, p)
    else:
        be = emcee.backends.Backend()
    max_iter = max(check_every, max_steps // thin_by)
    kw = dict(thin_by=thin_by, progress=progress, progress_kwargs={"desc": label or "sampling", "leave": False})

    def run(sampler, n):
        start = p0 if sampler.iteration == 0 else None
        # one BLAS thread: the likelihood's products are small, and threads
        # fighting over 2 cores made them 30x slower
        with threadpool_limits(limits=1, user_api="blas"):
            sampler.run_mcmc(start, n, **kw)

    sampler = emcee.EnsembleSampler(nw, p, log_prob, vectorize=True, moves=de, backend=be)
    if sampler.iteration == 0:
        sampler.random_state = random_state(seed)
    converged = False
    while True:
        done = sampler.iteration
        target = min(max_iter, (done // check_every + 1) * check_every)
        if target > done:
            run(sampler, target - done)
        chain = sampler.get_chain()
        b = _burn(len(chain))
        post = chain[b:]
        tau = thin_by * emcee.autocorr.integrated_time(post, c=5, tol=0, quiet=True)
        rhat, ess_b, ess_t = diagnostics(post, monitor)
        long_enough = thin_by * len(post) >= MIN_TAU_MULTIPLE * np.max(tau)
        mon = list(monitor)
        converged = bool(long_enough and np.all(rhat[mon] <= RHAT_MAX) and np.all(ess_b[mon] >= ESS_MIN))
        if converged or sampler.iteration >= max_iter:
            break
    if not converged:
        warnings.warn(
            f"{label or 'sampler'}: not converged within {max_steps} steps "
            f"(max tau {np.max(tau):.0f} steps, R-hat max {np.nanmax(rhat):.3f}, bulk ESS min {np.nanmin(ess_b):.0f}); "
            "results are marked converged: false", RuntimeWarning, stacklevel=2)
    lp = sampler.get_log_prob()[b:]
    return SamplerRun(
        chain=post, log_prob=lp, acceptance=sampler.acceptance_fraction.copy(), tau=tau, rhat=rhat,
        ess_bulk=ess_b, ess_tail=ess_t, steps=int(sampler.iteration * thin_by), burn=b, thin_by=thin_by,
        converged=converged, resumed=resumed,
    )
