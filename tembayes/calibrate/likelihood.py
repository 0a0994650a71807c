"""The step-response likelihood.

For every step window ``k`` and channel ``c`` (voltage, sensor dT, sensor
mean temperature) the residual ``r = observed - predicted`` is modelled as

    r_i = b_kc + e_i,   e_i ~ N(0, (s_c sigma_c)^2) independent,
    b_kc ~ N(0, beta_c^2)  (one offset per window and channel)

``sigma_c`` is the measurement noise estimated from the run itself (second
differences); ``s_c`` scales it (inferred, prior log-normal around 1).  The
window offset ``b_kc`` is the model discrepancy: no rig model is exact, and
with ~50 samples per window at sensor noise the data resolve a level error
of a millikelvin.  Left out, a 1-2 mK mismatch in a few windows drags the
slopes R1 and S1 by several posterior sd (measured on the virtual bench);
with it, the windows must agree with each other *as well as the model
explains them*, and the scatter of their levels sets how much the levels
say.  ``beta_c`` is inferred (log-normal prior), so a well-fitting model
loses nothing.  Because the offset is common to the whole window, including
the samples just before the step, it cannot absorb the voltage jump.

The offsets are integrated out analytically: within a window the residuals
are jointly normal with covariance ``sigma^2 I + beta^2 1 1^T``, whose
inverse and determinant are closed-form.

The model is driven by the hold currents, which are *measured*: each level
is the mean of a hold's samples, uncertain by ``level_sd`` (~0.02 mA).  That
is tiny, but dT responds at ~30 K/A, so a level error moves a hold's steady
dT by ~0.7 mK -- as much as the sensors resolve a level -- and left out it
made the slopes' posteriors ~20 % too narrow.  The errors ``dI_h`` are
integrated out too (:class:`LevelErrors`): the prediction is linear in them
(``G_h = d prediction / d level_h``, computed once at the posterior mode), so
with ``dI ~ N(0, diag(level_sd^2))`` the residuals are jointly normal with
covariance ``Sigma + G S G^T`` and the Woodbury identity and the matrix
determinant lemma give its log density from ``Sigma``'s.  A hold's level
reaches the window of the step into it and the next one (its pre-step
samples, then the decay) -- further on it has decayed to ~1 % of the noise
(``level_band_neglected`` in the diagnostics) -- so the ``dI`` precision
matrix is tridiagonal and costs ``O(holds)``.

:meth:`StepLikelihood.log_likelihood` takes a parameter mapping (the pure
function of the style guide); :meth:`StepLikelihood.pointwise` the sampler's
coordinate vectors, vectorised over walkers, and returns one log-likelihood
term per step window (the ``log_likelihood`` group of ``posterior.nc``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numba import njit

from tembayes.calibrate.priors import ParameterPrior
from tembayes.calibrate.stepdata import CHANNELS

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tembayes.calibrate.stepdata import StepData

#: Names of the noise parameters, per channel: scale of the measurement
#: noise (dimensionless) and the sd of the window offsets (channel unit).
NOISE_SCALE = tuple(f"noise_scale_{c.split('_')[0]}" for c in CHANNELS)
OFFSET_SD = tuple(f"offset_sd_{c}" for c in CHANNELS)
NOISE_PARAMETERS = NOISE_SCALE + OFFSET_SD


def noise_priors(data: StepData) -> tuple[ParameterPrior, ...]:
    """Priors of the noise parameters for a :class:`StepData`.

    ``s_c``: log-normal around 1, log-sd 0.5 (the second-difference
    estimate is good to ~10 %, but allow for coloured noise).  ``beta_c``:
    log-normal around 10x the noise's sd of a window mean (~ ``sigma``), log-sd 2: a
    level error anywhere from 0.02x to 50x the noise is plausible a priori.
    """
    pri = [ParameterPrior(n, "lognormal", 1.0, 0.5) for n in NOISE_SCALE]
    pri += [ParameterPrior(n, "lognormal", float(s), 2.0) for n, s in zip(OFFSET_SD, 0.2 * data.noise)]
    return tuple(pri)


def _window_terms(S1, S2, n, sigma, beta):
    """Window log-likelihood from residual sums ``S1``, ``S2`` (nw, nc, ns)."""
    s2 = (sigma * sigma)[:, :, None]
    b2 = (beta * beta)[:, :, None]
    quad = (S2 - b2 / (s2 + n * b2) * S1 * S1) / s2
    logdet = n * np.log(s2) + np.log1p(n * b2 / s2)
    return (-0.5 * (quad + logdet + n * np.log(2.0 * np.pi))).sum(axis=1)


def window_loglike(R: np.ndarray, starts: np.ndarray, sigma: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Log-likelihood of residuals with a random offset per window.

    Parameters
    ----------
    R : ndarray, shape (nw, nc, n)
        Residuals; window ``k`` is ``R[..., starts[k]:starts[k+1]]``.
    starts : ndarray of int, shape (ns,)
        First sample of every window (windows are contiguous).
    sigma, beta : ndarray, shape (nw, nc)
        Noise sd and offset sd.

    Returns
    -------
    ndarray, shape (nw, ns)
        Log-likelihood of every window (channels summed).
    """
    n = np.diff(np.append(starts, R.shape[2])).astype(float)  # (ns,)
    S1 = np.add.reduceat(R, starts, axis=2)  # (nw, nc, ns)
    S2 = np.add.reduceat(R * R, starts, axis=2)
    return _window_terms(S1, S2, n, sigma, beta)


