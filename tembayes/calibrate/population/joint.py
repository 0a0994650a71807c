"""The joint fit: module parameters and hyperparameters sampled together, the check of the two-stage fit."""

from __future__ import annotations

import time

import numpy as np
from scipy import optimize

from tembayes.calibrate.population.hyper import HyperPosterior, start_walkers
from tembayes.calibrate.population.inputs import check_modules, sampler_seed
from tembayes.calibrate.population.membership import Membership, odd_one, rao_blackwell, thinned_iterations
from tembayes.calibrate.population.model import (
    LEVEL,
    N_HYPER,
    N_PARAMS,
    OUTLIER_FRACTION_PRIOR,
    OUTLIER_SCALE,
    Population,
)
from tembayes.calibrate.population.result import assemble
from tembayes.calibrate.population.sampling import POPULATION_TARGETS, Budget, run_emcee
from tembayes.calibrate.population.terms import GaussianTerms
from tembayes.common.provenance import versions
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import ModelError

#: Default start of the slopes' mode search, in their prior sds (most modules rise with T).
SLOPE_START_SDS = 0.3
#: Walkers' start: jitter of the hyper part [sampler units], fraction of each module's likelihood sd.
START_JITTER_HYPER, START_FRACTION_MODULE = 0.05, 0.5
#: Default number of walkers is at least this.
MIN_WALKERS = 64
#: Hessian by central differences: first step [x units] and refinements.
HESSIAN_STEP, HESSIAN_ROUNDS = 1e-4, 3


def _hessian(f, x):
    """Hessian of ``f`` at ``x`` by central differences, the step adapted to the curvature."""
    h = np.full(N_PARAMS, HESSIAN_STEP)
    for _ in range(HESSIAN_ROUNDS):
        d2 = np.array([(f(x + h * e) - 2 * f(x) + f(x - h * e)) / h[k] ** 2 for k, e in enumerate(np.eye(N_PARAMS))])
        h = np.where(d2 < 0, 0.1 / np.sqrt(np.maximum(-d2, 1e-30)), h * 10)
    H = np.empty((N_PARAMS, N_PARAMS))
    E = np.eye(N_PARAMS) * h
    for a in range(N_PARAMS):
        for b in range(a, N_PARAMS):
            H[a, b] = H[b, a] = (f(x + E[a] + E[b]) - f(x + E[a] - E[b]) - f(x - E[a] + E[b]) + f(x - E[a] - E[b])) / (
                4 * h[a] * h[b]
            )
    return H


def laplace(loglike, mid, coords, x0, prior_sd):
    """Mode and covariance (in ``x``) of one module's likelihood, for initialisation.

    A weak Gaussian term (the interim prior's scale ``prior_sd``) keeps the
    search finite where the likelihood is flat; the covariance is the
    inverse of a finite-difference Hessian of the log likelihood alone.

    Returns
    -------
    x : ndarray (5,)
    cov : ndarray (5, 5)
    """

    def f(x):
        v = np.asarray(loglike(coords.to_theta(x[None, :])), dtype=float).reshape(-1)
        if v.shape != (1,):
            raise ModelError(f"loglike of module '{mid}' must return shape (n,) for theta (n, 5), got {v.shape}")
        return v[0]

    def nlp(x):
        v = f(x)
        return -v + 0.5 * (((x - x0) / prior_sd) ** 2).sum() if np.isfinite(v) else 1e300

    if not np.isfinite(f(x0)):
        raise ModelError(f"module '{mid}': loglike is not finite at the start values; pass start=")
    x = optimize.minimize(nlp, x0, method="Powell", options={"xtol": 1e-10, "ftol": 1e-12, "maxfev": 40000}).x
    x = optimize.minimize(nlp, x, method="BFGS").x
    ev, V = np.linalg.eigh(-_hessian(f, x))
    if not np.all(ev > 0):
        raise ModelError(f"module '{mid}': the likelihood has no well-defined maximum (Hessian not negative definite)")
    return x, (V / ev) @ V.T


