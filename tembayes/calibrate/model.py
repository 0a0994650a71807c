"""The step-response model: the rig simulated through every step window.

One continuous simulation of the rig from the steady state shortly before the
first step, with the current an ideal staircase (the hold levels of the run)
and the measured, smoothed boundary temperatures, evaluated at the
selected samples of :class:`~tembayes.calibrate.stepdata.StepData`.  The
simulation is the package's stiff integrator
(:func:`tembayes.physics.kernel.integrate_grids`), batched over parameter
draws.

The instant of a step within its sampling interval is unknown to the data
(the DAQ only sees the old level, then the new one) but common to all steps
of a run, because the amplifier and the DAQ run on fixed clocks: it is the
nuisance parameter ``step_shift_s`` [s], the offset of every step from the
midpoint of its sampling interval.  It matters: the plates heat at ~1 K/s
right after a step, so 0.1 s moves the early voltage by millivolts.

:class:`LinearisedModel` is the same prediction as a second-order expansion
around a point, built from one batched simulation of all finite-difference
perturbations; the sampler uses it, and the calibration checks it against
this exact model by importance sampling.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from tembayes.calibrate.stepdata import step_grid
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import ModelError
from tembayes.physics import effects
from tembayes.physics.simulate import build, integrate_on_grids

if TYPE_CHECKING:
    from collections.abc import Mapping

    from numpy.typing import ArrayLike

#: Name of the step-instant nuisance parameter [s].
SHIFT = "step_shift_s"

#: Integrator tolerance [K]: 50x below the sensor noise.
ATOL = 1e-4

#: How far a boundary may stray from its chord between grid points, in units of the mean temperature's noise sd.
KNOT_TOL = 1.0


class StepResponseModel:
    """Predict the step-response channels of one run for many parameter draws.

    Parameters
    ----------
    data : StepData
    rig : RigDescription
        The calibration rig (e.g. ``rig_from_config(None, leg_cells=2)``).
    input_spacing : float, optional
        Extra (unobserved) grid points at this spacing [s], so that the
        boundary temperatures' few-minute wobble reaches the model.
    atol : float, optional
        Integrator tolerance [K].
    hmax : float, optional
        Largest integrator step [s].
    """

    def __init__(self, data, rig, *, input_spacing=20.0, atol=ATOL, hmax=60.0):
        if data.boundary_names != rig.layout.boundaries:
            raise ModelError(
                f"{data.source}: boundaries {', '.join(data.boundary_names)}; rig '{rig.name}' reads "
                f"{', '.join(rig.layout.boundaries)} in this order"
            )
        self.data = data
        self.rig = rig
        self.atol = float(atol)
        self.hmax = float(hmax)
        ns = data.n_steps
        # grid: t0, observed samples, regular input points, points where a boundary moves
        # faster than linear between those can follow, and each step's points
        extra = np.arange(data.t0, data.time[-1], input_spacing)[1:]
        extra = np.union1d(extra, boundary_knots(data, np.concatenate([[data.t0], data.time, extra])))
        extra = extra[np.min(np.abs(extra[:, None] - data.step_time[None, :]), axis=1) > 1.0]
        near = np.clip(np.searchsorted(data.time, extra), 1, len(data.time) - 1)
        gap = np.minimum(np.abs(data.time[near] - extra), np.abs(data.time[near - 1] - extra))
        extra = extra[gap > 1e-3]
        base = np.concatenate([[data.t0], data.time, extra])
        kind = np.concatenate([[0], np.ones(len(data.time), int), np.full(len(extra), 2)])
        order = np.argsort(base, kind="stable")
        base, kind = base[order], kind[order]
        # the step points at their nominal instants (each draw shifts them in
        # grid()); the boundaries below are read there, so never leave them unset
        sg = step_grid(base, data.step_time, data.step_window, fractions=effects.STEP_FRACTIONS)
        grid, pos_step = sg.grid, sg.pos_step
        n = len(grid)
        kinds = np.full(n, 3)
        kinds[~sg.is_step] = kind
        self._steps = sg
        self._n = n
        self._pos_step = pos_step
        self.obs_pos = np.flatnonzero(kinds == 1)
        self._base_grid = grid
        # hold index of every non-step point, and the step points' levels
        hold = np.searchsorted(data.step_time, grid, side="right")
        hold[pos_step] = np.arange(ns)
        hold[sg.pos_new] = np.arange(ns)[:, None] + 1
        self._hold = hold
        self._current = data.levels[hold]
        self._bounds = data.boundaries(grid)
        self.shift_bound = sg.shift_bound

    def grid(self, shift: ArrayLike) -> np.ndarray:
        """Per-draw time grids ``(nd, n)`` for step shifts ``shift`` [s] (see :class:`StepGrid`)."""
        return self._steps.shifted(shift)

    def simulate(
        self, params: Mapping[str, float | np.ndarray], strict: bool = True, levels: np.ndarray | None = None
    ) -> dict:
        """Simulate the run for a parameter mapping (arrays of shape ``(nd,)``).

        ``params`` needs the five module parameters and :data:`SHIFT`; rig
        parameters default to nominal and effect parameters to zero.
        ``levels`` ``(nd, ns + 1)``: hold currents per draw [A] (default the
        measured ones).

        Returns
        -------
        dict
            ``sensors`` ``(nd, 2, n_obs)`` (the face sensors, ``data.face``) [K], ``voltage``
            ``(nd, n_obs)`` [V], ``t_hot``/``t_cold`` ``(nd, n_obs)`` [K] and
            ``steps`` (accepted integrator steps per draw).
        """
        params = dict(params)
        if SHIFT not in params:
            raise ModelError(f"the step-response model needs '{SHIFT}'")
        shift = np.atleast_1d(np.asarray(params.pop(SHIFT), dtype=float))
        if np.any(np.abs(shift) > self.shift_bound):
            raise ModelError(f"{SHIFT} must lie within +-{self.shift_bound:.4f} s (half the widest sampling interval)")
        m = build(params, self.rig)
        nd = m["nd"]
        shift = np.broadcast_to(shift, (nd,))
        names = m["network"].nodes
        a, b, f = self.rig.readout(self.data.face, m["params"])
        rec = np.concatenate([a, [names.index(self.rig.hot), names.index(self.rig.cold)], b]).astype(np.int64)
        G = self.grid(shift)
        if levels is None:
            Ic = np.repeat(self._current[None, :], nd, axis=0)
        else:
            Ic = np.ascontiguousarray(np.broadcast_to(levels, (nd, len(self.data.levels)))[:, self._hold])
        out, volt, failed, steps = integrate_on_grids(m, G, Ic, self._bounds, rec, self.atol, self.hmax)
        if strict and np.any(failed):
            raise ModelError(
                "the step-response simulation failed (no steady start, step budget exceeded or non-finite values)"
            )
        sensors = out[:, :, :2] + f[:, None, :] * (out[:, :, 4:] - out[:, :, :2])
        sensors = np.ascontiguousarray(sensors.transpose(0, 2, 1))
        self.rig.read_leads(sensors, self.data.face, m["params"], self._bounds)
        lags = self.rig.sensor_lags(self.data.face, m["params"])
        if effects.has_sensor_effect(m["params"], lags):
            effects.apply_sensors(G, sensors, m["params"], lags)  # each draw's own step instants
        o = self.obs_pos
        return dict(sensors=sensors[:, :, o], voltage=volt[:, o], t_hot=out[:, o, 2], t_cold=out[:, o, 3], steps=steps)

    def predict(
        self, params: Mapping[str, float | np.ndarray], strict: bool = True, levels: np.ndarray | None = None
    ) -> np.ndarray:
        """Predicted channels ``(nd, 3, n_obs)``: voltage [V], dT [K], Tmean [K].

        With ``strict=False`` a draw whose simulation fails comes back as NaN
        instead of raising :class:`~tembayes.errors.ModelError`.
        """
        s = self.simulate(params, strict=strict, levels=levels)
        hot, cold = s["sensors"][:, 0], s["sensors"][:, 1]
        return np.stack([s["voltage"], hot - cold, 0.5 * (hot + cold)], axis=1)

    def level_jacobian(self, params: Mapping[str, float | np.ndarray], dI: float = 1e-3) -> np.ndarray:
        """Response of the channels to each hold's current level, at one point.

        Parameters
        ----------
        params : dict
            One parameter point (scalars or shape ``(1,)``).
        dI : float
            Finite-difference step [A]; the response is linear far beyond
            the levels' uncertainty (~0.02 mA).

        Returns
        -------
        ndarray, shape (ns + 1, 3, n_obs)
            ``d prediction / d level_h`` [V/A, K/A, K/A].
        """
        nh = len(self.data.levels)
        L = np.repeat(self.data.levels[None, :], nh + 1, axis=0)
        L[1 + np.arange(nh), np.arange(nh)] += dI
        P = {k: np.repeat(np.ravel(v)[:1], nh + 1) for k, v in params.items()}
        Y = self.predict(P, levels=L)
        return (Y[1:] - Y[0]) / dI


class LinearisedModel:
    """Second-order expansion of a :class:`StepResponseModel` around a point.

    ``predict(x) = f(x0) + J d + C d^2 / 2 + sum_(i,j) H_ij d_i d_j`` with
    ``d = x - x0`` in the sampler's coordinates (see
    :class:`~tembayes.calibrate.parameters.ParameterSpace`).  Slopes ``J`` and
    the diagonal curvature ``C`` come from the ``2 p`` points ``x0 +- h_j``;
    with ``h_j`` about one posterior sd the three points per axis span the
    posterior, so the expansion interpolates over it rather than being a
    tangent at one point.  Mixed terms ``H_ij`` come from the points
    ``x0 + h_i + h_j``; only the pairs whose term moves the prediction by
    more than ``cross_threshold`` noise units (root-sum-square over the samples,
    at one step each) are kept.  All points are one batched simulation.

    Parameters
    ----------
    model : StepResponseModel
    space : ParameterSpace
        Maps coordinate vectors to parameter mappings.
    x0 : ndarray, shape (p,)
        Expansion point.
    steps : ndarray, shape (p,)
        Finite-difference steps in coordinate units.
    noise : ndarray, shape (nc,), optional
        Noise sd of each channel, to rank the mixed terms; no mixed terms
        without it.
    cross_threshold : float
    max_cross : int
        At most this many mixed terms (the largest).
    """

    def __init__(self, model, space, x0, steps, *, noise=None, cross_threshold=0.5, max_cross=24):
        self.model = model
        self.space = space
        self.x0 = np.asarray(x0, dtype=float)
        h = np.asarray(steps, dtype=float)
        p = len(self.x0)
        pairs = [(i, j) for i in range(p) for j in range(i + 1, p)] if noise is not None else []
        X = np.repeat(self.x0[None, :], 1 + 2 * p + len(pairs), axis=0)
        for j in range(p):
            X[1 + 2 * j, j] += h[j]
            X[2 + 2 * j, j] -= h[j]
        for k, (i, j) in enumerate(pairs):
            X[1 + 2 * p + k, i] += h[i]
            X[1 + 2 * p + k, j] += h[j]
        X = space.clip(X)
        Y = model.predict(space.params(X), strict=False)
        # a probe the rig cannot simulate (an open coordinate pushed where a
        # plate or paste is unphysical) is pulled halfway back, up to 5 times;
        # the formulas below use the points actually simulated
        for _ in range(5):
            bad = ~np.all(np.isfinite(Y), axis=(1, 2))
            if not bad[1:].any() or bad[0]:
                break
            X[bad] = self.x0 + 0.5 * (X[bad] - self.x0)
            Y[bad] = model.predict(space.params(X[bad]), strict=False)
        if not np.all(np.isfinite(Y)):
            raise ModelError(
                "the step-response simulation failed at the expansion point or next to it (no steady "
                "start, step budget exceeded or non-finite values)"
            )
        self.f0 = Y[0]
        jj = np.arange(p)
        Xp, Xm = X[1 : 1 + 2 * p : 2], X[2 : 2 + 2 * p : 2]
        hp = (Xp[jj, jj] - self.x0)[:, None, None]
        hm = (self.x0 - Xm[jj, jj])[:, None, None]
        Yp, Ym = Y[1 : 1 + 2 * p : 2], Y[2 : 2 + 2 * p : 2]
        dp, dm = Yp - Y[0], Y[0] - Ym
        # the parabola through the three points (uneven if clipped at a bound)
        self.C = 2.0 * (dp / hp - dm / hm) / (hp + hm)  # (p, nc, n)
        self.J = dp / hp - 0.5 * self.C * hp
        kept, H = [], []
        if pairs:
            D = X[1 + 2 * p :] - self.x0
            hi = D[np.arange(len(pairs)), [i for i, _ in pairs]]
            hj = D[np.arange(len(pairs)), [j for _, j in pairs]]
            Yij = Y[1 + 2 * p :]
            ii = np.array([i for i, _ in pairs])
            jx = np.array([j for _, j in pairs])
            # what the diagonal expansion predicts at x0 + h_i + h_j; the rest is the mixed term
            diag = (
                Y[0]
                + self.J[ii] * hi[:, None, None]
                + 0.5 * self.C[ii] * hi[:, None, None] ** 2
                + self.J[jx] * hj[:, None, None]
                + 0.5 * self.C[jx] * hj[:, None, None] ** 2
            )
            Hall = (Yij - diag) / (hi * hj)[:, None, None]
            size = np.sqrt(
                np.sum((Hall * (hi * hj)[:, None, None] / np.asarray(noise)[None, :, None]) ** 2, axis=(1, 2))
            )
            order = np.argsort(size)[::-1]
            for k in order[:max_cross]:
                if size[k] > cross_threshold:
                    kept.append(pairs[k])
                    H.append(Hall[k])
        self.pairs = np.array(kept, dtype=int).reshape(-1, 2)
        self.H = np.array(H).reshape((len(kept),) + self.f0.shape)

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Predicted channels ``(nw, 3, n)`` for coordinate vectors ``X`` ``(nw, p)``."""
        D = np.atleast_2d(X) - self.x0
        out = self.f0[None] + np.tensordot(D, self.J, axes=(1, 0)) + 0.5 * np.tensordot(D * D, self.C, axes=(1, 0))
        if len(self.pairs):
            out += np.tensordot(D[:, self.pairs[:, 0]] * D[:, self.pairs[:, 1]], self.H, axes=(1, 0))
        return out


