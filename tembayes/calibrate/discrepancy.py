"""Honest widths when the model is not the rig: the window sandwich and the held parameters.

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

The windows can agree on a wrong value, though: a rig parameter the
calibration holds fixed (the ceramic's conductance, held because sampling it
does not converge; on the reference rig the depths of T1 and T4, a block away
from the module) moves every window the same way.  Its
documented range is carried over to the posterior to first order
(:func:`held_nuisance_spread`): every draw moves by the mode's response to
a draw of the held parameter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tembayes.calibrate.priors import expit, logit

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from tembayes.calibrate.model import StepResponseModel
    from tembayes.calibrate.parameters import ParameterSpace
    from tembayes.physics.rig import RigParameter

__all__ = ["WindowSandwich", "window_scores", "window_sandwich", "HeldSpread", "held_nuisance_spread"]


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

    def to_json(self, names: Sequence[str]) -> dict:
        """JSON-ready dict: method, window count, each coordinate's sd factor (keyed by ``names``), variance ratios."""
        return {
            "method": "window-sandwich",
            "n_windows": int(self.n_windows),
            "sd_factor": {n: float(f) for n, f in zip(names, self.sd_factor)},
            "variance_ratios": [float(r) for r in self.ratios],
        }


def window_scores(X: np.ndarray, L: np.ndarray) -> np.ndarray:
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


def window_sandwich(X: np.ndarray, L: np.ndarray, idx: Sequence[int]) -> WindowSandwich:
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


@dataclass(frozen=True)
class HeldSpread:
    """What the rig parameters a calibration holds fixed add to its posterior (see :func:`held_nuisance_spread`).

    Attributes
    ----------
    names : tuple of str
        The held parameters.
    sd : ndarray, shape (m,)
        Their uncertainty in their coordinate (the log, the logit for a share: the sd of a
        uniform draw over their documented range, :attr:`~tembayes.physics.rig.RigParameter.spread_sd`).
    shift : ndarray, shape (p, m)
        Shift of the posterior mode's coordinates per unit of each one's coordinate.
    held_value : ndarray, shape (m,)
        The values the calibration held them at (SI).
    not_carried : tuple of str
        Held parameters whose response could not be simulated at the posterior's centre (their
        shift is zero: nothing is carried over for them).
    shares : tuple of str
        Held parameters that are shares (moved in their logit, not their log).
    """

    names: tuple
    sd: np.ndarray
    shift: np.ndarray
    held_value: np.ndarray
    not_carried: tuple = ()
    shares: tuple = ()

    def draw(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, m)`` draws of the held parameters' deviations from their held values, in their coordinates."""
        return rng.standard_normal((n, len(self.names))) * self.sd

    def values(self, xi: np.ndarray) -> dict[str, np.ndarray]:
        """``name -> (n,)`` the held parameters' values in the draws ``xi`` (SI).

        A draw's laws moved by its ``xi`` (:meth:`apply`), so a simulation of
        that draw needs these values, not the held ones: with the held value
        the laws' shift is a spread the data do not allow (on a liquid-plate
        module out-of-model the ceramic's carry-over spread the predicted
        voltage by 3.5 mV against 1.0 mV of noise; 0.7 mV at each draw's own
        ceramic).
        A parameter not carried over keeps its held value in every draw.
        """
        out = {}
        for i, q in enumerate(self.names):
            d = np.zeros(len(xi)) if q in self.not_carried else xi[:, i]
            v = self.held_value[i]
            out[q] = expit(logit(v) + d) if q in self.shares else v * np.exp(d)
        return out

    def apply(
        self,
        X: np.ndarray,
        xi: np.ndarray,
        relative: Sequence[int] = (),
        shares: Mapping[int, tuple[float, float]] | None = None,
    ) -> np.ndarray:
        """``X`` ``(n, >= p)`` with every draw moved by its held parameters' deviations ``xi`` (a copy).

        The coordinates ``relative`` (positive ones, e.g. a resistance) move
        by the same shift relative to their mean, ``x exp(dx / mean)``, and
        the coordinates ``shares`` (coordinate -> its flat prior's ``(low, high)``,
        e.g. a lead share) in the logit of their place in that range,
        ``u = (x - low) / (high - low)`` moved to ``expit(logit u + du / (m (1 - m)))``
        with ``m`` its mean: the same to first order, and never out of the range
        (the posterior has no mass outside its prior's support).
        """
        X = np.array(X, dtype=float)
        dX = np.asarray(xi, float) @ self.shift.T  # (n, p): the model's coordinates, the first p of X
        shares = dict(shares or {})
        rel, sh = (np.asarray(list(c), dtype=int) for c in (relative, shares))
        lin = np.setdiff1d(np.arange(dX.shape[1]), np.concatenate([rel, sh]))
        X[:, lin] += dX[:, lin]
        if len(rel):
            X[:, rel] *= np.exp(dX[:, rel] / X[:, rel].mean(axis=0))
        for j, (low, high) in shares.items():
            u = np.clip((X[:, j] - low) / (high - low), 1e-12, 1.0 - 1e-12)
            m = u.mean()
            X[:, j] = low + (high - low) * expit(logit(u) + dX[:, j] / ((high - low) * m * (1.0 - m)))
        return X

    def to_json(
        self, coordinate_names: Sequence[str], law_idx: Sequence[int], law_sd: np.ndarray
    ) -> dict[str, dict[str, float]]:
        """Each held parameter's sd contribution to each law, as a fraction of the law's posterior sd."""
        return {
            q: {
                coordinate_names[j]: float(abs(self.shift[j, i]) * self.sd[i] / law_sd[k])
                for k, j in enumerate(law_idx)
            }
            for i, q in enumerate(self.names)
        }