@njit(cache=True)
def _tridiagonal_terms(u, d, off):
    """Per-hold terms ``y_h^2 / (2 D_h) - log(D_h) / 2`` of a tridiagonal quadratic form.

    From the LDL^T factorisation of the tridiagonal ``P`` (diagonal ``d``,
    off-diagonal ``off``) and the forward solve ``L y = u``: summed, they are
    ``u^T P^-1 u / 2 - log det P / 2``.
    """
    nw, nh = u.shape
    out = np.empty((nw, nh))
    for w in range(nw):
        D = d[w, 0]
        y = u[w, 0]
        out[w, 0] = 0.5 * y * y / D - 0.5 * np.log(D)
        for h in range(1, nh):
            lo = off[w, h - 1] / D
            D = d[w, h] - lo * off[w, h - 1]
            y = u[w, h] - lo * y
            out[w, h] = 0.5 * y * y / D - 0.5 * np.log(D)
    return out


class LevelErrors:
    """The hold-current errors, integrated out of the likelihood.

    Parameters
    ----------
    response : ndarray, shape (nh, nc, n)
        ``d prediction / d level_h`` of every channel at every sample
        (:meth:`~tembayes.calibrate.model.StepResponseModel.level_jacobian`).
    level_sd : ndarray, shape (nh,)
        Standard error of each level [A].
    starts : ndarray of int, shape (ns,)
        First sample of every window; ``nh = ns + 1`` (window ``s`` follows
        the step from hold ``s`` into hold ``s + 1``).
    noise : ndarray, shape (nc,), optional
        Noise sd of each channel, to report :attr:`neglected`.

    Window ``s`` keeps the responses to holds ``s`` and ``s + 1`` only
    (``self.band``, shape ``(2, nc, n)``); :attr:`neglected` is the largest
    dropped response times ``level_sd`` over the noise (~0.01 on the bench).
    """

    def __init__(self, response, level_sd, starts, noise=None):
        nh, nc, n = response.shape
        ns = len(starts)
        if nh != ns + 1:
            raise ValueError(f"{nh} level responses for {ns} step windows (need windows + 1)")
        win = np.repeat(np.arange(ns), np.diff(np.append(starts, n)))
        i = np.arange(n)
        band = np.stack([response[win, :, i].T, response[win + 1, :, i].T])  # (2, nc, n)
        self.band = np.ascontiguousarray(band)
        self.starts = starts
        self.s2inv = 1.0 / np.asarray(level_sd, dtype=float) ** 2
        self.g1 = np.add.reduceat(band, starts, axis=2)  # (2, nc, ns)
        self.GG = np.stack(
            [
                np.add.reduceat(band[0] * band[0], starts, axis=1),
                np.add.reduceat(band[0] * band[1], starts, axis=1),
                np.add.reduceat(band[1] * band[1], starts, axis=1),
            ]
        )  # (3, nc, ns)
        self.neglected = 0.0
        if noise is not None:
            rest = response.copy()
            rest[win, :, i] = 0.0
            rest[win + 1, :, i] = 0.0
            self.neglected = float(
                np.max(np.abs(rest) * np.asarray(level_sd)[:, None, None] / np.asarray(noise)[None, :, None])
            )

    def projections(self, R: np.ndarray) -> np.ndarray:
        """``sum_window r G`` of residuals ``R`` ``(nw, nc, n)`` -> ``(nw, 2, nc, ns)``."""
        return np.add.reduceat(R[:, None] * self.band[None], self.starts, axis=3)

    def terms(self, GR: np.ndarray, S1: np.ndarray, n: np.ndarray, sigma: np.ndarray, beta: np.ndarray) -> np.ndarray:
        """Log-likelihood correction of every window ``(nw, ns)``.

        ``GR``: :meth:`projections` of the residuals; ``S1`` their window sums
        ``(nw, nc, ns)``; ``n`` window sizes; ``sigma``, ``beta`` ``(nw, nc)``.
        A hold's term goes to the window of the step into it (hold 0 to the
        first window), so the windows' terms still sum to the total.
        """
        iv = (1.0 / (sigma * sigma))[:, :, None]
        b2 = (beta * beta)[:, :, None]
        k = b2 / (sigma[:, :, None] ** 2 + n * b2)  # (nw, nc, ns)
        g0, g1 = self.g1
        u0 = np.sum(iv * (GR[:, 0] - k * g0 * S1), axis=1)  # (nw, ns)
        u1 = np.sum(iv * (GR[:, 1] - k * g1 * S1), axis=1)
        d0 = np.sum(iv * (self.GG[0] - k * g0 * g0), axis=1)
        d1 = np.sum(iv * (self.GG[2] - k * g1 * g1), axis=1)
        off = np.sum(iv * (self.GG[1] - k * g0 * g1), axis=1)
        nw, ns = u0.shape
        u = np.zeros((nw, ns + 1))
        u[:, :ns] += u0
        u[:, 1:] += u1
        d = np.repeat(self.s2inv[None, :], nw, axis=0)
        d[:, :ns] += d0
        d[:, 1:] += d1
        per_hold = _tridiagonal_terms(u, d, np.ascontiguousarray(off)) + 0.5 * np.log(self.s2inv)[None, :]
        out = per_hold[:, 1:].copy()
        out[:, 0] += per_hold[:, 0]
        return out