def module_params_of(params: Mapping[str, float | np.ndarray]) -> dict[str, float | np.ndarray]:
    """The five module parameters of a mapping."""
    return {k: params[k] for k in MODULE_PARAMETERS}


def boundary_knots(data, grid: np.ndarray, max_rounds: int = 16) -> np.ndarray:
    """Times to add to ``grid`` so that the boundaries, linear between its points, follow the measured ones.

    The model reads the boundary temperatures at its grid points and joins
    them linearly.  A boundary that moves fast (a liquid plate sent to a new
    setpoint: tens of mK/s, curving with the circulator's time constant) is
    then off by ``h^2 |T''| / 8`` between points ``h`` apart -- 0.1 K over
    20 s on the bench's plates, 30 mK at their sensors.  Each round adds,
    in every grid interval where some boundary strays from its chord by more
    than :data:`KNOT_TOL` of the mean temperature's noise sd, the sample where it strays most.

    Parameters
    ----------
    data : StepData
        Its smoothed boundaries and noise.
    grid : ndarray
        The grid points so far [s].
    max_rounds : int

    Returns
    -------
    ndarray
        The added times [s] (samples of the boundaries), sorted.
    """
    pts = np.unique(grid)
    inside = (data.boundary_time >= pts[0]) & (data.boundary_time <= pts[-1])
    t, B = data.boundary_time[inside], data.boundary_values[:, inside]
    tol = KNOT_TOL * float(data.noise[2])
    for _ in range(max_rounds):
        err = np.max(np.abs([np.interp(t, pts, np.interp(pts, t, b)) - b for b in B]), axis=0)
        bad = np.flatnonzero(err > tol)
        if not len(bad):
            break
        seg = np.searchsorted(pts, t[bad], side="right")
        order = np.lexsort((-err[bad], seg))
        worst = bad[order][np.r_[True, np.diff(seg[order]) != 0]]
        pts = np.union1d(pts, t[worst])
    return np.setdiff1d(pts, grid)
