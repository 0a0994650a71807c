"""A whole experiment as the calibration model sees it, for many draws at once.

The calibration looks at step windows; prediction needs every sample of a run
(every sensor of the rig and the voltage).  :class:`RunModel` simulates a run
the way :class:`~tembayes.calibrate.model.StepResponseModel` simulates the
windows -- the same rig, the current as the ideal staircase of the measured
hold levels (the amplifier's current is clean; the shunt's 1 mA noise is the
*measurement's*), the smoothed boundary temperatures, and every
current step at its own instant within its sampling interval -- but over the
whole run:

- the integrator lands on a *grid*: every sample in the first ``dense``
  seconds after each step (the plates and the voltage move within a second)
  and a point every ``spacing`` seconds elsewhere (the blocks respond in
  minutes);
- the outputs are interpolated onto all samples with a cubic spline per hold
  (never across a step, where the voltage jumps).  On the bench the
  interpolation is within 0.1 mK and 5 uV of simulating every sample
  (``tests/test_predict.py``), at a quarter of the cost.

The step instant is the parameter ``step_shift_s`` [s]: one offset for all
steps from the middle of their sampling intervals (a programme timer and a
DAQ clock keep a fixed phase), each step's instant clipped into its own
interval.  A validation run's phase is unknown: the predictive draws it.

A run starts wherever it starts: the rig at rest with the current switched
straight to its first level, or in the middle of an earlier program.  With
``start="data"`` the initial state is taken from the data: the steady state
of the rig under a constant *pre-history current* (:meth:`RunModel.fit_start`:
the one that explains the run's first minute best), moved along the rig's
slowest modes until the sensors read their first measured values (the rig's
own leaks and blocks set where it rests; a model's slightly different leaks
would rest a tenth of a kelvin elsewhere and carry that through the first
hour).  A run that starts settled at its first level gets that level back.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np
from scipy.interpolate import CubicSpline

from tembayes.calibrate.stepdata import BOUNDARY_SMOOTH_S, hold_levels, smooth_boundary, step_grid
from tembayes.data.quality import noise_estimate
from tembayes.data.steps import detect_steps
from tembayes.errors import DataError, ModelError
from tembayes.physics import effects
from tembayes.physics.simulate import build, integrate_on_grids

#: The voltage channel, predicted after the rig's sensors (``metrics.json``).
VOLTAGE = "voltage_V"

#: Integrator tolerance [K], as in the calibration.
ATOL = 1e-4
#: The run's beginning whose sensors fix its initial state [s].
START_WINDOW_S = 60.0
#: Pre-history currents tried, as multiples of the run's largest |level|.
START_SPAN = 1.5


class RunModel:
    """Simulate one experiment at every sample for many parameter draws.

    Parameters
    ----------
    exp : tembayes.data.Experiment
    rig : RigDescription
        The calibration rig (the run's ``leg_cells``/``block_split``).
    dense : float, optional
        Every sample in the first ``dense`` seconds of the run and after a
        step is a grid point [s].
    spacing : float, optional
        Grid spacing elsewhere [s].
    smooth : float, optional
        Width of the smoothing of the boundary inputs [s] (:func:`~tembayes.calibrate.stepdata.smooth_boundary`).
    atol, hmax : float, optional
        Integrator tolerance [K] and largest step [s].
    start : {"steady", "data"}
        The initial state: the steady state at the first level (or
        :attr:`start_current`), or taken from the data (see the module
        docstring).

    Attributes
    ----------
    sensor_channels : tuple of str
        The rig's sensor columns, the order of every sensor axis.
    channels : tuple of str
        ``sensor_channels`` and ``"voltage_V"``: the predicted channels.
    measured : ndarray, shape (nch, n)
        The run's measured channels in that order (K, V).
    time : ndarray, shape (n,)
        The run's sample times [s].
    step_time, step_window : ndarray, shape (ns,)
        Nominal step instants (mid-interval) and half their sampling
        intervals [s].
    levels : ndarray, shape (ns + 1,)
        Hold currents [A] (means of the measured current).
    start_current : float or None
        The pre-history current whose steady state the run starts from [A]
        (:meth:`fit_start`); None: the first hold's level.
    """

    def __init__(
        self, exp, rig, *, dense=20.0, spacing=5.0, smooth=BOUNDARY_SMOOTH_S, atol=ATOL, hmax=60.0, start="steady"
    ):
        if start not in ("steady", "data"):
            raise ValueError(f"start must be 'steady' or 'data', got {start!r}")
        self.exp = exp
        self.rig = rig
        self.sensor_channels = tuple(rig.sensors)
        self.channels = self.sensor_channels + (VOLTAGE,)
        missing = [c for c in self.channels if c not in exp.columns]
        if missing:
            raise DataError(
                str(exp.path),
                f"the run has no column {missing[0]!r}, which rig '{rig.name}' reads",
                "Predict a run recorded on the calibration's rig (its columns: " + ", ".join(self.channels) + ")",
            )
        self.measured = np.vstack([np.asarray(exp.channel(c), float) for c in self.channels])
        self.start = start
        self.start_current = None
        self.atol = float(atol)
        self.hmax = float(hmax)
        t = np.asarray(exp.time, dtype=float)
        self.time = t
        steps = detect_steps(t, exp.current)
        self.steps = steps
        cur = np.asarray(exp.current, dtype=float)
        if steps:
            holds = [(steps[0].prev_start, steps[0].index)] + [(s.hold_start, s.hold_end) for s in steps]
            # a run may start before the first hold was detected: the rest of it is hold 0
            holds[0] = (0, steps[0].index)
        else:
            holds = [(0, len(t))]
        self.levels = hold_levels(cur, holds)
        self.step_time = np.array([s.t for s in steps])
        self.step_window = np.array([s.t_window for s in steps])
        ns = len(steps)
        # hold of every sample: samples after a step's first new sample belong to it
        first_new = np.array([s.index for s in steps], dtype=np.int64)
        self.sample_hold = np.searchsorted(first_new, np.arange(len(t)), side="right")
        # grid points among the samples: dense after steps, every `spacing` s elsewhere
        keep = np.zeros(len(t), bool)
        keep[-1] = True
        # the run's start is a step too when it starts away from the first level's steady state
        keep[: np.searchsorted(t, t[0] + dense, side="right")] = True
        mark = np.floor((t - t[0]) / spacing)
        keep[1:] |= mark[1:] != mark[:-1]
        for s in steps:
            lo = s.index - 2
            hi = np.searchsorted(t, s.t + dense, side="right")
            keep[max(lo, 0) : hi] = True
            keep[s.index - 1] = True  # the last old sample ends its hold's spline
        self._samples = np.flatnonzero(keep)
        base = t[self._samples]
        # each step's points (old level, new level, the lag's unobserved ones) before its first new sample
        sg = step_grid(base, self.step_time, self.step_window, fractions=effects.STEP_FRACTIONS)
        self._steps = sg
        is_step, pos_step, grid = sg.is_step, sg.pos_step, sg.grid
        n = len(grid)
        self._obs_pos = np.flatnonzero(~is_step)
        self._base_grid = grid
        hold = np.empty(n, dtype=np.int64)
        hold[~is_step] = self.sample_hold[self._samples]
        hold[pos_step] = np.arange(ns)
        hold[sg.pos_new] = np.arange(ns)[:, None] + 1
        self._grid_hold = hold
        bounds = [exp.channel(c) for c in rig.boundaries.values()]
        self._bounds = np.array([np.interp(grid, t, smooth_boundary(t, np.asarray(b, float), smooth)) for b in bounds])
        self.shift_bound = sg.shift_bound
        # segments (holds) for the interpolation: grid samples and all samples per hold
        self._segments = []
        grid_hold_obs = hold[self._obs_pos]
        for h in range(ns + 1):
            g = np.flatnonzero(grid_hold_obs == h)
            a = np.flatnonzero(self.sample_hold == h)
            if len(a):
                if len(g) == 0:
                    raise ModelError(f"hold {h} of {exp.path} has no grid point")
                self._segments.append((g, a))
        if len(t) < 2:
            raise DataError(str(exp.path), "a run needs at least two samples", "record a longer experiment")

    @property
    def n_grid(self):
        """Points the integrator lands on."""
        return len(self._base_grid)

    def grid(self, shift):
        """Per-draw time grids ``(nd, n_grid)`` for step shifts ``shift`` [s]."""
        return self._steps.shifted(shift)

    def simulate(self, params, shift, *, at="samples", strict=True, start=None):
        """Simulate the run.

        Parameters
        ----------
        params : mapping
            Model parameters, scalars or arrays ``(nd,)`` (SI; rig nominal and
            effects zero if absent).
        shift : float or ndarray, shape (nd,)
            Step shift [s] (see the module docstring).
        at : {"samples", "grid"}
            Return every sample of the run, or only the samples on the grid
            (``grid_samples`` gives their indices).
        strict : bool
            Raise :class:`~tembayes.errors.ModelError` for a failed draw
            (else it comes back as NaN).
        start : float or ndarray, shape (nd,), optional
            Pre-history current per draw [A]; default :attr:`start_current`.

        Returns
        -------
        sensors : ndarray, shape (nd, ns, n)
            The rig's sensors (:attr:`sensor_channels`) [K].
        voltage : ndarray, shape (nd, n)
            Terminal voltage [V].
        """
        m = build(params, self.rig)
        nd = m["nd"]
        a, b, f = self.rig.readout(self.sensor_channels, m["params"])
        rec = np.concatenate([a, b]).astype(np.int64)
        shift = np.broadcast_to(np.atleast_1d(np.asarray(shift, dtype=float)), (nd,))
        G = self.grid(shift)
        Ic = np.repeat(self.levels[self._grid_hold][None, :], nd, axis=0)
        start = self.start_current if start is None else start
        # the steady state of the pre-history current, a millisecond before the first sample
        G = np.concatenate([G[:, :1] - 1e-3, G], axis=1)
        first = Ic[:, :1] if start is None else np.broadcast_to(np.asarray(start, float), (nd,))[:, None]
        Ic = np.ascontiguousarray(np.concatenate([first, Ic], axis=1))
        bounds = np.concatenate([self._bounds[:, :1], self._bounds], axis=1)
        y0 = self._initial_states(m, Ic[:, 0], G[:, 0], (a, b, f)) if self.start == "data" else None
        out, volt, failed, _ = integrate_on_grids(m, G, Ic, bounds, rec, self.atol, self.hmax, y0=y0)
        if strict and np.any(failed):
            raise ModelError(
                f"the simulation of {self.exp.path} failed for {int(failed.sum())} of {nd} draws "
                "(no steady start, step budget exceeded or non-finite values)"
            )
        nch = len(a)
        sensors = out[:, :, :nch] + f[:, None, :] * (out[:, :, nch:] - out[:, :, :nch])
        sensors = np.ascontiguousarray(sensors.transpose(0, 2, 1))
        self.rig.read_leads(sensors, self.sensor_channels, m["params"], bounds)
        lags = self.rig.sensor_lags(self.sensor_channels, m["params"])
        if effects.has_sensor_effect(m["params"], lags):
            effects.apply_sensors(G, sensors, m["params"], lags)  # each draw's own step instants
        sensors, volt = sensors[:, :, 1:], volt[:, 1:]
        o = self._obs_pos
        sensors, volt = sensors[:, :, o], volt[:, o]
        if at == "grid":
            return sensors, volt
        if at != "samples":
            raise ValueError(f"at must be 'samples' or 'grid', got {at!r}")
        return self._interpolate(sensors), self._interpolate(volt[:, None, :])[:, 0]

    @cached_property
    def noise(self):
        """White measurement noise of every channel (:attr:`channels`), ``(nch,)`` (K, V).

        Read off the run (:func:`~tembayes.data.quality.noise_estimate`:
        second differences, robust), so a model's misfit never enters it; a
        channel without any gets 1e-4.
        """
        sd = np.array([noise_estimate(y) for y in self.measured])
        return np.where(np.isfinite(sd) & (sd > 0), sd, 1e-4)

    def fit_phase(self, params, n=21):
        """The run's step phase that fits one parameter point best [s].

        The phase (the shift of every step from the middle of its sampling
        interval, see the module docstring) belongs to the run's clocks, not
        to the module: a model compared with a run may take it from the run.
        It matters for minutes: a step 0.45 s late moves a heat impulse of
        ``S T dI`` x 0.45 s (~7 J at 1 A) into a block, ~0.1 K on the reference rig's cold-face sensor that
        decays with the block.  Least squares over the sensors and the
        voltage (each scaled by its measurement noise) on ``n`` phases across
        the interval, refined by the parabola through the best three.

        Parameters
        ----------
        params : mapping
            One parameter point (scalars or shape ``(1,)``, SI).
        n : int

        Returns
        -------
        float
        """
        b = self.shift_bound
        if b <= 0:
            return 0.0
        s = np.linspace(-b, b, n) * (1 - 1e-9)
        P = {k: np.repeat(np.ravel(np.asarray(v, float))[:1], n) for k, v in params.items()}
        sens, volt = self.simulate(P, s, at="grid", strict=False)
        idx = self.grid_samples
        y = self.measured[:, idx]
        # the weights from the samples compared (the grid's), as the benchmark ran;
        # there second differences see some of the blocks' response on the far sensors
        sd = np.array([noise_estimate(np.asarray(y[c], float)) for c in range(len(y))])
        sd = np.where(np.isfinite(sd) & (sd > 0), sd, 1e-3)
        F = np.concatenate([sens, volt[:, None]], axis=1)
        cost = np.sum(((y[None] - F) / sd[None, :, None]) ** 2, axis=(1, 2))
        cost = np.where(np.isfinite(cost), cost, np.inf)
        k = int(np.argmin(cost))
        if 0 < k < n - 1 and np.all(np.isfinite(cost[k - 1 : k + 2])):
            c0, c1, c2 = cost[k - 1 : k + 2]
            den = c0 - 2 * c1 + c2
            if den > 0:
                return float(np.clip(s[k] + 0.5 * (s[1] - s[0]) * (c0 - c2) / den, -b * (1 - 1e-9), b * (1 - 1e-9)))
        return float(s[k])

    def _initial_states(self, m, current, t, readout, modes=4):
        """``(nd, N)``: the steady states under ``current`` [A], moved to the run's first samples.

        Moved along the ``modes`` slowest modes of the network until the sensors
        (``readout``: ``(a, b, f)`` of :meth:`RigDescription.readout`) read the
        run's first samples.
        """
        N = len(m["network"].nodes)
        G = np.stack([t - 1e-3, t], axis=1)
        I = np.ascontiguousarray(np.repeat(np.asarray(current, float)[:, None], 2, axis=1))
        xs, _, _, _ = integrate_on_grids(
            m,
            G,
            I,
            np.repeat(self._bounds[:, :1], 2, axis=1),
            np.arange(N, dtype=np.int64),
            self.atol,
            self.hmax,
        )
        xs = xs[:, -1]
        # the network's conduction with the module's own (K along its chain of plates and legs):
        # L symmetric, dx/dt = C^-1 L x, so C^(-1/2) L C^(-1/2) is symmetric and its eigenvectors the modes
        net = m["network"]
        L = net.G.copy()
        tem = m["tem"]
        g = m["params"]["K_W_per_K"] * (len(tem) - 1)
        for a, b in zip(tem[:-1], tem[1:]):
            L[:, a, b] += g
            L[:, b, a] += g
        idx = np.arange(N)
        L[:, idx, idx] -= L.sum(axis=2) + net.Gb.sum(axis=2)
        root = np.sqrt(net.C)
        w, U = np.linalg.eigh(L / root[:, :, None] / root[:, None, :])
        V = U[:, :, -modes:] / root[:, :, None]  # the slowest: eigenvalues nearest zero
        first = self.measured[:-1, 0]
        a, b, f = readout
        # a sensor with leads reads (1 - s) of its nodes and s of the room (RigDescription.lead_shares)
        mix = (xs[:, a] + f * (xs[:, b] - xs[:, a]))[:, :, None]
        self.rig.read_leads(mix, self.sensor_channels, m["params"], self._bounds[:, :1])
        keep = 1.0 - self.rig.lead_shares(self.sensor_channels, m["params"])
        M = keep[:, :, None] * (V[:, a, :] + f[:, :, None] * (V[:, b, :] - V[:, a, :]))
        r = first[None] - mix[:, :, 0]
        MtM = np.einsum("dij,dik->djk", M, M) + 1e-9 * np.eye(modes)
        coef = np.linalg.solve(MtM, np.einsum("dij,di->dj", M, r)[..., None])[..., 0]
        x0 = xs + np.einsum("dnk,dk->dn", V, coef)
        x0[~np.all(np.isfinite(x0), axis=1)] = np.nan
        return x0

    def fit_start(self, params, n=25):
        """Take the run's initial state from its first minute; sets and returns :attr:`start_current`.

        The pre-history current whose steady state, followed by the run's own
        current, fits the sensors and the voltage over the first
        :data:`START_WINDOW_S` seconds best (least squares, each channel in
        units of its noise): the best of ``n`` currents across
        +-:data:`START_SPAN` x the run's largest level, then of ``n`` across
        its two neighbours, refined by the parabola through the best three.
        The second grid matters: the cost is far from quadratic over the
        first's spacing (Peltier heat is linear in the current, Joule heat
        quadratic), and a parabola there put the vertex where the cost was
        19 times its minimum.

        Parameters
        ----------
        params : mapping
            One parameter point (scalars or shape ``(1,)``, SI), e.g. the
            posterior's median.
        n : int

        Returns
        -------
        float
            [A]
        """
        span = START_SPAN * max(float(np.max(np.abs(self.levels))), 0.1)
        cand = np.linspace(-span, span, n)
        k = int(np.argmin(self._start_cost(params, cand)))
        cand = np.linspace(cand[max(k - 1, 0)], cand[min(k + 1, n - 1)], n)
        cost = self._start_cost(params, cand)
        k = int(np.argmin(cost))
        best = float(cand[k])
        if 0 < k < n - 1 and np.all(np.isfinite(cost[k - 1 : k + 2])):
            c0, c1, c2 = cost[k - 1 : k + 2]
            den = c0 - 2 * c1 + c2
            if den > 0:
                best = float(cand[k] + 0.5 * (cand[1] - cand[0]) * (c0 - c2) / den)
        self.start_current = best
        return best

    def _start_cost(self, params, currents):
        """The first minute's misfit (sum of squares in noise units) for each pre-history current [A]."""
        m = len(currents)
        P = {k: np.repeat(np.ravel(np.asarray(v, float))[:1], m) for k, v in params.items()}
        sens, volt = self.simulate(P, 0.0, at="grid", strict=False, start=currents)
        idx = self.grid_samples
        early = self.time[idx] <= self.time[0] + START_WINDOW_S
        y = self.measured[:-1, idx][:, early]
        v = self.measured[-1, idx][early]
        # the voltage too: it reads the junctions, whose fast modes the block sensors barely see
        cost = np.sum(((y[None] - sens[:, :, early]) / self.noise[None, :-1, None]) ** 2, axis=(1, 2)) + np.sum(
            ((v[None] - volt[:, early]) / self.noise[-1]) ** 2, axis=1
        )
        return np.where(np.isfinite(cost), cost, np.inf)

    @property
    def grid_samples(self):
        """Indices of the run's samples that are grid points."""
        return self._samples

    def _interpolate(self, Y):
        """Grid-sample values ``(nd, nc, n_grid_obs)`` -> every sample ``(nd, nc, n)``."""
        nd, nc = Y.shape[:2]
        ok = np.all(np.isfinite(Y), axis=(1, 2))
        if not ok.all():  # failed draws (strict=False) stay NaN; the spline takes the others
            out = np.full((nd, nc, len(self.time)), np.nan)
            if ok.any():
                out[ok] = self._interpolate(Y[ok])
            return out
        out = np.empty((nd, nc, len(self.time)))
        tg = self.time[self._samples]
        for g, a in self._segments:
            if len(g) == 1:
                out[:, :, a] = Y[:, :, g]
            elif len(g) == 2:
                w = (self.time[a] - tg[g[0]]) / (tg[g[1]] - tg[g[0]])
                out[:, :, a] = Y[:, :, g[0], None] * (1 - w) + Y[:, :, g[1], None] * w
            else:
                out[:, :, a] = CubicSpline(tg[g], Y[:, :, g], axis=2)(self.time[a])
        return out
