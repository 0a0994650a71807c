"""The hyperparameters' posterior in the sampler's coordinates, and where its walkers start."""

from __future__ import annotations

import math

import numpy as np
from scipy import optimize

from tembayes.calibrate.population import kernels
from tembayes.calibrate.population.model import N_PARAMS

#: Start ball (sampler coordinates): sd of ``nu``, of ``log tau`` and of ``logit f``.
START_SD_NU, START_SD_LOG_TAU, START_SD_LOGIT_F = 0.5, 0.2, 0.3
#: Walkers outside the prior box are redrawn this often, in a ball this much smaller.
START_RETRIES, START_SHRINK = 100, 0.1
#: Floor of the start spread, relative to the typical spread of the hyperprior.
START_TAU_FLOOR = 0.3
#: The start spreads lie within this many sds of their prior: a stated spread
#: (``--population-prior``) may be far tighter than a few units' scatter, and
#: a start outside the sampler's box leaves every walker at -inf.
START_PRIOR_SDS = 3.0
#: MAD -> sd of a Gaussian.
MAD_TO_SD = 1.4826


class HyperPosterior:
    """Log posterior of the hyperparameters, in the sampler's coordinates.

    The sampler moves ``u = (nu, log tau, logit f)`` with
    ``mu = mbar + nu * sqrt(tau^2 + cbar) / sqrt(N)``: given the spreads, the
    centre is known to about that sd, so ``nu`` is roughly standard normal
    whatever ``tau`` is.  Without this the (mu, log tau) funnel of small
    batches slows emcee down (autocorrelation time ~55 -> ~40 steps).

    Parameters
    ----------
    pop : .model.Population
    terms : .terms.GaussianTerms or .terms.ImportanceTerms
        The modules' likelihood terms.
    m : ndarray (N, 5)
        Module means in ``x``, for ``mbar``.
    C : ndarray (N, 5, 5)
        Module covariances in ``x``; ``cbar`` is the median of their diagonals.
    """

    def __init__(self, pop, terms, m, C):
        self.pop = pop
        self.terms = terms
        self.mbar = m.mean(axis=0)
        self.cbar = np.median(np.einsum("ijj->ij", C), axis=0)
        self.sqrt_n = math.sqrt(len(m))
        self._prior_args = (
            self.mbar,
            self.cbar,
            self.sqrt_n,
            pop.mu_mean,
            pop.mu_sd,
            pop.logtau_mean,
            pop.logtau_sd,
            pop.beta[0],
            pop.beta[1],
        )

    def scale(self, logtau):
        """``sqrt(tau^2 + cbar) / sqrt(N)``: the scale of ``nu`` (..., 5)."""
        with np.errstate(over="ignore"):
            return np.sqrt(np.exp(2.0 * logtau) + self.cbar) / self.sqrt_n

    def natural(self, u):
        """Sampler coordinates (..., 11) -> natural ``(mu, log tau, logit f)``."""
        u = np.asarray(u, dtype=float)
        h = u.copy()
        h[..., :N_PARAMS] = self.mbar + self.scale(u[..., N_PARAMS : 2 * N_PARAMS]) * u[..., :N_PARAMS]
        return h

    def from_natural(self, h):
        """Natural ``(mu, log tau, logit f)`` (..., 11) -> sampler coordinates."""
        u = np.asarray(h, dtype=float).copy()
        u[..., :N_PARAMS] = (h[..., :N_PARAMS] - self.mbar) / self.scale(h[..., N_PARAMS : 2 * N_PARAMS])
        return u

    def log_natural(self, h):
        """Log posterior density of natural hyperparameters (W, 11) -> (W,) (reference implementation)."""
        lp = self.pop.log_prior(h)
        out = np.full(len(h), -np.inf)
        ok = np.isfinite(lp)
        if ok.any():
            mu, tau, _, logeps, log1m = self.pop.unpack(h[ok])
            ll, _ = self.terms(self.pop, mu, tau, logeps, log1m)
            out[ok] = lp[ok] + ll.sum(axis=1)
        return np.where(np.isfinite(out), out, -np.inf)

    def __call__(self, u):
        """Log posterior density in sampler coordinates (W, 11) -> (W,) (the sampler's hot path)."""
        mu, tau, logeps, log1m, lp = kernels.hyper_prep(np.ascontiguousarray(u, dtype=float), *self._prior_args)
        ok = np.isfinite(lp)
        if not ok.all():
            if not ok.any():
                return lp
            mu, tau, logeps, log1m = mu[ok], tau[ok], logeps[ok], log1m[ok]
        ll, _ = self.terms(self.pop, mu, tau, logeps, log1m)
        lp[ok] += ll.sum(axis=1)
        return np.where(np.isfinite(lp), lp, -np.inf)


