"""Ornstein-Uhlenbeck models of residuals: maximum-likelihood fits on a grid of correlation times.

A residual ``r`` at sample times ``t`` is modelled as an OU disturbance ``d``
(stationary sd ``sd``, correlation time ``tau``: ``d' = -d/tau + w``), plus,
optionally, white measurement noise of known sd: ``r = d + v``.  Between two
samples ``dt`` apart the disturbance keeps the fraction
``phi = exp(-dt/tau)`` and gains variance ``sd^2 (1 - phi^2)`` (the exact
discretisation, so uneven sampling is handled).

Two fits share that model:

- without white noise (:func:`fit_ou`, ``white_sd=None``) the likelihood is
  the exact OU one and ``sd`` is profiled out in closed form for each ``tau``;
- with white noise of known sd a scalar Kalman filter gives the likelihood,
  vectorised over a ``(tau, sd)`` grid.  A plain OU fit of a residual that
  holds white noise spends its correlation time on the white noise (taus of
  a second on a 1 Hz residual); this one does not.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from numpy.typing import ArrayLike

#: Correlation times tried without white noise [s]: down to a twentieth of a
#: 1 Hz sample, since a residual that is nearly white must find a short tau.
TAUS_PLAIN_S = np.geomspace(0.05, 2e4, 80)
#: Correlation times tried with the white noise modelled [s]: below a sample
#: interval an OU disturbance is indistinguishable from the white noise.
TAUS_UNDER_WHITE_S = np.geomspace(1.0, 2e4, 48)
#: Disturbance sds tried with the white noise modelled: 0 and a geometric grid
#: up to twice the residual's sd (this many values in all).
N_SD_UNDER_WHITE = 48
#: Lowest grid sd, as a fraction of the residual's sd (the grid's top is twice it).
SD_GRID_LOW = 1e-3
SD_GRID_HIGH = 2.0


@dataclass(frozen=True)
class OUFit:
    """A fitted OU disturbance.

    Attributes
    ----------
    sd : float
        Stationary standard deviation of the disturbance [unit of the
        residual]; 0 when the residual is white noise only.
    tau_s : float
        Correlation time [s].
    """

    sd: float
    tau_s: float


def fit_ou(
    t: ArrayLike,
    r: ArrayLike,
    *,
    white_sd: float | None = None,
    taus: ArrayLike | None = None,
    n_sd: int = N_SD_UNDER_WHITE,
) -> OUFit:
    """Maximum-likelihood OU disturbance of residuals ``r`` at times ``t``.

    Parameters
    ----------
    t : array_like, shape (n,)
        Sample times [s], increasing.
    r : array_like, shape (n,)
        Residuals [any unit].
    white_sd : float, optional
        Sd of the white noise in ``r`` [unit of r], known; None: no white
        noise is modelled (the closed-form fit).
    taus : array_like, optional
        Correlation times tried [s]; default :data:`TAUS_PLAIN_S` without
        white noise, :data:`TAUS_UNDER_WHITE_S` with it.
    n_sd : int
        Disturbance sds tried with white noise (0 and ``n_sd - 1`` geometric
        values); unused without.

    Returns
    -------
    OUFit
    """
    t = np.asarray(t, float)
    r = np.asarray(r, float)
    if white_sd is not None:
        return _fit_under_white(t, r, float(white_sd), TAUS_UNDER_WHITE_S if taus is None else taus, n_sd)
    return _fit_plain(t, r, TAUS_PLAIN_S if taus is None else taus)


def _fit_plain(t, r, taus):
    """Exact OU likelihood, ``sd`` profiled out for each ``tau`` (the first best ``tau`` kept)."""
    dt = np.diff(t)
    best = None
    for tau in taus:
        phi = np.exp(-dt / tau)
        q = 1.0 - phi * phi
        innov = r[1:] - phi * r[:-1]
        s2 = (r[0] ** 2 + np.sum(innov * innov / q)) / len(r)
        ll = -0.5 * len(r) * np.log(s2) - 0.5 * np.sum(np.log(q))
        if best is None or ll > best[0]:
            best = (ll, tau, s2)
    _, tau, s2 = best
    return OUFit(float(np.sqrt(s2)), float(tau))


def _fit_under_white(t, r, white_sd, taus, n_sd):
    """Kalman-filter likelihood of ``r = d + v`` on a ``(tau, sd)`` grid (the first best point kept)."""
    rv = white_sd**2
    top = max(np.std(r), 1e-12)
    sds = np.concatenate([[0.0], np.geomspace(top * SD_GRID_LOW, top * SD_GRID_HIGH, n_sd - 1)])
    tau, sd = (a.ravel() for a in np.meshgrid(taus, sds, indexing="ij"))
    q = sd * sd
    m, P = np.zeros_like(q), q.copy()
    ll = np.zeros_like(q)
    dt = np.diff(t, prepend=t[0])
    for k in range(len(r)):
        phi = np.exp(-dt[k] / tau)
        m = phi * m
        P = phi * phi * P + q * (1.0 - phi * phi)
        S = P + rv
        e = r[k] - m
        ll -= 0.5 * (np.log(S) + e * e / S)
        g = P / S
        m = m + g * e
        P = (1.0 - g) * P
    i = int(np.argmax(ll))
    return OUFit(float(sd[i]), float(tau[i]))


def spectral_density(sd: ArrayLike, tau_s: ArrayLike) -> np.ndarray:
    """Spectral density ``2 sd^2 / tau`` of the white drive ``w`` of OU disturbances [unit^2 / s]."""
    sd, tau_s = np.asarray(sd, float), np.asarray(tau_s, float)
    return 2.0 * sd**2 / tau_s


def innovations(t: np.ndarray, r: np.ndarray, sd: float, tau_s: float) -> np.ndarray:
    """Whitened residuals ``(r_i - phi_i r_{i-1}) / (sd sqrt(1 - phi_i^2))`` of an OU process.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Sample times [s].
    r : ndarray, shape (..., n)
        Residuals (the last axis is time) [unit of sd].
    sd, tau_s : float
        The process's stationary sd and correlation time [s].

    Returns
    -------
    ndarray, shape (..., n)
        Standard-normal innovations when ``r`` is that process.
    """
    phi = np.exp(-np.diff(t) / tau_s)
    e = np.empty(r.shape)
    e[..., 0] = r[..., 0] / sd
    e[..., 1:] = (r[..., 1:] - phi * r[..., :-1]) / (sd * np.sqrt(1.0 - phi * phi))
    return e
