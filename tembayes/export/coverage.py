"""The calibrated range: the operating conditions the identification runs covered.

An exported linear model is only as good as the laws behind it, and the laws
were calibrated where the identification runs went: ``R(T̄)`` and ``S(T̄)``
over the junction temperatures of the step windows, at the currents of the
staircase.  An operating point ``(T̄, I)`` outside that box extrapolates the
laws, so :func:`check_points` refuses it unless extrapolation is allowed.

- ``tavg_C``: the model's mean junction temperature at every step window
  (``posterior.nc``, ``constant_data/step_Tavg_C``), the range every exported
  module covered (the intersection over the modules);
- ``current_A``: the hold currents of the identification runs (the
  intersection over the modules);
- ``boundaries_C``: the temperature of every boundary column of the rig the
  runs saw (the union over the modules).  A point asks for boundary
  temperatures (the controlled ones solved so that the steady state has its
  T̄, :func:`~tembayes.export.linearise.linearise`): far outside the range
  seen, the rig is extrapolated in a way the laws' box does not show, so
  that is a warning, not a refusal (:func:`boundary_warnings`).

The steady states at the end of the holds, ``(T̄, I)`` pairs the rig really
sat at, give the default operating points (:func:`default_points`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tembayes.constants import KELVIN
from tembayes.data.steps import detect_steps
from tembayes.errors import DataError

#: Two hold currents closer than this are one level of the staircase [A].
LEVEL_TOL_A = 0.05
#: A solved water (or the given ambient) temperature further than this
#: outside the range the identification runs saw is warned about [K].
BOUNDARY_MARGIN_K = 3.0
#: The default points' resolution: T̄ [K], current [A].
POINT_ROUND = (0.1, 0.01)
#: A point this close to the range counts as inside: T̄ [K], current [A].  The
#: range's ends are measured (hold medians, model T̄) to about this, and the
#: messages show them to this precision.
RANGE_TOL = (0.01, 0.001)


@dataclass(frozen=True)
class OperatingRange:
    """What the identification runs of the exported modules covered.

    Attributes
    ----------
    tavg_C : (float, float)
        Mean junction temperature [degC]: lowest and highest step window
        that every module reached.
    current_A : (float, float)
        Hold current [A] that every module's staircase spanned.
    boundaries_C : dict of str to (float, float)
        Boundary column -> the temperatures any of the runs saw [degC].
    states : ndarray, shape (k, 2)
        ``(T̄ [degC], I [A])`` at the end of every hold before a step, all
        modules pooled: where the rig really sat.
    modules : tuple of str
    source : Path
        The calibration run folder.
    """

    tavg_C: tuple
    current_A: tuple
    boundaries_C: dict
    states: np.ndarray
    modules: tuple
    source: Path

    def bounds(self):
        """``((T̄ low, T̄ high), (I low, I high))`` of the laws' box, widened by :data:`RANGE_TOL`."""
        return tuple((lo - tol, hi + tol) for (lo, hi), tol in zip((self.tavg_C, self.current_A), RANGE_TOL))

    def contains(self, tavg_C, current_A):
        """Whether the point ``(T̄ [degC], I [A])`` lies inside the laws' box."""
        (tl, th), (il, ih) = self.bounds()
        return tl <= tavg_C <= th and il <= current_A <= ih

    def describe(self):
        """``"T_avg 12.7..49.5 C, I -1.6..0.8 A"`` for messages."""
        return (
            f"T_avg {self.tavg_C[0]:.2f}..{self.tavg_C[1]:.2f} C, I {self.current_A[0]:.3f}..{self.current_A[1]:.3f} A"
        )

    def to_dict(self):
        """The range as plain data (``meta.calibrated_range`` of the export file)."""
        return {
            "tavg_C": list(self.tavg_C),
            "current_A": list(self.current_A),
            "boundaries_C": {c: list(v) for c, v in self.boundaries_C.items()},
            "modules": list(self.modules),
        }


def calibrated_range(run, batch, *, modules):
    """The :class:`OperatingRange` of a run's identification data for some of its modules.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
        Gives the junction temperature of every step window.
    batch : tembayes.data.Batch
        Gives the identification runs' currents and boundary temperatures.
    modules : sequence of str
        The exported module ids.

    Returns
    -------
    OperatingRange

    Raises
    ------
    DataError
        The modules' runs share no range (calibrated on different programmes).
    """
    per = [_module_coverage(run, batch.modules[m].identification, m) for m in modules]
    tavg = (max(p["tavg"][0] for p in per), min(p["tavg"][1] for p in per))
    cur = (max(p["current"][0] for p in per), min(p["current"][1] for p in per))
    if tavg[0] > tavg[1] or cur[0] > cur[1]:
        raise DataError(
            run.path,
            f"the identification runs of {list(modules)} share no operating range",
            "Export the modules one at a time (--module ID).",
        )
    bounds = {
        c: (min(p["boundaries"][c][0] for p in per), max(p["boundaries"][c][1] for p in per))
        for c in per[0]["boundaries"]
    }
    return OperatingRange(
        tavg_C=tavg,
        current_A=cur,
        boundaries_C=bounds,
        states=np.vstack([p["states"] for p in per]),
        modules=tuple(modules),
        source=Path(run.path),
    )


