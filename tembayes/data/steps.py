"""Current steps and holds of a staircase experiment.

The amplifier makes the current a clean staircase, but the shunt measurement
carries noise (~1 mA), sampling may be uneven, and steps may be small.  A
step is a jump between two consecutive samples that is large against the
noise of the first differences; consecutive jumps (a step caught half-way by
a sample) are merged; and a step must change the *level* (median of the holds
on both sides), which rejects spikes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

_MAD_TO_SD = 1.4826
#: What the calibration needs of an identification run: this many steps, and this long [s]
#: at rest before the first one (the model starts from the steady state at the first sample).
CALIBRATE_MIN_STEPS = 4
CALIBRATE_LEAD_S = 30.0


@dataclass(frozen=True)
class Step:
    """A current step and the hold that follows it.

    Attributes
    ----------
    index : int
        First sample at the new level.
    t : float
        Step instant [s]: midway between the last old and first new sample.
    t_window : float
        Half the sampling interval around the step: the instant is known to
        +- this [s].
    i_before, i_after : float
        Median current of the holds before and after [A].
    hold_start, hold_end : int
        Sample range ``[hold_start, hold_end)`` of the hold after the step.
    prev_start : int
        First sample of the hold before the step.
    """

    index: int
    t: float
    t_window: float
    i_before: float
    i_after: float
    hold_start: int
    hold_end: int
    prev_start: int

    @property
    def dI(self) -> float:
        """Current change [A]."""
        return self.i_after - self.i_before

    @property
    def direction(self) -> str:
        """``"up"`` for a current increase, ``"down"`` for a decrease."""
        return "up" if self.dI > 0 else "down"


def current_noise(current: np.ndarray) -> float:
    """Robust noise level of a staircase current [A] (MAD of first differences)."""
    d = np.diff(np.asarray(current, dtype=float))
    return float(_MAD_TO_SD * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


#: Samples after a step whose median is the new level a split step's samples are compared with.
LEVEL_SAMPLES = 10


def _first_at_new_level(i, group, tol, stop):
    """The first sample of a step's differences ``group`` within ``tol`` [A] of the level after it.

    A pair of same-sign differences is a sample caught mid-transition, or a step followed by a
    noise excursion of the same sign; only in the first case does the middle sample sit away from
    the new level, so the boundary is the first sample that does not.  The level is the median
    of up to :data:`LEVEL_SAMPLES` samples after the group, none at or beyond ``stop`` (the next
    group's first sample past its jump), so a short hold's level is its own.
    """
    last = group[-1] + 1
    level = np.median(i[last : min(last + LEVEL_SAMPLES, stop)])
    for j in range(group[0] + 1, last):
        if abs(i[j] - level) <= tol:
            return j
    return last


def detect_steps(
    time: np.ndarray, current: np.ndarray, *, min_step: float | None = None, min_hold: float = 5.0
) -> list[Step]:
    """Find the steps of a staircase current.

    Parameters
    ----------
    time : ndarray, shape (n,)
        Sample times [s], strictly increasing (sampling may be uneven).
    current : ndarray, shape (n,)
        Measured current [A].
    min_step : float, optional
        Smallest step to report [A]; default ``max(10 * noise, 0.01 A)``.
    min_hold : float, optional
        Holds shorter than this [s] are merged into the next step (a ramp
        or a glitch, not a step of the staircase).

    Returns
    -------
    list of Step
    """
    t = np.asarray(time, dtype=float)
    i = np.asarray(current, dtype=float)
    sigma = current_noise(i)
    thr = max(10.0 * sigma, 0.01) if min_step is None else float(min_step)
    d = np.diff(i)
    # a step split over two intervals (sampled mid-transition) shows as two
    # large differences of the same sign in a row: take the pair as one
    cand = np.flatnonzero(np.abs(d) > 0.5 * thr)
    groups = []
    for k in cand:
        if groups and k == groups[-1][-1] + 1 and np.sign(d[k]) == np.sign(d[groups[-1][-1]]):
            groups[-1].append(k)
        else:
            groups.append([k])
    # boundaries between holds: the first sample at the new level
    stops = [g[0] + 1 for g in groups[1:]] + [len(i)]
    bounds = [_first_at_new_level(i, g, 0.5 * thr, stop) for g, stop in zip(groups, stops) if abs(d[g].sum()) > thr]
    bounds = [b for b in bounds if 0 < b < len(i)]
    # drop holds shorter than min_hold
    edges = [0] + bounds + [len(i)]
    keep = [0]
    for b, nxt in zip(edges[1:-1], edges[2:]):
        if t[nxt - 1] - t[b] >= min_hold and t[b] - t[keep[-1]] >= min_hold:
            keep.append(b)
    edges = keep + [len(i)]
    # a boundary that does not change the level is a spike: merge its holds
    changed = True
    while changed:
        changed = False
        for j in range(1, len(edges) - 1):
            before = np.median(i[edges[j - 1] : edges[j]])
            after = np.median(i[edges[j] : edges[j + 1]])
            if abs(after - before) < thr:
                del edges[j]
                changed = True
                break
    steps = []
    for a, b, c in zip(edges[:-2], edges[1:-1], edges[2:]):
        steps.append(
            Step(
                index=int(b),
                t=float(0.5 * (t[b - 1] + t[b])),
                t_window=float(0.5 * (t[b] - t[b - 1])),
                i_before=float(np.median(i[a:b])),
                i_after=float(np.median(i[b:c])),
                hold_start=int(b),
                hold_end=int(c),
                prev_start=int(a),
            )
        )
    return steps
