"""Preflight: what a well-formed file can hold but a test rig cannot produce.

:func:`~tembayes.data.load_experiment` checks the file format; these checks
read the physics of the data and run before any command's work:

- **time**: logging gaps (the current and temperatures in between are
  unknown) and time stamps in the wrong unit, from how fast the sensors
  settle after a current step (a rig's blocks settle in minutes);
- **sensors**: a channel that is stuck (frozen while the others move),
  jumps faster than any block can change, or reads colder than the module
  can pump below the rig's boundaries;
- **polarity**: positive current must cool the cold (bottom) side, and the
  voltage must follow the current;
- **temperature units**: at zero current no part of the rig can sit outside
  the range of its boundary temperatures (one column in another unit), and
  the Seebeck voltage per kelvin must match the datasheet's order (a whole
  file in degF reads 1.8 times too many kelvin);
- **identifiability** of an identification run (warnings): current steps in
  both directions, holds long enough to settle, a wide enough range of the
  mean temperature.

Each finding names the file, the line and the column, and says what to do.
Errors refuse the input; warnings are printed and the work goes on.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..constants import KELVIN
from ..errors import DataError
from .quality import noise_estimate
from .steps import CALIBRATE_LEAD_S, CALIBRATE_MIN_STEPS, current_noise, detect_steps

if TYPE_CHECKING:  # batch.py and experiment.py import this module
    from collections.abc import Iterable, Mapping

    from ..physics.layout import Layout
    from .batch import Datasheet
    from .experiment import Experiment

__all__ = ["Finding", "check_experiment", "degf_evidence", "raise_first_error", "ERROR", "WARNING"]

ERROR = "error"
WARNING = "warning"

#: A time step this many times the median sampling interval is a gap ...
GAP_FACTOR = 10.0
#: ... if it is also longer than this [s].
GAP_MIN_S = 2.0
#: A gap is refused when longer than this [s] (or this many median intervals) ...
GAP_REFUSE_S = 30.0
GAP_REFUSE_FACTOR = 50.0
#: ... or when the current changes across it by more than this many noise sds (a step at an unknown instant).
GAP_STEP_SIGMAS = 10.0

#: A sensor frozen for this long [s] and this many samples while another moves by
#: STUCK_OTHERS_K is stuck.
STUCK_MIN_S = 60.0
STUCK_MIN_SAMPLES = 20
STUCK_OTHERS_K = 0.5
#: For a coarsely quantised channel, a frozen stretch must also be this many times
#: its longest other one.
STUCK_QUANTISED_RATIO = 10.0

#: A change between two samples above JUMP_K + JUMP_RATE_K_PER_S * dt is a glitch.
JUMP_K = 5.0
JUMP_RATE_K_PER_S = 5.0
#: A sensor colder than the coldest boundary minus dTmax minus this [K] is impossible.
COLD_MARGIN_K = 5.0

#: Sensor settling (63 % of the response after a current step) outside this range [s]
#: means the time stamps are not seconds: a rig's blocks take minutes (the reference rig
#: about 150 s), so a file in minutes reads a few time units and one in hours a few hundredths.
#: The limits are the reference rig's; a rig whose slowest time constant is shorter than
#: SETTLE_REFERENCE_TAU_S has them scaled down with it (liquid-cooled plates settle in seconds).
SETTLE_MAX_S = 6 * 3600.0
SETTLE_MIN_S = 10.0
SETTLE_REFERENCE_TAU_S = 165.0
#: The slower sensor's 63 % time is sure when it comes within this fraction of its median hold.
SETTLE_HOLD_FRACTION = 0.5
#: The lower limit when only one of the two sensors responded, or no hold was long enough [s].
SETTLE_MIN_UNSURE_S = 0.3

#: Along a heat path from a boundary to a module face through the rig's sensors
#: (:attr:`~tembayes.physics.layout.Layout.paths`) one heat flow crosses every settled hold, so
#: the steps along it rise and fall together: two neighbouring steps are out of order when, over
#: the settled holds, they anti-correlate below this and the first spans at least SERIES_MIN_SPAN_K.
SERIES_MAX_CORR = -0.8
SERIES_MIN_SPAN_K = 0.2
SERIES_MIN_HOLDS = 4

#: Zero-current holds this many settling times long are used for the maximum principle ...
ZERO_HOLD_SETTLINGS = 2.0
#: ... with this margin [K] plus this fraction of the sensor's change over the hold, at least ...
ZERO_MARGIN_K = 2.0
ZERO_MARGIN_FRACTION = 0.2
#: ... this many times what a hold of ``h`` leaves of a relaxation with the rig's slowest time
#: constant ``tau``, per kelvin moved: ``r / (1 - r)``, ``r = exp(-h / tau)`` (short holds, e.g. a
#: designed staircase's 240 s against the reference rig's 165 s, end well before the rig settles).
ZERO_MARGIN_SAFETY = 1.5

#: Seebeck ratio (the voltage per degree of the face sensors at zero current, over the datasheet's S)
#: in [LOW, this) with a tight linear fit (R^2 >= SEEBECK_MIN_R2) reads degF; in degC it is 0.85-0.9 on
#: the reference rig, in degF 1.8 times less.
SEEBECK_RATIO_DEGF = 0.62
SEEBECK_RATIO_DEGF_LOW = 0.35
SEEBECK_MIN_R2 = 0.8
#: Samples with the face sensors' difference above this [K] at zero current are needed, at least SEEBECK_MIN_SAMPLES.
SEEBECK_MIN_DT_K = 0.5
SEEBECK_MIN_SAMPLES = 200

#: Identification-run checks: holds shorter than this many settling times (a warning); T-bar span
#: below this [K] (refused by calibrate).
HOLD_SETTLINGS = 2.0
TAVG_SPAN_MIN_K = 5.0


@dataclass(frozen=True)
class Finding:
    """One preflight finding.

    Attributes
    ----------
    severity : str
        ``"error"`` (the input is refused) or ``"warning"``.
    path : Path
        The file.
    problem, hint : str
        What is wrong, and what to do.
    line : int, optional
        The file line (header = line 1).
    column : str, optional
        The column.
    refused_by : tuple of str
        Commands that refuse the input on this warning (``"calibrate"`` for
        an identification run it cannot use).
    """

    severity: str
    path: Path
    problem: str
    hint: str
    line: int | None = None
    column: str | None = None
    refused_by: tuple[str, ...] = ()

    def error(self) -> DataError:
        """The finding as the :class:`~tembayes.errors.DataError` that refuses the input."""
        return DataError(self.path, self.problem, self.hint, line=self.line, column=self.column)

    def __str__(self):
        return str(self.error())

    def to_json(self) -> dict:
        """JSON-ready dict of the finding (severity, path, line, column, problem, hint, refused_by)."""
        return {
            "severity": self.severity,
            "path": str(self.path),
            "line": self.line,
            "column": self.column,
            "problem": self.problem,
            "hint": self.hint,
            "refused_by": list(self.refused_by),
        }


def raise_first_error(findings: Iterable[Finding], *, command: str | None = None) -> None:
    """Raise the first error-level finding as a DataError (nothing to do without one).

    With ``command``, also the first warning that command refuses on.
    """
    for f in findings:
        if f.severity == ERROR or (command is not None and command in f.refused_by):
            raise f.error()


def check_experiment(
    exp: Experiment,
    *,
    datasheet: Datasheet | None = None,
    identification: bool = False,
    layout: Layout | None = None,
) -> list:
    """Every preflight check of one experiment.

    Parameters
    ----------
    exp : tembayes.data.Experiment
    datasheet : tembayes.data.Datasheet, optional
        Enables the checks that need the module type's scale (sensor range,
        Seebeck ratio).
    identification : bool
        Also the warnings on what the run can identify.
    layout : tembayes.physics.layout.Layout, optional
        Where the rig's sensors sit (face sensors, heat paths); default the
        reference rig.

    Returns
    -------
    list of Finding
        Errors first.
    """
    if layout is None:
        from .experiment import reference_layout  # experiment.py imports this module

        layout = reference_layout()
    steps = detect_steps(exp.time, exp.current)
    settle, slow, sure = _settling_time(exp, steps, layout.face)
    scale = min(1.0, layout.slowest_tau_s / SETTLE_REFERENCE_TAU_S)
    found = [*_gaps(exp), *_time_unit(exp, slow, sure, scale), *_stuck(exp), *_jumps(exp)]
    if datasheet is not None:
        found += _below_pumping(exp, datasheet)
    # each check below reads physics a broken sensor or clock (or the one before) would confound:
    # a column in another unit breaks the heat paths, and swapped sensors reverse the polarity test
    for check in (_zero_current_range, _sensor_order, _polarity):
        if not any(f.severity == ERROR for f in found):
            found += check(exp, steps, settle, layout)
    found += _unsettled(exp, steps, settle, layout)
    if identification:
        found += _identifiability(exp, steps, settle, layout.face)
    return sorted(found, key=lambda f: f.severity != ERROR)


def _finding(severity, exp, problem, hint, i=None, column=None, refused_by=()):
    return Finding(severity, exp.path, problem, hint, None if i is None else exp.line(i), column, refused_by)


# -- time ---------------------------------------------------------------------


def _gaps(exp):
    dt = np.diff(exp.time)
    if dt.size < 2:
        return []
    med = float(np.median(dt))
    gaps = np.flatnonzero(dt > max(GAP_FACTOR * med, GAP_MIN_S))
    if not gaps.size:
        return []
    sigma = max(current_noise(exp.current), 1e-4)
    out = []
    for k in gaps:
        before = float(np.median(exp.current[max(0, k - 4) : k + 1]))
        after = float(np.median(exp.current[k + 1 : k + 6]))
        stepped = abs(after - before) > GAP_STEP_SIGMAS * sigma
        refuse = stepped or dt[k] > max(GAP_REFUSE_S, GAP_REFUSE_FACTOR * med)
        what = f"a {dt[k]:.4g} s gap in the time stamps after {exp.where(k)} (the sampling interval is {med:.3g} s)"
        if stepped:
            what += f", and the current changed inside it from {before:+.3f} to {after:+.3f} A at an unknown instant"
        out.append(
            _finding(
                ERROR if refuse else WARNING,
                exp,
                what,
                "Split the experiment at the gap into two files, or record it again"
                if refuse
                else "The gap is short and the current held: the model interpolates across it",
                k + 1,
                "time_s",
            )
        )
    errors = [f for f in out if f.severity == ERROR]
    return errors[:1] + [f for f in out if f.severity == WARNING][:1]


def _settling_time(exp, steps, face):
    """How long the sensors next to the module take to cover 63 % of their move after a current step.

    Returns
    -------
    settle : float
        The median over every step and both sensors [s]: the scale of the
        holds the physics checks read.  NaN without a clear response.
    slow : float
        The slower sensor's median [s], for the time unit: the top sensor of
        a water-cooled rig moves little and fast while the bottom block
        takes minutes.  NaN without a clear response.
    sure : bool
        Both sensors responded, and the slower one's holds last beyond
        1/SETTLE_HOLD_FRACTION times ``slow`` (holds cut short of the
        response measure the hold, not the rig).
    """
    pooled, per_sensor = [], []
    for c in face:
        x = exp.channel(c)
        noise = noise_estimate(x)
        times, holds = [], []
        for s in steps:
            y = x[s.hold_start : s.hold_end]
            move = y[-1] - y[0]
            if y.size < 5 or not abs(move) > max(50.0 * noise, 0.05):
                continue
            reached = np.flatnonzero(np.abs(y - y[0]) >= 0.63 * abs(move))
            times.append(exp.time[s.hold_start + reached[0]] - s.t)
            holds.append(exp.time[s.hold_end - 1] - s.t)
        pooled += times
        if len(times) >= 2:
            per_sensor.append((float(np.median(times)), float(np.median(holds))))
    settle = float(np.median(pooled)) if len(pooled) >= 2 else math.nan
    if not per_sensor:
        return settle, math.nan, False
    slow, hold = max(per_sensor)
    return settle, slow, len(per_sensor) == len(face) and slow < SETTLE_HOLD_FRACTION * hold


def _time_unit(exp, slow, sure, scale):
    if not math.isfinite(slow):
        return []
    # one sensor responding (the other stuck or flat) may be the fast one, and short holds cut the response
    low = scale * (SETTLE_MIN_S if sure else SETTLE_MIN_UNSURE_S)
    if slow > scale * SETTLE_MAX_S:
        return [
            _finding(
                ERROR,
                exp,
                f"the sensors take {slow / 3600:.3g} h (in the file's time unit) to settle "
                f"after a current step, but {_settles(scale)}: time_s looks like milliseconds",
                "Convert the time column to seconds (divide by 1000)",
                column="time_s",
            )
        ]
    if slow < low:
        return [
            _finding(
                ERROR,
                exp,
                f"the sensors settle {slow:.3g} time units after a current step, but "
                f"{_settles(scale)}: time_s looks like minutes or hours",
                "Convert the time column to seconds (minutes: multiply by 60; hours: by 3600)",
                column="time_s",
            )
        ]
    return []


def _settles(scale):
    if scale >= 1.0:
        return "a rig's blocks settle in minutes"
    return f"this rig settles in about {scale * SETTLE_REFERENCE_TAU_S:.2g} s (its slowest time constant)"


# -- sensors ------------------------------------------------------------------


def _runs(x):
    """``(start, stop)`` index pairs of stretches of exactly equal consecutive values (stop exclusive)."""
    same = np.diff(x) == 0
    if not same.any():
        return np.empty((0, 2), dtype=np.int64)
    edges = np.diff(np.concatenate([[0], same.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return np.column_stack([starts, stops + 1])


def _stuck(exp):
    out = []
    t = exp.time
    for j, c in enumerate(exp.sensor_names):
        x = exp.sensors[j]
        runs = _runs(x)
        if not runs.size:
            continue
        length = t[runs[:, 1] - 1] - t[runs[:, 0]]
        long = np.flatnonzero((length >= STUCK_MIN_S) & (runs[:, 1] - runs[:, 0] >= STUCK_MIN_SAMPLES))
        if not long.size:
            continue
        steps = np.abs(np.diff(x))
        q = float(np.median(steps[steps > 0])) if (steps > 0).any() else 0.0
        coarse = q > noise_estimate(x)
        for k in long[np.argsort(-length[long])]:
            if coarse and length[k] < STUCK_QUANTISED_RATIO * np.max(np.delete(length, k), initial=0.0):
                continue
            a, b = runs[k]
            others = [(exp.channel(o)[a:b].max() - exp.channel(o)[a:b].min(), o) for o in exp.sensor_names if o != c]
            moved, other = max(others)
            if moved > STUCK_OTHERS_K:
                out.append(
                    _finding(
                        ERROR,
                        exp,
                        f"{c} reads exactly {x[a] - KELVIN:.6g} degC from {exp.where(a)} to "
                        f"{exp.where(b - 1)} ({length[k] / 60:.3g} min) while {other} moves by {moved:.3g} K: the "
                        "sensor or its logger channel is stuck",
                        f"Repair the channel and record again, or cut the run before line {exp.line(a)}"
                        if exp.lines is not None
                        else "Repair the channel and record again",
                        a,
                        c,
                    )
                )
                break
    return out


def _jumps(exp):
    dt = np.diff(exp.time)
    limit = JUMP_K + JUMP_RATE_K_PER_S * dt
    for j, c in enumerate(exp.sensor_names):
        d = np.abs(np.diff(exp.sensors[j]))
        bad = np.flatnonzero(d > limit)
        if bad.size:
            k = int(bad[0])
            return [
                _finding(
                    ERROR,
                    exp,
                    f"{c} jumps from {exp.sensors[j][k] - KELVIN:.4g} to "
                    f"{exp.sensors[j][k + 1] - KELVIN:.4g} degC in {dt[k]:.3g} s at {exp.where(k + 1)}, "
                    "faster than any block of the rig can change",
                    "Check the sensor and its wiring; delete the glitched rows or cut the run there",
                    k + 1,
                    c,
                )
            ]
    return []


def _below_pumping(exp, datasheet):
    coldest = float(exp.boundaries.min())
    floor = coldest - datasheet.dtmax - COLD_MARGIN_K
    for j, c in enumerate(exp.sensor_names):
        k = int(np.argmin(exp.sensors[j]))
        if exp.sensors[j][k] < floor:
            return [
                _finding(
                    ERROR,
                    exp,
                    f"{c} reads {exp.sensors[j][k] - KELVIN:.4g} degC at {exp.where(k)}, "
                    f"{coldest - exp.sensors[j][k]:.3g} K below the coldest boundary; the module pumps at "
                    f"most dTmax = {datasheet.dtmax:g} K",
                    "Check the sensor (a broken or shorted thermistor reads at its limit) and its column",
                    k,
                    c,
                )
            ]
    return []


# -- polarity -----------------------------------------------------------------


def _slope(x, y):
    """Least-squares slope of ``y`` on ``x`` and its standard error."""
    xc = x - x.mean()
    sxx = float(xc @ xc)
    if sxx <= 0:
        return 0.0, math.inf
    b = float(xc @ (y - y.mean())) / sxx
    resid = y - y.mean() - b * xc
    return b, math.sqrt(float(resid @ resid) / max(len(x) - 2, 1) / sxx)


def _polarity(exp, steps, settle, layout):
    i = exp.current
    span = float(i.max() - i.min())
    if span < 0.1:
        return []
    hot, cold = layout.face
    dT = exp.channel(cold) - exp.channel(hot)
    thermal, _ = _slope(i, dT)
    volt, _ = _slope(i, exp.voltage)
    cools = None if abs(thermal) * span < 1.0 else thermal < 0
    follows = volt > 0
    if cools is None or (cools and follows):
        return (
            []
            if follows
            else [
                _finding(
                    ERROR,
                    exp,
                    f"the voltage falls as the current rises ({volt:+.3g} V per A)",
                    "The voltage has the "
                    "current's sign (V = R I + S dT): negate voltage_V (or current_A, if positive current warms the "
                    "cold side)",
                    column="voltage_V",
                )
            ]
        )
    side = f"positive current warms the cold side: {cold} - {hot} rises by {thermal:.3g} K per A" if not cools else ""
    if not cools and follows:
        return [
            _finding(
                ERROR,
                exp,
                side + "; the voltage follows the current, so both are reversed",
                "Negate current_A and voltage_V (positive current must cool the module's cold side, "
                f"where {layout.face[1]} is); if the module is mounted the right way, check that "
                f"{', '.join(layout.hot_side)} are the hot side's sensors",
                column="current_A",
            )
        ]
    if not cools:
        return [
            _finding(
                ERROR,
                exp,
                side + f"; the voltage falls as the current rises ({volt:+.3g} V per A)",
                f"Negate current_A (positive current must cool the module's cold side, where {layout.face[1]} is)",
                column="current_A",
            )
        ]
    return [
        _finding(
            ERROR,
            exp,
            f"the voltage falls as the current rises ({volt:+.3g} V per A) while positive "
            "current cools the cold side as it should",
            "Negate voltage_V",
            column="voltage_V",
        )
    ]


# -- temperature units --------------------------------------------------------


def _settled_holds(exp, steps, settle, layout, *, zero):
    """``(a, b)`` sample ranges of holds at least ZERO_HOLD_SETTLINGS settling times long.

    Also at least the rig's slowest time constant long: in holds shorter than the rig's slowest
    mode the face sensors' 63 % time measures the hold, not the rig.  One time constant leaves
    up to 37 % of a move unrelaxed; the checks that read these holds leave room for it (the
    zero-current check's margin is ZERO_MARGIN_K plus what the hold leaves of a relaxation at the
    slowest time constant, :func:`_unrelaxed_per_move`, times the sensor's move over the hold; the
    sensor-order check reads correlations, not levels).  Only the holds at zero current
    (``zero=True``) or only the others.
    """
    bounds = [(0, steps[0].index if steps else exp.n)] + [(s.hold_start, s.hold_end) for s in steps]
    sigma = max(current_noise(exp.current), 1e-3)
    need = max(ZERO_HOLD_SETTLINGS * settle, layout.slowest_tau_s) if math.isfinite(settle) else math.inf
    out = []
    for a, b in bounds:
        if b - a < 10 or (abs(float(np.median(exp.current[a:b]))) > 5 * sigma) == zero:
            continue
        if exp.time[b - 1] - exp.time[a] >= need:
            out.append((a, b))
    return out


def _tail(a, b):
    """The settled last fifth of the sample range ``a:b``."""
    return slice(a + int(0.8 * (b - a)), b)


def _sensor_order(exp, steps, settle, layout):
    """Sensors out of their place on a heat path (swapped columns), from the settled holds.

    Along a path boundary -> far sensor -> face sensor one heat flow crosses
    both steps, so across holds the two differences are proportional with a
    positive factor; a swap makes one of them change sign.  Slopes across
    holds, not levels, so constant sensor offsets do not matter.
    """
    holds = _settled_holds(exp, steps, settle, layout, zero=False)
    if len(holds) < SERIES_MIN_HOLDS:
        return []
    for path in layout.paths:
        columns = [exp.channel(c) for c in path]
        levels = np.array([[np.median(x[_tail(a, b)]) for x in columns] for a, b in holds])
        moves = np.diff(levels, axis=1).T
        for j in range(len(path) - 2):
            found = _out_of_order(exp, holds, path[j : j + 3], levels[:, j : j + 3], moves[j], moves[j + 1], layout)
            if found:
                return found
    return []


def _out_of_order(exp, holds, path, levels, first, second, layout):
    if np.ptp(first) < SERIES_MIN_SPAN_K or np.ptp(second) == 0.0:
        return []
    r = float(np.corrcoef(first, second)[0, 1])
    if r >= SERIES_MAX_CORR:
        return []
    k = int(np.argmax(np.abs(first)))  # the hold shown: the largest step
    b = holds[k][1]
    shown = ", ".join(f"{c} {v - KELVIN:.4g}" for c, v in zip(path, levels[k]))
    where = "; ".join(layout.describe(c) for c in path[1:])
    return [
        _finding(
            ERROR,
            exp,
            f"{path[0]} -> {path[1]} -> {path[2]} is not the order of the heat path: over "
            f"{len(holds)} settled holds {path[1]} - {path[0]} and {path[2]} - {path[1]} move in "
            f"opposite directions (correlation {r:+.2f}; at {exp.where(b - 1)}: {shown} degC)",
            f"Check which column is which sensor ({where}); a swap across the module shows on this path too "
            "(the rig file's [sensors])",
            b - 1,
            path[2],
        )
    ]


def _unrelaxed_per_move(hold_s, tau_s):
    """Kelvin still to go per kelvin moved at the end of a hold, for a relaxation with time constant ``tau_s``."""
    r = math.exp(-hold_s / tau_s)
    return max(ZERO_MARGIN_FRACTION, ZERO_MARGIN_SAFETY * r / (1.0 - r))


def _unsettled(exp, steps, settle, layout):
    """A warning when no hold is long enough for the checks that read settled holds."""
    if not steps or not math.isfinite(settle):
        return []
    if _settled_holds(exp, steps, settle, layout, zero=True) or _settled_holds(exp, steps, settle, layout, zero=False):
        return []
    return [
        _finding(
            WARNING,
            exp,
            f"no hold lasts the rig's slowest time constant ({layout.slowest_tau_s:.0f} s) and "
            f"{ZERO_HOLD_SETTLINGS:g} settling times: the zero-current and sensor-order checks cannot read this run, "
            "so an offset sensor or swapped columns would go unnoticed here",
            "Check the columns against the rig file by eye, or add one long hold at 0 A",
        )
    ]


#: A hold's own relaxation counts when its late moves exceed this [K] (far above sensor noise) ...
HOLD_TAU_MIN_MOVE_K = 0.1
#: ... and its time constant up to this many times the rig's slowest.
HOLD_TAU_MAX_FACTOR = 3.0


def _hold_tau(x, hold_s, rig_tau_s):
    """The time constant [s] of a hold's late relaxation, from three equally spaced windows of its second half.

    Of an exponential approach, successive differences shrink by ``exp(-spacing / tau)``.  0
    when the hold does not visibly relax that way (settled, flat, noisy or turning), so a
    settled hold keeps the rig's margin; at most :data:`HOLD_TAU_MAX_FACTOR` times ``rig_tau_s``.
    """
    n = len(x)
    if n < 40:
        return 0.0
    m = [float(np.median(x[int((f - 0.05) * n) : int((f + 0.05) * n)])) for f in (0.5, 0.725, 0.95)]
    d1, d2 = m[1] - m[0], m[2] - m[1]
    if abs(d1) < HOLD_TAU_MIN_MOVE_K or not 0.0 < d2 / d1 < 1.0:
        return 0.0
    return min(-0.225 * hold_s / math.log(d2 / d1), HOLD_TAU_MAX_FACTOR * rig_tau_s)


def _zero_current_range(exp, steps, settle, layout):
    for a, b in _settled_holds(exp, steps, settle, layout, zero=True):
        tail = _tail(a, b)
        bounds = np.median(exp.boundaries[:, tail], axis=1)
        lo, hi = float(bounds.min()), float(bounds.max())
        hold = float(exp.time[b - 1] - exp.time[a])
        for j, c in enumerate(exp.sensor_names):
            x = exp.sensors[j]
            level = float(np.median(x[tail]))
            # a module type slower than the rig's nominal one relaxes slower: the hold's own rate counts
            tau = max(layout.slowest_tau_s, _hold_tau(x[a:b], hold, layout.slowest_tau_s))
            margin = ZERO_MARGIN_K + _unrelaxed_per_move(hold, tau) * abs(level - float(x[a]))
            if not lo - margin <= level <= hi + margin:
                return [
                    _finding(
                        ERROR,
                        exp,
                        f"at zero current {c} settles at {level - KELVIN:.4g} degC ({exp.where(b - 1)}), "
                        f"outside the boundaries' {lo - KELVIN:.4g}..{hi - KELVIN:.4g} degC: with no heat source no "
                        "part of the rig can stay there",
                        f"Check {c}'s unit (all temperatures in degC: degF? an "
                        "offset?) and that the columns are not swapped",
                        b - 1,
                        c,
                    )
                ]
    return []


def degf_evidence(
    current: np.ndarray,
    voltage: np.ndarray,
    temps: Mapping[str, np.ndarray],
    datasheet: Datasheet,
    face: tuple[str, str],
) -> str | None:
    """Why a file's temperatures read degF, or None.

    At zero current the terminal voltage is the Seebeck voltage of the
    junctions, about the datasheet's S times the difference of the face
    sensors (somewhat less: the junctions relax first).  In degF a kelvin
    reads as 1.8 degrees, so the voltage per degree falls to ~1/1.8 of that,
    a tight linear relation still (unlike a broken sensor), and the cooling
    water reads above 32, its freezing point in degF.

    Parameters
    ----------
    current, voltage : ndarray, shape (n,)
        [A], [V].
    temps : mapping of str to ndarray
        Temperature columns as read (degC, or degF if wrong).
    datasheet : tembayes.data.Datasheet
    face : tuple of (str, str)
        The columns of the sensors next to the hot and the cold module face.

    Returns
    -------
    str or None
    """
    sigma = max(current_noise(current), 1e-3)
    dT = temps[face[0]] - temps[face[1]]  # hot face minus cold face
    use = (np.abs(current) < 5 * sigma) & (np.abs(dT) > SEEBECK_MIN_DT_K)
    if use.sum() < SEEBECK_MIN_SAMPLES or min(float(np.median(v)) for v in temps.values()) < 32.0:
        return None
    x, y = dT[use], voltage[use]
    s, _ = _slope(x, y)
    r2 = np.corrcoef(x, y)[0, 1] ** 2
    ratio = s / datasheet.seebeck()
    if r2 >= SEEBECK_MIN_R2 and SEEBECK_RATIO_DEGF_LOW <= ratio < SEEBECK_RATIO_DEGF:
        return (
            f"at zero current the voltage is {1e3 * s:.3g} mV per degree of {face[0]} - "
            f"{face[1]}, {ratio:.2f} of the datasheet's Seebeck coefficient ({1e3 * datasheet.seebeck():.3g} "
            "mV/K), as when a kelvin reads 1.8 degrees, and no column reads below 32"
        )
    return None


# -- what an identification run can identify ----------------------------------


def _identifiability(exp, steps, settle, face):
    hint = "The reference staircase: 0 -> +0.8 -> -1.6 -> 0 A in 0.2 A steps, each held about 600 s"
    if not steps:
        return [
            _finding(
                WARNING,
                exp,
                "the current has no steps: R and S cannot be identified from this run (calibrate refuses it)",
                hint,
                column="current_A",
                refused_by=("calibrate",),
            )
        ]
    out = []
    if len(steps) < CALIBRATE_MIN_STEPS:
        out.append(
            _finding(
                WARNING,
                exp,
                f"the run has {len(steps)} current step(s): calibrate refuses it (it needs at least "
                f"{CALIBRATE_MIN_STEPS}; identify works from 3)",
                hint,
                column="current_A",
                refused_by=("calibrate",),
            )
        )
    rest = float(exp.time[steps[0].index] - exp.time[0])
    if rest < CALIBRATE_LEAD_S:
        out.append(
            _finding(
                WARNING,
                exp,
                f"the first current step comes {rest:.1f} s after the start: calibrate refuses the run "
                f"(it needs at least {CALIBRATE_LEAD_S:.0f} s at rest before the first step)",
                "Record the rig at rest before the first step",
                steps[0].index,
                "current_A",
                refused_by=("calibrate",),
            )
        )
    directions = {s.direction for s in steps}
    if directions != {"up", "down"}:
        missing = ({"up", "down"} - directions).pop()
        out.append(
            _finding(
                WARNING,
                exp,
                f"the current never steps {missing}: the hysteresis check (every mean "
                "temperature visited by an up- and a down-step) is impossible",
                hint,
                column="current_A",
            )
        )
    holds = np.array([exp.time[s.hold_end - 1] - exp.time[s.hold_start] for s in steps])
    if math.isfinite(settle) and np.median(holds) < HOLD_SETTLINGS * settle:
        out.append(
            _finding(
                WARNING,
                exp,
                f"the holds ({np.median(holds):.0f} s) are short against the sensors' "
                f"settling (63 % in {settle:.0f} s): the steady states the step method reads are not "
                "reached (calibrate reads the transients and is not affected)",
                hint,
                column="current_A",
            )
        )
    tavg = 0.5 * (exp.channel(face[0]) + exp.channel(face[1]))
    span = float(np.percentile(tavg, 99) - np.percentile(tavg, 1))
    if span < TAVG_SPAN_MIN_K:
        out.append(
            _finding(
                WARNING,
                exp,
                f"the mean temperature at the module faces spans only {span:.3g} K: the slopes R1 and S1 of the "
                f"laws cannot be told from the model's shortcomings, so calibrate refuses the run (it needs "
                f"{TAVG_SPAN_MIN_K:g} K)",
                "Use larger currents in both directions (" + hint + "), or on a rig whose boundaries hold the "
                "module's temperature (liquid-cooled plates) step the boundaries' temperature between staircases",
                column="current_A",
                refused_by=("calibrate",),
            )
        )
    return out