class _ExpansionSums:
    """Window sums of an expansion's residual, exactly, without the samples.

    With ``r = e - J d - C d^2 / 2 - H d_i d_j`` (``e = obs - f0``) every
    window's ``sum r`` and ``sum r^2`` are a linear and a quadratic form in
    ``z = (1, -d, -d^2/2, -d_i d_j)``; their coefficients are summed once, so
    a likelihood call costs ``O(windows x m^2)`` instead of
    ``O(samples x m)``.
    """

    def __init__(self, obs, lin, starts, levels=None):
        p = lin.J.shape[0]
        e = obs - lin.f0  # (nc, n)
        H = getattr(lin, "H", np.zeros((0,) + e.shape))
        self.pairs = getattr(lin, "pairs", np.zeros((0, 2), int))
        Q = np.concatenate([e[None], lin.J, lin.C, H], axis=0)  # (m, nc, n)
        m, nc, n = Q.shape
        self.M1 = np.add.reduceat(Q, starts, axis=2)  # (m, nc, ns)
        outer = Q[:, None] * Q[None, :]  # (m, m, nc, n)
        G = np.add.reduceat(outer, starts, axis=3)  # (m, m, nc, ns)
        self.G = np.ascontiguousarray(G.reshape(m, m * nc * len(starts)))
        self.m, self.nc, self.ns, self.p = m, nc, len(starts), p
        # the residual's projections on the level responses: linear in z too
        self.GQ = None if levels is None else np.add.reduceat(Q[:, None] * levels.band[None], starts, axis=3)

    def sums(self, D):
        nw = D.shape[0]
        z = np.concatenate(
            [np.ones((nw, 1)), -D, -0.5 * D * D, -D[:, self.pairs[:, 0]] * D[:, self.pairs[:, 1]]], axis=1
        )  # (nw, m)
        S1 = np.einsum("wm,mcs->wcs", z, self.M1)
        T = (z @ self.G).reshape(nw, self.m, self.nc, self.ns)
        S2 = np.einsum("wm,wmcs->wcs", z, T)
        GR = None if self.GQ is None else np.einsum("wm,macs->wacs", z, self.GQ)
        return S1, S2, GR


