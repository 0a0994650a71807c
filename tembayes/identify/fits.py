"""Linear laws in the mean temperature, fitted to per-step estimates.

``y(T) = a + b (T - T_ref)`` by weighted least squares on the independent
errors.  When the scatter about the line is larger than those say (reduced
chi-square > 1), the covariance is scaled by the reduced chi-square, so the
reported standard errors follow the real scatter.

Errors shared between points (the step-time error of one run, the rig
values behind every reconstructed junction temperature) do not average out,
but they must not steer the estimator either: generalised least squares with
a correlated component that is not constant across points can put the line
beside its own points (Peelle's pertinent puzzle).  So they are propagated
into the covariance ("sandwich") and leave the estimate alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tembayes.constants import T_REF
from tembayes.errors import ModelError

if TYPE_CHECKING:
    from numpy.typing import ArrayLike


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
    def a_sd(self) -> float:
        """Standard error of the intercept ``a`` (the value at ``tref``)."""
        return float(np.sqrt(self.cov[0, 0]))

    @property
    def b_sd(self) -> float:
        """Standard error of the slope ``b`` (the law's unit per kelvin)."""
        return float(np.sqrt(self.cov[1, 1]))

    def __call__(self, T):
        """Law value at temperature(s) ``T`` [K]."""
        return self.a + self.b * (np.asarray(T, dtype=float) - self.tref)

    def sd(self, T: ArrayLike) -> float | np.ndarray:
        """Standard error of the law at ``T`` [K]."""
        x = np.asarray(T, dtype=float) - self.tref
        return np.sqrt(self.cov[0, 0] + 2 * x * self.cov[0, 1] + x * x * self.cov[1, 1])


def fit_line(
    T: ArrayLike,
    y: ArrayLike,
    sd: ArrayLike | None = None,
    *,
    common: ArrayLike | None = None,
    draws: ArrayLike | None = None,
    tref: float = T_REF,
) -> LineFit:
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
        A fully correlated error component of each ``y`` (one shared shift
        scaled per point, e.g. the step-time error of one run).
    draws : array_like, shape (n_draws, n), optional
        Correlated perturbations of ``y`` from shared uncertain inputs (e.g.
        Monte-Carlo draws of the rig values); their covariance is propagated.
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
    w = np.ones(n) if sd is None else 1.0 / sd[ok] ** 2
    X = np.c_[np.ones(n), T - tref]
    A = np.linalg.inv(X.T @ (w[:, None] * X))
    coef = A @ (X.T @ (w * y))
    cov = A
    resid = y - X @ coef
    chi2_red = float(np.sum(w * resid**2) / (n - 2))
    if sd is None or chi2_red > 1.0:
        cov = cov * chi2_red
    # correlated components: a shift d of the data moves the estimate by G d
    G = A @ (X.T * w)
    if common is not None:
        g = G @ np.asarray(common, dtype=float)[ok]
        cov = cov + np.outer(g, g)
    if draws is not None:
        D = np.asarray(draws, dtype=float)[:, ok]
        D = D - D.mean(axis=0)
        GD = D @ G.T
        cov = cov + GD.T @ GD / max(len(D) - 1, 1)
    return LineFit(float(coef[0]), float(coef[1]), cov, chi2_red, n, tref)


def hysteresis(
    T: ArrayLike,
    y: ArrayLike,
    sd: ArrayLike,
    direction: ArrayLike,
    *,
    common: ArrayLike | None = None,
    tref: float = T_REF,
) -> dict:
    """Up-step against down-step estimates at similar temperatures.

    Fits ``y = a + b (T - tref) + d s`` with ``s = +1/2`` for up-steps and
    ``-1/2`` for down-steps (weighted least squares, shared errors propagated
    as in :func:`fit_line`), so ``d`` is the up-minus-down difference at
    equal temperature.  Its
    standard error is scaled by this model's reduced chi-square when > 1.
    (Scaling by the plain line's chi-square would let the very difference
    under test inflate its own error bar.)

    Returns
    -------
    dict
        ``diff`` (up - down), ``sd``, ``z``, ``n_up``, ``n_down``,
        ``relative`` (diff over the mean of ``y``).
    """
    T = np.asarray(T, dtype=float)
    y = np.asarray(y, dtype=float)
    sd = np.asarray(sd, dtype=float)
    direction = np.asarray(direction)
    ok = np.isfinite(T) & np.isfinite(y) & np.isfinite(sd) & (sd > 0)
    n_up = int((ok & (direction == "up")).sum())
    n_down = int((ok & (direction == "down")).sum())
    if n_up < 2 or n_down < 2 or ok.sum() < 5:
        return {"diff": None, "sd": None, "z": None, "n_up": n_up, "n_down": n_down, "relative": None}
    s_dir = np.where(direction[ok] == "up", 0.5, -0.5)
    w = 1.0 / sd[ok] ** 2
    X = np.c_[np.ones(ok.sum()), T[ok] - tref, s_dir]
    A = np.linalg.inv(X.T @ (w[:, None] * X))
    coef = A @ (X.T @ (w * y[ok]))
    r = y[ok] - X @ coef
    chi2_red = float(np.sum(w * r**2) / (ok.sum() - 3))
    var = A[2, 2] * max(1.0, chi2_red)
    if common is not None:  # propagated, as in fit_line
        g = (A @ (X.T * w)) @ np.asarray(common, dtype=float)[ok]
        var += g[2] ** 2
    dsd = float(np.sqrt(var))
    diff = float(coef[2])
    return {
        "diff": diff,
        "sd": dsd,
        "z": diff / dsd,
        "n_up": n_up,
        "n_down": n_down,
        "relative": diff / float(np.mean(y[ok])),
    }