def held_parameters(rig, space: ParameterSpace) -> dict:
    """The rig parameters ``space`` holds at nominal though their documented range is not a point: name -> RigParameter."""
    return {
        q: rig.parameter(q)
        for q in space.fixed
        if q in rig.parameter_names and rig.parameter(q).high > rig.parameter(q).low
    }


def held_nuisance_spread(
    model: StepResponseModel,
    space: ParameterSpace,
    x: np.ndarray,
    J: np.ndarray,
    noise: np.ndarray,
    held: Mapping[str, RigParameter],
    h: float = 0.05,
) -> HeldSpread:
    """Carry the uncertainty of held rig parameters over to the posterior, to first order.

    A parameter the calibration holds at its nominal value (``RigParameter.held``,
    or a documented range too narrow to sample) is still uncertain.  Where
    the mode would move if it were moved by ``d`` in its coordinate (``e^d``
    times its value; a share in its logit, so it stays below one) is the weighted
    least-squares response ``-(J^T W J + P)^-1 J^T W df/dd`` of the mode to
    the prediction's change ``df/dd`` (``J`` the prediction's slopes in the
    sampled coordinates, ``W`` the noise weights, ``P`` the prior's curvature at ``x``);
    adding that shift times a draw of ``d`` to every posterior draw is the
    posterior marginalised over the held parameter, to first order.

    Parameters
    ----------
    model : StepResponseModel
    space : ParameterSpace
        The model's sampled coordinates (``space.fixed`` holds the held values).
    x : ndarray, shape (p,)
        The posterior's centre.
    J : ndarray, shape (p, nc, n)
        The prediction's slopes at (about) ``x``.
    noise : ndarray, shape (nc,)
        The channels' noise sd.
    held : mapping of str to RigParameter
        The held parameters to carry over.
    h : float
        Finite-difference step in log units.

    Returns
    -------
    HeldSpread
        A parameter whose two probes the model cannot simulate (a posterior
        centre outside the rig's physical range, where only the expansion
        went) is listed in ``not_carried`` instead of failing the module.
    """
    names = tuple(held)
    m = len(names)
    X = np.repeat(np.asarray(x, float)[None], 2 * m, axis=0)
    params = space.params(X)
    for i, q in enumerate(names):
        v = np.full(2 * m, float(space.fixed[q]))
        v[2 * i] = held[q].moved(v[2 * i], h)
        v[2 * i + 1] = held[q].moved(v[2 * i + 1], -h)
        params[q] = v
    Y = model.predict(params, strict=False)
    ok = np.all(np.isfinite(Y), axis=(1, 2))
    ok = ok[0::2] & ok[1::2]
    D = np.where(ok[:, None, None], (Y[0::2] - Y[1::2]) / (2.0 * h), 0.0)  # (m, nc, n)
    w = 1.0 / np.asarray(noise, float) ** 2
    JtWJ = np.einsum("icn,jcn,c->ij", J, J, w)
    prec = np.array([p.coordinate_precision(xj) for p, xj in zip(space.priors, x)])
    JtWD = np.einsum("icn,qcn,c->iq", J, D, w)
    shift = -np.linalg.solve(JtWJ + np.diag(prec), JtWD)
    sd = np.array([held[q].spread_sd for q in names])
    failed = tuple(q for q, good in zip(names, ok) if not good)
    value = np.array([float(space.fixed[q]) for q in names])
    shares = tuple(q for q in names if held[q].is_share)
    return HeldSpread(names=names, sd=sd, shift=shift, held_value=value, not_carried=failed, shares=shares)