class JointPosterior:
    """Log posterior of (hyperparameters, module coordinates) for :func:`joint_fit`.

    Sampler vector: the hyper part ``u`` of :class:`.hyper.HyperPosterior`,
    then per module and parameter either ``xi`` (centred: ``x = m + s xi``,
    ``m, s`` the module likelihood's mode and sd) or ``eta`` (non-centred:
    ``x = mu + tau eta``).  Non-centred is used for parameters whose
    likelihood is wider than the population spread (typically the slopes),
    centred otherwise: each avoids the funnel the other would have.
    """

    def __init__(self, hyper, loglikes, ids, m, s, noncentred):
        self.hyper = hyper
        self.pop = hyper.pop
        self.loglikes = [loglikes[i] for i in ids]
        self.m, self.s = m, s
        self.nc = noncentred  # (5,) bool
        self.N = len(ids)

    def split(self, v):
        """Sampler vectors (W, 11 + 5N) -> natural hyper (W, 11), x (W, N, 5)."""
        W = len(v)
        h = self.hyper.natural(v[:, :N_HYPER])
        z = v[:, N_HYPER:].reshape(W, self.N, N_PARAMS)
        with np.errstate(over="ignore", invalid="ignore"):  # far proposals are refused by the prior box
            mu, tau = h[:, None, :N_PARAMS], np.exp(h[:, None, N_PARAMS : 2 * N_PARAMS])
            x = np.where(self.nc, mu + tau * z, self.m + self.s * z)
        return h, x

    def join(self, h, x):
        """Natural hyper (W, 11) and x (W, N, 5) -> sampler vectors."""
        mu, tau = h[:, None, :N_PARAMS], np.exp(h[:, None, N_PARAMS : 2 * N_PARAMS])
        z = np.where(self.nc, (x - mu) / tau, (x - self.m) / self.s)
        return np.concatenate([self.hyper.from_natural(h), z.reshape(len(h), -1)], axis=1)

    def __call__(self, v):
        """Log posterior density of sampler vectors (W, 11 + 5N) -> (W,)."""
        W = len(v)
        u = v[:, :N_HYPER]
        h, x = self.split(v)
        lp = self.pop.log_prior(h) + np.log(self.hyper.scale(u[:, N_PARAMS : 2 * N_PARAMS])).sum(axis=1)
        out = np.full(W, -np.inf)
        ok = np.isfinite(lp)
        if not ok.any():
            return out
        h, x, lp = h[ok], x[ok], lp[ok]
        mu, tau, _, logeps, log1m = self.pop.unpack(h)
        if not np.all(np.isfinite(x)):
            bad = ~np.isfinite(x).all(axis=(1, 2))
            lp[bad] = -np.inf
            x[bad] = self.m
        lmix, _ = self.pop.log_density(x, mu, tau, logeps, log1m)
        # non-centred coordinates: the Jacobian dx/deta = tau cancels the density's 1/tau
        lmix = lmix + (np.log(tau)[:, None, :] * self.nc).sum(axis=2)
        total = lp + lmix.sum(axis=1)
        theta = self.pop.coords.to_theta(x)
        for i, f in enumerate(self.loglikes):
            ll = np.asarray(f(theta[:, i, :]), dtype=float).reshape(-1)
            total = total + ll
        out[ok] = np.where(np.isfinite(total), total, -np.inf)
        return out


def _likelihood_modes(loglikes, ids, pop, start):
    """Modes ``m`` (N, 5) and covariances ``C`` (N, 5, 5) in ``x`` of the module likelihoods."""
    x0 = pop.mu_mean.copy()
    x0[~LEVEL] = pop.mu_sd[~LEVEL] * SLOPE_START_SDS
    starts = {}
    for mid in ids:
        if start is not None and mid in start:
            th = np.asarray(start[mid], dtype=float).reshape(-1)
            if th.shape != (N_PARAMS,) or not np.all(np.isfinite(th)) or np.any(th[LEVEL] <= 0):
                raise ModelError(f"start['{mid}'] must be 5 finite SI values with R0, S0, K > 0, got {start[mid]!r}")
            starts[mid] = pop.coords.to_x(th)
        else:
            starts[mid] = x0
    modes, covs = zip(*(laplace(loglikes[mid], mid, pop.coords, starts[mid], pop.mu_sd) for mid in ids))
    return np.array(modes), np.array(covs)


def _joint_start(post, u0, C, rng, nwalkers):
    """Walkers: a hyper ball around the hyper-MAP walkers ``u0``, modules around their likelihood modes."""
    hyper = post.hyper
    uh = u0[rng.integers(0, len(u0), nwalkers)] + START_JITTER_HYPER * rng.standard_normal((nwalkers, N_HYPER))
    h = hyper.natural(uh)
    z = rng.standard_normal((nwalkers, post.N, N_PARAMS))
    x = post.m + START_FRACTION_MODULE * np.einsum("ijk,wik->wij", np.linalg.cholesky(C), z)
    return post.join(h, x)


