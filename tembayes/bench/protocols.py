"""The experiments a test bench runs (``docs/data-format.md``, 'The identification run').

A protocol is a list of current holds.  :func:`identification_staircase`
is the paper's identification run (0 -> +0.8 A -> -1.6 A -> 0 in 0.2 A steps,
each held ~600 s), :func:`plate_staircase` the same run on a rig whose plates
hold both module faces (repeated at several plate temperatures, since there
the current alone barely moves the mean temperature) and
:func:`validation_cycle` the diagnostic-device-like validation run.
Levels are given for the reference module (Imax 6.4 A) and scale with the
datasheet's Imax, so another module type sees the same relative load.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tembayes.constants import KELVIN

if TYPE_CHECKING:
    from collections.abc import Sequence

REFERENCE_IMAX = 6.4  # [A] the module the reference levels were written for
#: The reference staircase's turning levels (top, bottom) for the reference module [A].
REFERENCE_TURNS_A = (0.8, -1.6)
#: Plate temperatures of :func:`plate_staircase` [degC]: a 40 K span of the mean temperature,
#: about the reference staircase's on the reference rig.
PLATE_SETPOINTS_C = (15.0, 35.0, 55.0)
#: Step of :func:`plate_staircase`'s current staircases, for the reference module [A].
PLATE_STEP_A = 0.4
#: Time constant of a circulator settling to a new setpoint [s] (a bath of a few litres).
CIRCULATOR_TAU_S = 90.0


@dataclass(frozen=True)
class Protocol:
    """Piecewise-constant true current.

    Attributes
    ----------
    levels : ndarray, shape (n,)
        Current of each hold [A].
    durations : ndarray, shape (n,)
        Duration of each hold [s].
    setpoints : ndarray, shape (n,), optional
        Setpoint of the rig's controlled boundaries during each hold [K];
        None: the bench's fixed setpoint.
    """

    levels: np.ndarray
    durations: np.ndarray
    setpoints: np.ndarray | None = None

    @property
    def step_times(self) -> np.ndarray:
        """Times of the current steps from the protocol start [s]."""
        return np.cumsum(self.durations)[:-1]

    @property
    def edges(self) -> np.ndarray:
        """Start of every hold and the end of the run [s], shape (n + 1,)."""
        return np.concatenate([[0.0], np.cumsum(self.durations)])

    @property
    def duration(self) -> float:
        """Total duration of the protocol [s]."""
        return float(np.sum(self.durations))

    def current(self, t: np.ndarray) -> np.ndarray:
        """True current [A] at times ``t`` [s] from the protocol start."""
        idx = np.searchsorted(self.step_times, t, side="right")
        return self.levels[np.minimum(idx, len(self.levels) - 1)]

    def setpoints_C(self) -> list[float] | None:
        """The distinct setpoints in the order run [degC] (to the µK); None without setpoints."""
        if self.setpoints is None:
            return None
        return [round(float(v) - KELVIN, 6) for v in dict.fromkeys(self.setpoints)]

    def setpoint(self, t: np.ndarray) -> np.ndarray | None:
        """The controlled boundaries' temperature [K] at times ``t`` [s]; None without setpoints.

        Each new setpoint is approached with the time constant :data:`CIRCULATOR_TAU_S`.
        """
        if self.setpoints is None:
            return None
        t = np.asarray(t, dtype=float)
        out = np.full(t.shape, float(self.setpoints[0]))
        starts = np.concatenate([[0.0], self.step_times])
        for k in np.flatnonzero(np.diff(self.setpoints)) + 1:
            late = t > starts[k]
            dt = t[late] - starts[k]
            out[late] += (self.setpoints[k] - self.setpoints[k - 1]) * -np.expm1(-dt / CIRCULATOR_TAU_S)
        return out


def identification_staircase(
    imax: float = REFERENCE_IMAX,
    hold: float = 600.0,
    step: float = 0.2,
    top: float = REFERENCE_TURNS_A[0],
    bottom: float = REFERENCE_TURNS_A[1],
) -> Protocol:
    """The identification staircase: every level visited by an up- and a down-step.

    Parameters
    ----------
    imax : float
        Datasheet Imax of the module [A]; levels scale with ``imax / 6.4``.
    hold : float
        Duration of each hold [s].
    step, top, bottom : float
        Step size and turning levels for the reference module [A].
    """
    up = np.arange(0.0, top + 1e-9, step)
    down = np.arange(top - step, bottom - 1e-9, -step)
    back = np.arange(bottom + step, 0.0 + 1e-9, step)
    levels = np.round(np.concatenate([up, down, back]), 6) * imax / REFERENCE_IMAX
    return Protocol(levels, np.full(len(levels), float(hold)))


def plate_staircase(
    imax: float = REFERENCE_IMAX,
    hold: float = 600.0,
    setpoints_C: Sequence[float] = PLATE_SETPOINTS_C,
    step: float = PLATE_STEP_A,
) -> Protocol:
    """The identification run on plates that hold both faces: a staircase at each plate temperature.

    At each setpoint the current runs 0 -> +0.8 -> -1.6 -> 0 A in ``step``
    steps (levels for the reference module, scaled by ``imax / 6.4``).  Each
    staircase after the first starts with its 0 A hold at the new setpoint,
    during which the plates move there, so the rig rests for two holds
    between staircases: the previous one's last and this one's first.

    Parameters
    ----------
    imax : float
        Datasheet Imax of the module [A].
    hold : float
        Duration of each hold [s].
    setpoints_C : sequence of float
        Plate temperatures [degC], in the order run.
    step : float
        Step of the reference module's staircase [A].
    """
    one = identification_staircase(imax, hold=hold, step=step)
    levels = np.concatenate([one.levels] * len(setpoints_C))
    n = len(one.levels)
    setpoints = np.repeat(np.asarray(setpoints_C, dtype=float) + KELVIN, n)
    return Protocol(levels, np.full(len(levels), float(hold)), setpoints)


def validation_cycle(
    rng: np.random.Generator,
    imax: float = REFERENCE_IMAX,
    duration: float = 4 * 3600.0,
    low: float = -1.6,
    high: float = 0.9,
    hold_range: tuple[float, float] = (300.0, 1200.0),
    rest: float = 300.0,
) -> Protocol:
    """A validation run: random holds between ``low`` and ``high`` amperes.

    Starts with a ``rest`` [s] at 0 A (0: straight into the first level);
    levels are drawn on a 0.05 A grid so that consecutive holds differ by at
    least 0.15 A.
    """
    levels, durations = ([0.0], [float(rest)]) if rest > 0 else ([0.0], [0.0])
    total = float(rest)
    grid = np.round(np.arange(low, high + 1e-9, 0.05), 6)
    while total < duration:
        while True:
            lv = float(rng.choice(grid))
            if abs(lv - levels[-1]) >= 0.15:
                break
        d = float(np.round(rng.uniform(*hold_range)))
        levels.append(lv)
        durations.append(d)
        total += d
    if rest <= 0:  # no rest hold: the placeholder only made the first level differ from 0 A
        levels, durations = levels[1:], durations[1:]
    scale = imax / REFERENCE_IMAX
    return Protocol(np.array(levels) * scale, np.array(durations))


def sample_times(
    rng: np.random.Generator, duration: float, rate: float = 5.0, jitter: float = 0.002, t0: float = 0.0
) -> np.ndarray:
    """Sample times of a data-acquisition system [s].

    ``rate`` Hz with timing jitter, on a clock whose phase is independent of
    the protocol's (the DAQ and the current programme run on different
    timers), so current steps fall anywhere between two samples.
    """
    phase = rng.uniform(0.0, 1.0 / rate)
    n = int(np.floor((duration - phase) * rate)) + 1
    t = phase + np.arange(n) / rate
    t[1:-1] += rng.uniform(-jitter, jitter, n - 2)
    return t0 + t


def boundary_drifts(
    rng: np.random.Generator,
    t: np.ndarray,
    rooms: Sequence[bool] = (False, True),
    *,
    controlled: float | np.ndarray | None = None,
    room: float = 22.0 + 273.15,
) -> np.ndarray:
    """True boundary temperatures ``(nb, len(t))`` [K] at times ``t`` [s], in the rig's boundary order.

    A controlled boundary (a chiller, a liquid loop) wobbles by a few
    hundredths of a kelvin about ``controlled`` [K] (a control cycle of a few
    minutes plus a little wander; a constant, the setpoint at each of
    ``t`` (:meth:`Protocol.setpoint`), or None: 20 degC); the room (``rooms[k]`` true) drifts by a
    few tenths of a kelvin over hours about ``room``.  The default is the
    reference rig's: the water, then the room.
    """
    controlled = 20.0 + KELVIN if controlled is None else controlled
    out = []
    for is_room in rooms:
        if is_room:
            out.append(room + rng.uniform(-1.0, 1.0) + _smooth_walk(rng, t, 0.25, 3600.0))
            continue
        period = rng.uniform(200.0, 400.0)
        phase = rng.uniform(0, 2 * np.pi)
        x = controlled + rng.uniform(-0.3, 0.3) + 0.02 * np.sin(2 * np.pi * t / period + phase)
        out.append(x + _smooth_walk(rng, t, 0.01, 600.0))
    return np.array(out)


def _smooth_walk(rng, t, sd, tau):
    """A stationary Ornstein-Uhlenbeck path with standard deviation ``sd`` and time constant ``tau`` [s]."""
    knots = np.arange(t[0], t[-1] + tau / 10, tau / 10)
    a = np.exp(-0.1)
    x = np.empty(len(knots))
    x[0] = rng.normal(0, sd)
    e = rng.normal(0, sd * np.sqrt(1 - a * a), len(knots))
    for i in range(1, len(knots)):
        x[i] = a * x[i - 1] + e[i]
    return np.interp(t, knots, x)
