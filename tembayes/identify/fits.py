"""Linear laws in the mean temperature, fitted to per-step estimates.

``y(T) = a + b (T - T_ref)`` by (generalised) least squares.  When the scatter
about the line is larger than the per-point uncertainties say (reduced
chi-square > 1: the extrapolated jumps carry shape errors no single fit can
see), the covariance is scaled by the reduced chi-square, so the reported
standard errors follow the real scatter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tembayes.constants import T_REF
from tembayes.errors import ModelError


@dataclass(frozen=True)
class LineFit:
    """A fitted linear law.

    Attributes
    ----------
    a : float
        Value at ``tref``.
    b : float
        Slope per kelvin.
    cov : ndarray, shape (2, 2)
        Covariance of ``(a, b)``.
    chi2_red : float
        Reduced chi-square with the per-point uncertainties.
    n : int
        Points used.
    tref : float
        [K]
    """

    a: float
    b: float
    cov: np.ndarray
    chi2_red: float
    n: int
    tref: float = T_REF

    @property
    def a_sd(self):
        return float(np.sqrt(self.cov[0, 0]))

    @property
    def b_sd(self):
        return float(np.sqrt(self.cov[1, 1]))

    def __call__(self, T):
        """Law value at temperature(s) ``T`` [K]."""
        return self.a + self.b * (np.asarray(T, dtype=float) - self.tref)

    def sd(self, T):
        """Standard error of the law at ``T`` [K]."""
        x = np.asarray(T, dtype=float) - self.tref
        return np.sqrt(self.cov[0, 0] + 2 * x * self.cov[0, 1] + x * x * self.cov[1, 1])


def fit_line(T, y, sd=None, *, common=None, tref=T_REF):
    """Weighted least-squares line ``y = a + b (T - tref)``.

    Parameters
    ----------
    T : array_like
        Temperatures [K].
    y : array_like
        Values.
    sd : array_like, optional
        Standard uncertainties of ``y``; equal weights if absent (then the
        covariance comes from the residual scatter alone).
    common : array_like, optional
        A fully correlated error component of each ``y`` (same sign for all,
        e.g. the step-time error of one run); the fit is then generalised
        least squares with covariance ``diag(sd^2) + common common^T``.
    tref : float
        [K]

    Returns
    -------
    LineFit
    """
    T = np.asarray(T, dtype=float)
    y = np.asarray(y, dtype=float)
    ok = np.isfinite(T) & np.isfinite(y)
    if sd is not None:
        sd = np.asarray(sd, dtype=float)
        ok &= np.isfinite(sd) & (sd > 0)
    T, y = T[ok], y[ok]
    n = len(y)
    if n < 3 or np.ptp(T) <= 0:
        raise ModelError(f"a linear law needs at least 3 points at different temperatures, got {n}")
    V = np.eye(n) if sd is None else np.diag(sd[ok] ** 2)
    if common is not None:
        c = np.asarray(common, dtype=float)[ok]
        V = V + np.outer(c, c)
    W = np.linalg.inv(V)
    X = np.c_[np.ones(n), T - tref]
    cov = np.linalg.inv(X.T @ W @ X)
    coef = cov @ (X.T @ W @ y)
    resid = y - X @ coef
    chi2_red = float(resid @ W @ resid / (n - 2))
    if sd is None or chi2_red > 1.0:
        cov = cov * chi2_red
    return LineFit(float(coef[0]), float(coef[1]), cov, chi2_red, n, tref)


def hysteresis(T, y, sd, direction, fit):
    """Up-step against down-step estimates at similar temperatures.

    The common line ``fit`` takes out the temperature dependence; what is
    left is the weighted mean residual of the up-steps minus that of the
    down-steps, with its standard error (scaled like the fit's).

    Returns
    -------
    dict
        ``diff`` (up - down), ``sd``, ``z``, ``n_up``, ``n_down``,
        ``relative`` (diff over the law's mean value).
    """
    T = np.asarray(T, dtype=float)
    y = np.asarray(y, dtype=float)
    sd = np.asarray(sd, dtype=float)
    direction = np.asarray(direction)
    ok = np.isfinite(T) & np.isfinite(y) & np.isfinite(sd) & (sd > 0)
    resid = y - fit(T)
    scale = max(1.0, fit.chi2_red)
    out = {}
    for d in ("up", "down"):
        m = ok & (direction == d)
        if m.sum() == 0:
            return {"diff": None, "sd": None, "z": None, "n_up": int((ok & (direction == "up")).sum()),
                    "n_down": int((ok & (direction == "down")).sum()), "relative": None}
        w = 1.0 / sd[m] ** 2
        out[d] = (float(np.sum(w * resid[m]) / np.sum(w)), float(np.sqrt(scale / np.sum(w))), int(m.sum()))
    diff = out["up"][0] - out["down"][0]
    dsd = float(np.hypot(out["up"][1], out["down"][1]))
    return {
        "diff": diff, "sd": dsd, "z": diff / dsd, "n_up": out["up"][2], "n_down": out["down"][2],
        "relative": diff / float(np.mean(fit(T[ok]))),
    }
