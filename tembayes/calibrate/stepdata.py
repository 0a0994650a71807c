"""What the step likelihood looks at: the identification run cut into step responses.

Every current step of the staircase starts a response: the voltage jumps by
``R(T) dI`` at once, then drifts as the plates, legs and blocks heat or cool
(the Seebeck back-EMF ``S(T) dT(t)`` building up) until ``dT`` settles at the
end of the hold.  A step's *window* is the hold that follows it plus a few
samples just before it (the level the jump starts from).

The windows keep every sample of the first seconds after the step (the jump
and the fast plate transient, where the voltage carries ``R``) and
log-spaced samples after that (the slow block response and the steady state,
where ``dT`` and the voltage carry ``S`` and ``K``).  Log spacing keeps the
information of each time scale at ~50 points per step, so a simulation of all
windows costs ~1/50 of the whole run.

The channels compared are the voltage, the temperature difference ``dT``
between the rig's face sensors (the sensor nearest each module face,
:attr:`~tembayes.physics.layout.Layout.face`; T2 - T3 on the reference rig)
and their mean (which fixes the temperature the laws are evaluated at).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.signal import savgol_filter

from tembayes.data.quality import noise_estimate
from tembayes.data.steps import CALIBRATE_LEAD_S, CALIBRATE_MIN_STEPS, current_noise, detect_steps
from tembayes.errors import DataError

if TYPE_CHECKING:
    from collections.abc import Iterable

    from numpy.typing import ArrayLike

    from tembayes.data.experiment import Experiment

#: Channels of the step likelihood, in the order of every channel axis.
CHANNELS = ("voltage_V", "dT_K", "Tmean_K")

#: Least noise sd the likelihood assumes per sensor temperature [K], voltage [V]
#: and current [A].  Data cleaner than this (a simulation without noise) would
#: ask the model for more precision than its integration gives
#: (``tembayes.calibrate.model.ATOL``, 0.1 mK), and a noise estimate of zero
#: makes the posterior mode's least squares singular.  A logger's resolution
#: raises the floor to its rounding error (:func:`_noise_sd`).
NOISE_FLOOR = {"temperature_K": 1e-4, "voltage_V": 1e-5, "current_A": 1e-6}


def _noise_sd(estimate, floor, *channels):
    """A noise sd no smaller than ``floor`` nor the channels' rounding error.

    The rounding error is ``q / sqrt(12)``, ``q`` the smallest change any of the channels shows: a quiet
    signal logged at a coarse resolution repeats its values, and the noise estimate from differences is
    then zero however large the rounding error is.
    """
    steps = np.concatenate([np.abs(np.diff(np.asarray(c, dtype=float))) for c in channels])
    steps = steps[steps > 0]
    rounding = float(steps.min()) / np.sqrt(12.0) if steps.size else 0.0
    return max(estimate, rounding, floor)


#: Duration of the current ramp of a step in the model [s] (an amplifier
#: slews in about a millisecond; the exact value does not matter below 10 ms).
RAMP = 1e-3


@dataclass(frozen=True)
class StepData:
    """The selected samples of every step response of one experiment (SI).

    Attributes
    ----------
    source : str
        File the data came from.
    t0 : float
        Start of the simulation [s] (steady state assumed there).
    step_time : ndarray, shape (ns,)
        Nominal step instants [s]: midway between the last sample at the old
        level and the first at the new one.
    step_window : ndarray, shape (ns,)
        Half the sampling interval around each step [s]: the true instant is
        within ``step_time +- step_window``.
    levels : ndarray, shape (ns + 1,)
        Current of every hold [A] (mean of the measured current over the
        hold), the hold before the first step first.
    level_sd : ndarray, shape (ns + 1,)
        Standard error of each level [A]: the current noise over the root of
        the hold's sample count.  ~0.02 mA, yet it moves a hold's steady dT
        by ~0.7 mK (30 K/A), as much as the sensors resolve a level: the
        likelihood integrates these errors out.
    time : ndarray, shape (n,)
        Times of the selected samples [s].
    step : ndarray of int, shape (n,)
        Window (step number) of each selected sample.
    since : ndarray, shape (n,)
        Time since the nominal step [s] (negative just before it).
    obs : ndarray, shape (3, n)
        Observed ``voltage [V], dT [K], Tmean [K]`` (:data:`CHANNELS`).
    noise : ndarray, shape (3,)
        Measurement noise sd of each channel, estimated from the whole run.
    face : tuple of (str, str)
        The hot- and cold-face sensor columns ``dT`` is read from.
    boundary_names : tuple of str
        The boundary columns of ``boundary_values``, in order.
    boundary_time : ndarray, shape (m,)
        The run's sample times [s].
    boundary_values : ndarray, shape (nb, m)
        The smoothed boundary temperatures there [K], in the rig's order, for
        inputs at any time (:meth:`boundaries`).
    """

    source: str
    t0: float
    step_time: np.ndarray
    step_window: np.ndarray
    levels: np.ndarray
    level_sd: np.ndarray
    time: np.ndarray
    step: np.ndarray
    since: np.ndarray
    obs: np.ndarray
    noise: np.ndarray
    face: tuple
    boundary_names: tuple
    boundary_time: np.ndarray
    boundary_values: np.ndarray

    @property
    def n_steps(self) -> int:
        """Number of current steps."""
        return len(self.step_time)

    @property
    def window_starts(self) -> np.ndarray:
        """First selected sample of every step window, ``(ns,)``."""
        return np.flatnonzero(np.diff(np.concatenate([[-1], self.step])))

    @property
    def dI(self) -> np.ndarray:
        """Current change of every step [A]."""
        return np.diff(self.levels)

    @property
    def direction(self) -> np.ndarray:
        """+1 for an up-step, -1 for a down-step."""
        return np.sign(self.dI).astype(int)

    def boundaries(self, t: ArrayLike) -> np.ndarray:
        """Smoothed boundary temperatures ``(nb, len(t))`` [K] at times ``t`` [s]."""
        return np.array([np.interp(t, self.boundary_time, b) for b in self.boundary_values])


def hold_levels(current: np.ndarray, holds: Iterable[tuple[int, int]]) -> np.ndarray:
    """Current of each hold ``(start, stop)`` [A].

    The mean (the efficient estimate for the amplifier's white noise) leaving out two samples at
    either end, the median of a short hold.
    """
    return np.array([np.mean(current[a + 2 : b - 2]) if b - a > 8 else np.median(current[a:b]) for a, b in holds])


@dataclass(frozen=True)
class StepGrid:
    """A time grid with each current step's points (old level, new level, optional unobserved ones).

    Each draw moves the step instants within their sampling intervals.  The step may fall anywhere
    in its sampling interval: one common shift ranges over the widest interval and each step's
    instant is clipped into its own (the intervals differ by the DAQ's jitter).  A bound at the
    narrowest one excluded the true instant of ~5 % of the bench's runs and pulled R, S and K with
    the shift.

    Optionally each step is followed by unobserved points at ``fractions`` of the way from its
    new-level point to the next point (the first sample after it), which move with the step.  A
    sensor's first-order lag is integrated between grid points as if its input were linear there,
    and in the first second after a step a module plate's temperature is far from linear: at 1 Hz
    the lag's reading of the first sample after a 0.7 A step came out 0.07-0.24 K short.

    Attributes
    ----------
    grid : ndarray, shape (n,)
        The points, the step points at their nominal instants [s].
    pos_step : ndarray of int, shape (ns,)
        Index of each step's old-level point; the new-level point and the step's
        ``len(fractions)`` unobserved points follow it.
    step_time : ndarray, shape (ns,)
        Nominal step instants [s].
    lo, hi : ndarray, shape (ns,)
        Each step's shift bounds [s].
    shift_bound : float
        Largest common shift [s] (half the widest sampling interval, less a margin).
    fractions : tuple of float
        Where the unobserved points sit between the new-level point and the next point
        (increasing, in (0, 1)); empty: none.
    """

    grid: np.ndarray
    pos_step: np.ndarray
    step_time: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    shift_bound: float
    fractions: tuple = ()

    @property
    def pos_new(self) -> np.ndarray:
        """``(ns, 1 + len(fractions))`` indices of each step's points on its new level (none observed)."""
        return self.pos_step[:, None] + 1 + np.arange(1 + len(self.fractions))[None, :]

    @property
    def is_step(self) -> np.ndarray:
        """Boolean mask ``(n,)`` of the grid's step points (old level, new level, the unobserved ones)."""
        out = np.zeros(len(self.grid), bool)
        out[self.pos_step] = True
        out[self.pos_new.ravel()] = True
        return out

    def shifted(self, shift: ArrayLike) -> np.ndarray:
        """Per-draw grids ``(nd, n)`` for common step shifts ``shift`` [s]."""
        shift = np.atleast_1d(np.asarray(shift, dtype=float))
        G = np.repeat(self.grid[None, :], len(shift), axis=0)
        if len(self.step_time):
            G[:, self.pos_step] = self.step_time[None, :] + np.clip(shift[:, None], self.lo[None, :], self.hi[None, :])
            G[:, self.pos_step + 1] = G[:, self.pos_step] + RAMP
            if self.fractions:
                new = G[:, self.pos_step + 1]
                after = self.pos_step + 2 + len(self.fractions)
                # a step after the last point has no sample to resolve: its points stay within RAMP
                nxt = np.where(after < len(self.grid), G[:, np.minimum(after, len(self.grid) - 1)], new + RAMP)
                G[:, self.pos_new[:, 1:]] = new[:, :, None] + np.asarray(self.fractions) * (nxt - new)[:, :, None]
        return G


def step_grid(
    points: np.ndarray, step_time: ArrayLike, step_window: ArrayLike, eps: float = 1e-4, fractions: tuple = ()
) -> StepGrid:
    """Insert a step's points before the first of the sorted ``points`` after each nominal step.

    ``fractions``: see :class:`StepGrid`.

    Returns
    -------
    StepGrid
    """
    fractions = tuple(float(f) for f in fractions)
    if fractions and not (np.all(np.diff(fractions) > 0) and 0 < fractions[0] and fractions[-1] < 1):
        raise ValueError(f"fractions must increase strictly inside (0, 1), got {fractions}")
    ns = len(step_time)
    per = 2 + len(fractions)
    pos_step = np.searchsorted(points, step_time) + per * np.arange(ns)
    at_step = (pos_step[:, None] + np.arange(per)[None, :]).ravel()
    grid = np.empty(len(points) + per * ns)
    grid[at_step] = np.repeat(np.asarray(step_time, float), per)  # placed by shifted(0) below
    grid[np.setdiff1d(np.arange(len(grid)), at_step)] = points
    w = np.asarray(step_window, float)
    sg = StepGrid(
        grid,
        pos_step,
        np.asarray(step_time, float),
        -w + eps,
        w - RAMP - eps,
        float(np.max(w)) - eps if ns else 0.0,
        fractions,
    )
    return replace(sg, grid=sg.shifted(0.0)[0]) if ns else sg


#: Width of the local quadratic fit that takes the noise off a boundary input [s].
BOUNDARY_SMOOTH_S = 20.0


def smooth_boundary(time: np.ndarray, x: np.ndarray, width: float = BOUNDARY_SMOOTH_S) -> np.ndarray:
    """A boundary temperature with its noise smoothed off: a local quadratic over ``width`` seconds.

    A boundary's noise enters the model as an input error.  A moving average
    would take it off but bend a boundary that curves, by ``T'' w^2 / 24``:
    10 mK over 10 s on a liquid plate approaching a new setpoint with its
    circulator's 90 s time constant, which its sensor follows within
    seconds (3-4 noise sds of the mean temperature there, a false gap).  The
    quadratic (Savitzky-Golay) keeps a curve's shape; over 20 s its noise is
    about that of a 10 s average.
    """
    dt = float(np.median(np.diff(time)))
    n = int(round(width / dt)) | 1  # odd: a centre sample
    if n <= 3 or len(x) < n:
        return np.asarray(x, float).copy()
    return savgol_filter(np.asarray(x, float), n, 2, mode="interp")


def step_data(
    exp: Experiment,
    *,
    face: tuple[str, str],
    dense: float = 2.0,
    per_decade: int = 16,
    pre: float = 1.0,
    lead: float = CALIBRATE_LEAD_S,
    min_steps: int = CALIBRATE_MIN_STEPS,
    smooth: float = BOUNDARY_SMOOTH_S,
) -> StepData:
    """Cut an identification experiment into step-response windows.

    Parameters
    ----------
    exp : tembayes.data.Experiment
    face : tuple of (str, str)
        The columns of the sensors nearest the module's hot and cold faces
        (``rig.layout.face``).
    dense : float, optional
        Keep every sample in the first ``dense`` seconds after a step.
    per_decade : int, optional
        Log-spaced samples per decade of time-since-step after that.
    pre : float, optional
        Keep the samples in the last ``pre`` seconds before each step.
    lead : float, optional
        The run must rest at least this long before the first step [s].
        The simulation starts at the first sample, from the steady state
        there: the rest before the first step lets the model settle into
        the slow drifts of the boundaries.
    min_steps : int, optional
        Refuse a run with fewer steps (the laws need several temperatures).
    smooth : float, optional
        Width of the smoothing of the boundary inputs [s] (:func:`smooth_boundary`).

    Returns
    -------
    StepData

    Raises
    ------
    DataError
        Too few steps, or a step too close to the start of the run.
    """
    t = exp.time
    steps = detect_steps(t, exp.current)
    src = str(exp.path)
    if len(steps) < min_steps:
        raise DataError(
            src,
            f"found {len(steps)} current step(s); the calibration needs at least {min_steps}",
            "run the identification staircase (steps held until the temperatures settle)",
        )
    first = steps[0]
    if t[first.index] - t[0] < lead:
        raise DataError(
            src,
            f"the first current step comes {t[first.index] - t[0]:.1f} s after the start",
            f"record at least {lead:.0f} s at rest before the first step",
            line=first.index + 2,
        )
    holds = [(steps[0].prev_start, steps[0].index)] + [(s.hold_start, s.hold_end) for s in steps]
    cur = exp.current
    levels = hold_levels(cur, holds)
    counts = np.array([max(b - a - 4, 1) for a, b in holds], dtype=float)
    level_sd = _noise_sd(current_noise(cur), NOISE_FLOOR["current_A"], cur) / np.sqrt(counts)
    idx, win = [], []
    for k, s in enumerate(steps):
        start, stop = s.index, s.hold_end
        ts = t[start:stop] - s.t
        sel = set(np.flatnonzero(ts <= dense).tolist())
        if ts[-1] > dense:
            targets = np.geomspace(dense, ts[-1], max(2, int(np.ceil(per_decade * np.log10(ts[-1] / dense)))))
            sel.update(np.clip(np.searchsorted(ts, targets), 0, len(ts) - 1).tolist())
        sel.add(len(ts) - 1)
        before = np.flatnonzero((t[:start] >= s.t - pre))
        chosen = sorted(set(before.tolist()) | {start + j for j in sel})
        idx.extend(chosen)
        win.extend([k] * len(chosen))
    idx = np.asarray(idx)
    win = np.asarray(win)
    # a sample picked twice (end of one hold, pre-step of the next) belongs to the later step
    _, last = np.unique(idx[::-1], return_index=True)
    keep = np.sort(len(idx) - 1 - last)
    idx, win = idx[keep], win[keep]
    order = np.argsort(idx, kind="stable")
    idx, win = idx[order], win[order]
    hot, cold = (exp.channel(c) for c in face)
    obs = np.vstack([exp.voltage[idx], (hot - cold)[idx], 0.5 * (hot + cold)[idx]])
    sT = _noise_sd(np.nanmean([noise_estimate(hot), noise_estimate(cold)]), NOISE_FLOOR["temperature_K"], hot, cold)
    sV = _noise_sd(noise_estimate(exp.voltage), NOISE_FLOOR["voltage_V"], exp.voltage)
    noise = np.array([sV, np.sqrt(2.0) * sT, sT / np.sqrt(2.0)])
    bounds = np.array([smooth_boundary(t, b, smooth) for b in exp.boundaries])
    step_time = np.array([s.t for s in steps])
    return StepData(
        source=src,
        t0=float(t[0]),
        step_time=step_time,
        step_window=np.array([s.t_window for s in steps]),
        levels=levels,
        level_sd=level_sd,
        time=t[idx].copy(),
        step=win,
        since=t[idx] - step_time[win],
        obs=obs,
        noise=noise,
        face=tuple(face),
        boundary_names=exp.boundary_names,
        boundary_time=t.copy(),
        boundary_values=bounds,
    )