def _robust_start(post, m, C):
    """Sampler coordinates of robust moment estimates: median centres, MAD spreads net of the modules' sds."""
    pop = post.pop
    mu0 = np.median(m, axis=0)
    mad = MAD_TO_SD * np.median(np.abs(m - mu0), axis=0)
    meas = np.median(np.sqrt(np.einsum("ijj->ij", C)), axis=0)
    typical = np.exp(pop.logtau_mean)
    tau0 = np.sqrt(np.maximum(mad**2 - meas**2, (START_TAU_FLOOR * typical) ** 2))
    reach = START_PRIOR_SDS * pop.logtau_sd
    logtau0 = np.clip(np.log(tau0), pop.logtau_mean - reach, pop.logtau_mean + reach)
    a, b = pop.beta
    return post.from_natural(np.concatenate([mu0, logtau0, [np.log(a / b)]]))


def start_walkers(post, m, C, rng, nwalkers):
    """Walkers (sampler coordinates) around the hyper-MAP, found from robust moment estimates.

    Parameters
    ----------
    post : HyperPosterior
    m, C : ndarray
        As for :class:`HyperPosterior`.
    rng : numpy.random.Generator
    nwalkers : int

    Returns
    -------
    ndarray (nwalkers, 11)
        Every walker inside the prior box.
    """
    u0 = _robust_start(post, m, C)

    def nlp(u):
        v = post(u[None, :])[0]
        return -v if np.isfinite(v) else 1e300

    best = optimize.minimize(nlp, u0, method="Powell", options={"xtol": 1e-4, "ftol": 1e-9, "maxfev": 20000})
    u = best.x if np.isfinite(best.fun) and best.fun < nlp(u0) else u0
    # a ball emcee expands quickly
    scale = np.concatenate([np.full(N_PARAMS, START_SD_NU), np.full(N_PARAMS, START_SD_LOG_TAU), [START_SD_LOGIT_F]])
    p0 = u + scale * rng.standard_normal((nwalkers, len(u)))
    lp = post(p0)
    for _ in range(START_RETRIES):
        bad = ~np.isfinite(lp)
        if not bad.any():
            break
        p0[bad] = u + START_SHRINK * scale * rng.standard_normal((bad.sum(), len(u)))
        lp = post(p0)
    return p0


def sample_hyper(pop, terms, mean, cov, rng, nwalkers, budget, *, label, seed=None):
    """Sample the hyperposterior of module likelihood ``terms`` with emcee.

    Parameters
    ----------
    pop : .model.Population
    terms : GaussianTerms or ImportanceTerms
    mean, cov : ndarray, shapes (N, 5) and (N, 5, 5)
        The modules' likelihood moments (start and scale of the walkers).
    rng : numpy.random.Generator
        Starts the walkers (and draws the emcee seed after them when ``seed`` is None).
    nwalkers : int
    budget : .sampling.Budget
    label : str
    seed : int, optional

    Returns
    -------
    kept : ndarray, shape (n, W, 11)
        Natural hyper draws after burn-in.
    diag : dict
        The sampler's diagnostics (:func:`.sampling.run_emcee`).
    """
    from tembayes.calibrate.population.sampling import run_emcee

    post = HyperPosterior(pop, terms, mean, cov)
    p0 = start_walkers(post, mean, cov, rng, nwalkers)
    kept, diag = run_emcee(post, p0, int(rng.integers(2**32)) if seed is None else seed, budget, label=label)
    return post.natural(kept), diag