def _joint_membership(post, kept, n_draws):
    """The :class:`Membership` of ``P(member | x_i, alpha)`` at about ``n_draws`` joint draws."""
    n_keep, W, ndim = kept.shape
    idx = thinned_iterations(n_keep, W, n_draws)
    hs, xs = post.split(kept[idx].reshape(-1, ndim))
    mu, tau, _, logeps, log1m = post.pop.unpack(hs)
    _, lmem = post.pop.log_density(xs, mu, tau, logeps, log1m)
    p_out, mcse = rao_blackwell(np.exp(lmem).reshape(len(idx), W, -1))
    return Membership(p_out, mcse, *odd_one(lmem))


def joint_fit(
    loglikes,
    datasheet,
    *,
    rng,
    max_steps=200000,
    max_seconds=None,
    progress=False,
    spread_prior=None,
    outlier_fraction_prior=OUTLIER_FRACTION_PRIOR,
    outlier_scale=OUTLIER_SCALE,
    nwalkers=None,
    n_predictive=4000,
    n_rao_blackwell=2048,
    convergence=POPULATION_TARGETS,
    start=None,
):
    """Module parameters and hyperparameters sampled together (the check of the two-stage fit).

    Same population model and hyperpriors as :func:`.fit.fit_population`, but
    each module enters through its likelihood instead of posterior draws, so
    no interim prior and no approximation are involved.  The cost grows with
    ``11 + 5 N`` sampled dimensions: meant for small batches.

    Parameters
    ----------
    loglikes : dict
        Module id -> callable ``loglike(theta) -> (n,)`` log likelihood for
        ``theta`` (n, 5) SI in MODULE_PARAMETERS order (vectorised).
    datasheet : tembayes.data.Datasheet
    rng : numpy.random.Generator
    max_steps, max_seconds, progress, spread_prior, outlier_fraction_prior, outlier_scale, n_predictive,
    n_rao_blackwell, convergence
        As in :func:`.fit.fit_population`.
    nwalkers : int, optional
        Default ``max(64, 2 * ndim + 2)``, ``ndim = 11 + 5 N``.
    start : dict, optional
        Module id -> (5,) SI parameters to start each module's likelihood-mode
        search from (default: the datasheet values, slopes +0.3 %/K).

    Returns
    -------
    PopulationResult
        ``diagnostics`` cover every sampled dimension (hyper and module).
        ``outlier_prob`` averages ``P(member | x_i, alpha)`` over the joint draws.
    """
    budget = Budget(max_steps, max_seconds, progress, convergence)
    ids = check_modules(loglikes, "loglikes")
    for mid in ids:
        if not callable(loglikes[mid]):
            raise ModelError(f"module '{mid}': loglike must be callable, got {type(loglikes[mid]).__name__}")
    seed = sampler_seed(rng)
    t0 = time.perf_counter()
    pop = Population(
        datasheet, spread_prior=spread_prior, outlier_fraction_prior=outlier_fraction_prior, outlier_scale=outlier_scale
    )
    m, C = _likelihood_modes(loglikes, ids, pop, start)
    hyper = HyperPosterior(pop, GaussianTerms(m, C), m, C)
    u0 = start_walkers(hyper, m, C, rng, 2 * N_HYPER + 2)
    tau_hat = np.exp(np.median(hyper.natural(u0)[:, N_PARAMS : 2 * N_PARAMS], axis=0))
    s = np.sqrt(np.einsum("ijj->ij", C))
    noncentred = np.median(s, axis=0) > tau_hat
    post = JointPosterior(hyper, loglikes, ids, m, s, noncentred)
    ndim = N_HYPER + N_PARAMS * len(ids)
    W = nwalkers or max(MIN_WALKERS, 2 * ndim + 2 + (ndim % 2))
    if W < 2 * ndim or W % 2:
        raise ModelError(f"nwalkers must be even and >= {2 * ndim}, got {W}")
    p0 = _joint_start(post, u0, C, rng, W)
    kept, diag = run_emcee(post, p0, seed, budget, label="joint population fit")
    members = _joint_membership(post, kept, n_rao_blackwell)
    diag.update(
        {
            "method": "joint",
            "noncentred": {p: bool(b) for p, b in zip(MODULE_PARAMETERS, noncentred)},
            "versions": versions(),
            "elapsed_s": float(time.perf_counter() - t0),
        }
    )
    return assemble(pop, ids, post.hyper.natural(kept[:, :, :N_HYPER]), members, rng, n_predictive, diag)