class StepLikelihood:
    """Likelihood of a run's step responses.

    Parameters
    ----------
    data : StepData
    model : StepResponseModel or LinearisedModel
        Anything with ``predict``: the exact model takes a parameter mapping,
        the linearised one coordinate vectors.
    space : ParameterSpace
        The sampled coordinates, including :data:`NOISE_PARAMETERS`.
    levels : LevelErrors, optional
        The hold-current errors to integrate out (none if not given).
    """

    def __init__(self, data, model, space, levels=None):
        self.data = data
        self.model = model
        self.space = space
        self.starts = data.window_starts
        if len(self.starts) != data.n_steps or np.any(np.diff(data.step) < 0):
            raise ValueError("step windows must be contiguous and ordered")
        self._ni = [space.index(n) for n in NOISE_SCALE]
        self._bi = [space.index(n) for n in OFFSET_SD]
        self.model_names = tuple(n for n in space.names if n not in NOISE_PARAMETERS)
        self._mi = [space.index(n) for n in self.model_names]
        self._n = np.diff(np.append(self.starts, data.obs.shape[1])).astype(float)
        self.levels = levels
        self._sums = _ExpansionSums(data.obs, model, self.starts, levels) if hasattr(model, "C") else None

    def _noise(self, X):
        vals = np.exp(X[:, self._ni]) * self.data.noise[None, :], np.exp(X[:, self._bi])
        return vals

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Model channels ``(nw, 3, n)`` for coordinate vectors ``X``."""
        if hasattr(self.model, "x0"):
            return self.model.predict(X[:, self._mi])
        # a draw whose simulation fails is NaN here and impossible below
        return self.model.predict(self.space.params(X, self.model_names), strict=False)

    def pointwise(self, X: np.ndarray, Y: np.ndarray | None = None) -> np.ndarray:
        """Log-likelihood of every step window, ``(nw, ns)``.

        ``Y``: predictions for ``X`` if already computed.
        """
        X = np.atleast_2d(X)
        sigma, beta = self._noise(X)
        if Y is None and self._sums is not None:
            S1, S2, GR = self._sums.sums(X[:, self._mi] - self.model.x0)
            ll = _window_terms(S1, S2, self._n, sigma, beta)
        else:
            if Y is None:
                Y = self.predict(X)
            R = self.data.obs[None] - Y
            ll = window_loglike(R, self.starts, sigma, beta)
            if self.levels is not None:
                S1, GR = np.add.reduceat(R, self.starts, axis=2), self.levels.projections(R)
        if self.levels is not None:
            ll = ll + self.levels.terms(GR, S1, self._n, sigma, beta)
        ll[np.isnan(ll)] = -np.inf
        return ll

    def log_likelihood_x(self, X: np.ndarray) -> np.ndarray:
        """Total log-likelihood ``(nw,)`` of coordinate vectors ``(nw, p)``."""
        return self.pointwise(X).sum(axis=1)

    def log_likelihood(self, params: Mapping[str, float]) -> float:
        """Log-likelihood of one parameter mapping ``name -> value`` (SI)."""
        x = self.space.to_x(params)
        return float(self.log_likelihood_x(x[None])[0])

    def log_prob(self, X: np.ndarray) -> np.ndarray:
        """Log posterior density of coordinate vectors ``(nw, p)`` -> ``(nw,)``.

        ``-inf`` outside the prior's support; the sampler's callable.
        """
        X = np.atleast_2d(X)
        lp = self.space.log_prior(X)
        ok = np.isfinite(lp)
        out = np.full(X.shape[0], -np.inf)
        if np.any(ok):
            out[ok] = lp[ok] + self.log_likelihood_x(X[ok])
        return out