def _module_coverage(run, exp, module_id):
    """One module's ranges and its hold-end states ``(T̄ [degC], I [A])``."""
    windows = run.steps(module_id)
    tavg = np.asarray(windows["Tavg_C"], float)
    steps = detect_steps(exp.time, exp.current)
    if not steps:
        raise DataError(exp.path, "has no current step", "An identification run is a current staircase.")
    step_t = np.array([s.t for s in steps])
    # each window's step is the detected step nearest to it; the hold before it ends at the window's T̄
    before = np.array([steps[int(np.argmin(np.abs(step_t - t)))].i_before for t in windows["t_s"]])
    levels = np.array([s.i_before for s in steps] + [steps[-1].i_after])
    ok = np.isfinite(tavg)
    return {
        "tavg": (float(tavg[ok].min()), float(tavg[ok].max())),
        "current": (float(levels.min()), float(levels.max())),
        "boundaries": {c: _span_C(exp.channel(c)) for c in exp.boundary_names},
        "states": np.column_stack([tavg[ok], before[ok]]),
    }


def _span_C(x_K):
    x = np.asarray(x_K, float) - KELVIN
    return float(np.min(x)), float(np.max(x))


def default_points(covered):
    """Operating points inside the range: the hold-end states at the lowest, the nearest-zero and the highest current.

    Each point is the median over the pooled states at that staircase level
    (within :data:`LEVEL_TOL_A`), rounded to :data:`POINT_ROUND` and kept
    inside the laws' box (the modules' median may lie a little past the
    range every module covered).

    Returns
    -------
    tuple of (float, float)
        ``(T̄ [degC], I [A])``, lowest current first, without repeats.
    """
    T, current = covered.states[:, 0], covered.states[:, 1]
    targets = (current.min(), current[np.argmin(np.abs(current))], current.max())
    points = []
    for level in sorted(set(float(x) for x in targets)):
        near = np.abs(current - level) <= LEVEL_TOL_A
        tavg = _round_inside(np.median(T[near]), covered.bounds()[0], POINT_ROUND[0])
        i = _round_inside(np.median(current[near]), covered.bounds()[1], POINT_ROUND[1])
        if all(abs(i - p[1]) > LEVEL_TOL_A for p in points):
            points.append((tavg, i))
    return tuple(points)


def _round_inside(x, bounds, step):
    """``x`` rounded to a multiple of ``step``, the nearest such multiple inside ``bounds`` (``x`` clipped if none)."""
    lo, hi = bounds
    r = float(np.clip(np.round(x / step) * step, np.ceil(lo / step) * step, np.floor(hi / step) * step))
    return round(r, 6) + 0.0 if lo <= r <= hi else float(np.clip(x, lo, hi))  # + 0.0: no -0.0


def check_points(points, *, covered, allow_extrapolation):
    """Refuse, or warn about, operating points outside the laws' box.

    Parameters
    ----------
    points : sequence of (float, float)
        ``(T̄ [degC], I [A])``.
    covered : OperatingRange
    allow_extrapolation : bool
        Turn the refusal into warnings.

    Returns
    -------
    list of str
        One warning per point outside (empty when every point is inside).

    Raises
    ------
    DataError
        A point is outside and extrapolation is not allowed (the message
        names the point and the range).
    """
    outside = [(t, i) for t, i in points if not covered.contains(t, i)]
    if outside and not allow_extrapolation:
        named = "; ".join(f"T_avg {t:g} C, I {i:g} A (--point {t:g},{i:g})" for t, i in outside)
        raise DataError(
            covered.source,
            f"operating point(s) {named} outside the calibrated range: the "
            f"identification runs of {', '.join(covered.modules)} covered {covered.describe()}",
            "Choose --point values inside it, or add --allow-extrapolation to export there anyway "
            "(the file then records a warning).",
        )
    return [
        f"operating point T_avg {t:g} C, I {i:g} A lies outside the calibrated range ({covered.describe()}): "
        "the laws are extrapolated there"
        for t, i in outside
    ]


def boundary_warnings(linear, *, covered, room_C, room, controlled):
    """Warnings for operating points whose boundary temperatures are far from what the runs saw.

    Parameters
    ----------
    linear : sequence of sequence of LinearModel
        Per exported entry (module, population), its points as linearised
        (``u0[1:]`` holds the boundary temperatures [K], named by ``inputs[1:]``).
    covered : OperatingRange
    room_C : float
        The temperature given for the room the rig leaks to [degC].
    room : str
        The room's boundary column.
    controlled : sequence of str
        The boundary columns the points solve
        (:attr:`~tembayes.physics.layout.Layout.controlled`).

    Returns
    -------
    list of str
        One for the room, and one per point whose solved boundaries, in any
        entry, lie more than :data:`BOUNDARY_MARGIN_K` outside the range seen.
    """
    out = []
    columns = linear[0][0].inputs[1:]
    solved = [j for j, c in enumerate(columns) if c in controlled]
    if room not in controlled:
        lo, hi = covered.boundaries_C[room]
        if not lo - BOUNDARY_MARGIN_K <= room_C <= hi + BOUNDARY_MARGIN_K:
            out.append(f"{room} {room_C:g} C is outside the {_span(lo, hi)} C the identification runs saw")
    for k, point in enumerate(linear[0]):
        for j in solved:
            c = columns[j]
            lo, hi = covered.boundaries_C[c]
            ub = np.array([float(entry[k].u0[1 + j]) for entry in linear]) - KELVIN
            if np.any((ub < lo - BOUNDARY_MARGIN_K) | (ub > hi + BOUNDARY_MARGIN_K)):
                out.append(
                    f"operating point T_avg {point.tavg_C:g} C, I {point.current_A:g} A needs {c} at "
                    f"{_span(ub.min(), ub.max())} C; the identification runs saw {_span(lo, hi)} C"
                )
                break
    return out


def _span(lo, hi):
    """``"20.2..20.3"``, or ``"25.2"`` when both ends read the same to 0.1."""
    a, b = f"{lo:.1f}", f"{hi:.1f}"
    return a if a == b else f"{a}..{b}"
