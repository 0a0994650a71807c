"""Honest widths when the model is not the rig: the window sandwich.

The step-response likelihood is a sum over step windows.  When the model is
right, each window's score (the gradient of its log-likelihood) varies from
window to window as much as the likelihood's curvature says (the information
identity), and the posterior's covariance is the laws' sampling covariance.
When the model is not the rig, windows at different currents and
temperatures pull the laws different ways, the scores scatter more, and the
posterior is too narrow: the sandwich ``Sigma V Sigma`` (``Sigma`` the
posterior covariance, ``V`` the scatter of the window scores) is the
covariance that scatter implies (Müller 2013, *Econometrica* 81, 1805;
the windows are the independent units, so the noise's autocorrelation within
a window is in it too).

The scores come from the posterior draws themselves: each window's
log-likelihood is regressed on the sampled coordinates across the draws,
which gives its gradient at the posterior mean exactly for a quadratic
log-likelihood.  Each law coordinate's draws are then stretched about their
mean by the square root of its sandwich over its posterior variance when
that ratio exceeds 1, never narrowed.  The marginal ratios, not the
sandwich's eigendirections: with 24 windows the largest eigenvalue of a
correct model's ratio matrix is ~2 by chance alone (measured on a bench
module: 0.44 ... 2.97), a marginal ratio scatters by ~30 % about 1, so a
correctly specified module keeps its posterior up to a few percent.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["WindowSandwich", "window_scores", "window_sandwich"]


@dataclass(frozen=True)
class WindowSandwich:
    """The stretch of the law coordinates (see the module docstring).

    Attributes
    ----------
    stretch : ndarray, shape (k, k)
        ``x' = mean + stretch (x - mean)`` on the stretched coordinates
        (diagonal).
    ratios : ndarray, shape (k,)
        Sandwich over posterior variance of each coordinate (before flooring
        at 1).
    sd_factor : ndarray, shape (k,)
        Each coordinate's sd after over before.
    n_windows : int
    """

    stretch: np.ndarray
    ratios: np.ndarray
    sd_factor: np.ndarray
    n_windows: int

    def to_json(self, names):
        return {"method": "window-sandwich", "n_windows": int(self.n_windows),
                "sd_factor": {n: float(f) for n, f in zip(names, self.sd_factor)},
                "variance_ratios": [float(r) for r in self.ratios]}


def window_scores(X, L):
    """Gradient of every window's log-likelihood at the draws' mean, ``(K, p)``.

    Parameters
    ----------
    X : ndarray, shape (n, p)
        Posterior draws (sampler coordinates).
    L : ndarray, shape (n, K)
        Each window's log-likelihood at every draw.
    """
    Xc = X - X.mean(axis=0)
    Lc = L - L.mean(axis=0)
    coef, *_ = np.linalg.lstsq(Xc, Lc, rcond=None)
    return coef.T


def window_sandwich(X, L, idx):
    """The stretch of coordinates ``idx`` that widens the posterior to the window sandwich.

    Parameters
    ----------
    X : ndarray, shape (n, p)
    L : ndarray, shape (n, K)
    idx : sequence of int
        The coordinates to stretch (the laws and K).

    Returns
    -------
    WindowSandwich
    """
    idx = np.asarray(idx)
    S = window_scores(X, L)
    K = S.shape[0]
    Sc = S - S.mean(axis=0)
    V = Sc.T @ Sc * K / max(K - 1, 1)
    post = np.cov(X.T)
    sand = np.diag(post @ V @ post)[idx]
    r = sand / np.diag(post)[idx]
    f = np.sqrt(np.maximum(r, 1.0))
    return WindowSandwich(stretch=np.diag(f), ratios=r, sd_factor=f, n_windows=K)
