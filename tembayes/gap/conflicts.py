"""Effects hiding in the base model's own parameters: prior-posterior conflicts.

An unmodelled effect can be absorbed by a parameter that has the right
sensitivity pattern: extra heat exchange with ambient shows up as a leak
conductance far above what the enclosure allows, a sensor lag as a plate
capacitance the size of a block.  Every rig parameter has a documented
plausible range (:class:`~tembayes.physics.rig.RigParameter`); a posterior
that sits outside it is evidence of a gap even where the residuals are
clean.

For each parameter the score is how far the posterior median lies outside
the range, in units of the prior's log-sd (the range spans +-2 of them), and
a conflict is declared when the posterior's central 90 % interval lies
entirely outside the range.

A conflict is a gap only if it matters (:class:`RangeCheck`): the base
model is refitted with the conflicting values held at the range's edge, and
the conflict is *material* when that refit leaves a significant and material
held-out step window the base refit does not -- the yardstick the rest of
the diagnosis uses -- or moves a law by more than :data:`LAW_SHIFT_MAX` of
its posterior sds.  Parameters the data tell only through transients trade
along ridges (on a two-sensor rig a thermistor's depth, the plates'
capacities and the pastes): there the posterior can sit outside a range
while the documented rig fits the held-out windows as well and gives the
same laws.  The windows alone are not enough: a contact resistance the
base model puts into a paste below its range (in-model, the reference rig)
is refitted at the paste's edge with no window cell (the rest of the rig
takes it up) but moves a law by 4.4 sds.

:func:`suspect_table` maps a conflict to the effects it can stand for, by
the parameter's role in the rig's network (:func:`suspects`); a suspect's
refit starts from the conflict moved into the effect (:func:`suspect_start`).
"""

from __future__ import annotations

import numpy as np

from tembayes.calibrate.priors import rig_prior
from tembayes.physics.rigfile import expression_names

#: What a rig parameter beyond its documented range can stand for, by its role:
#: an extra leak absorbs more heat exchange with the room; a module plate's
#: capacitance the size of a block absorbs a sensor lag or a contact resistance
#: (both delay the blocks' response); a face contact's conductance below its
#: range absorbs a contact resistance.
ROLE_SUSPECTS = {
    ("leak", "high"): ("ambient_leak",),
    ("plate", "high"): ("sensor_lag", "contact_resistance"),
    ("contact", "low"): ("contact_resistance",),
}


def parameter_roles(rig):
    """``{parameter: (role, side)}`` of the rig parameters that can absorb an effect.

    ``leak``: a conductance of a leak to the room
    (:attr:`~tembayes.physics.layout.Layout.leaks`; a heat sink's fins are the
    rig's main path, not a leak); ``plate``: a capacitance of the module's
    plates; ``contact``: a conductance between a module face and the rig that
    no other link uses (steel in series with the paste is not one).  ``side``
    is ``"hot"`` or ``"cold"``, or None for a leak and for a parameter both
    sides share.  Shares and the module's own ``c_legs`` have no role.
    """
    layout = rig.layout
    skip = {p.name for p in rig.parameters if p.is_share} | {"c_legs"}
    faces = dict(zip(rig.module_faces, ("hot", "cold")))
    own = {*rig.tem_chain, *rig.module_faces}

    def face_of(a, b):
        for x, y in ((a, b), (b, a)):
            if x in faces and y not in own and y not in rig.boundaries:
                return faces[x]
        return None

    elsewhere = {n for a, b, expr in rig.links if face_of(a, b) is None for n in expression_names(expr)}
    found = {}  # name -> (role, {sides})
    for a, b, expr in rig.links:
        side = face_of(a, b)
        for name in set(expression_names(expr)) - skip:
            if layout.leak_boundary in (a, b) and (a in layout.leaks or b in layout.leaks):
                found.setdefault(name, ("leak", set()))
            elif side is not None and name not in elsewhere:
                found.setdefault(name, ("contact", set()))[1].add(side)
    for node, expr in rig.nodes:
        if node in (rig.hot, rig.cold):
            for name in set(expression_names(expr)) - skip:
                found.setdefault(name, ("plate", set()))[1].add("hot" if node == rig.hot else "cold")
    return {name: (role, sides.pop() if len(sides) == 1 else None) for name, (role, sides) in found.items()}


#: Largest shift of a law [its posterior sds] that a conflict held at its documented edge may
#: cause and still not matter: the half-width of the laws' 90 % intervals.
LAW_SHIFT_MAX = 1.645


def is_gap(row):
    """A range-conflict row that counts as a gap: outside the range and, where checked, needed by the data."""
    return bool(row["conflict"] and row.get("material", True))


def is_immaterial(row):
    """A range-conflict row outside the range that its range checks found not to matter."""
    return bool(row["conflict"] and row.get("material") is False)


class RangeCheck:
    """Which of a module's range conflicts matter: refits with them held at their range's edges.

    Every conflict is first held at the nearer edge of its range together with
    the others.  If that refit leaves no new window cell (one the base refit
    does not leave) and moves no law by more than :data:`LAW_SHIFT_MAX`
    posterior sds, none is needed.  Otherwise the held set is grown one
    conflict at a time, the least outside first: a conflict that joins without
    either is not needed, one that brings either is.  So of two conflicts
    that stand in for each other (two leaks, either of which can carry a
    missing heat path) the second to join is needed, and a ridge beside them
    (a plate's capacity) is not.  A refit that fails counts as cells.

    Drive it with :meth:`next` (the held values to refit with, or None when
    done) and :meth:`record`; :meth:`judged` gives the rows.

    Parameters
    ----------
    rows : list of dict
        A module's :func:`range_conflicts` rows.
    """

    def __init__(self, rows):
        self.rows = [dict(r) for r in rows]
        conflicts = sorted((r for r in self.rows if r["conflict"]), key=lambda r: r["outside_sd"])
        self._edges = {r["parameter"]: (r["high"] if r["median"] > r["high"] else r["low"]) for r in conflicts}
        self._order = list(self._edges)  # the greedy order, least outside first
        self._kept = {}  # held without mattering, kept held for the next
        self._verdicts = {}  # parameter -> (material, new cells, law shift, converged)
        self._together = None
        self._pending = dict(self._edges) if self._edges else None

    def next(self):
        """The held values (``name -> SI``) of the next refit; None when every conflict is judged."""
        return None if self._pending is None else dict(self._pending)

    def record(self, cells, law_shift=0.0, converged=True):
        """The result of the refit :meth:`next` asked for.

        Parameters
        ----------
        cells : int or None
            Significant and material held-out window cells it leaves that the
            base refit does not (None: it could not be refitted there).
        law_shift : float
            The largest shift of a law's mode from the base refit's, in the
            law's posterior sds.
        converged : bool
            Its mode search stopped on a tolerance.
        """
        if self._pending is None:
            raise RuntimeError("RangeCheck.record: every conflict is judged already")
        new = None if cells is None else int(cells)
        shift = None if new is None else float(law_shift)
        matters = new != 0 or shift > LAW_SHIFT_MAX
        if self._together is None:
            self._together = (new, shift)
            if not matters or len(self._order) == 1:
                for name in self._order:
                    self._verdicts[name] = (matters, new, shift, converged)
                self._pending = None
                return
        else:
            name = next(n for n in self._order if n not in self._verdicts)
            self._verdicts[name] = (matters, new, shift, converged)
            if not matters:
                self._kept[name] = self._edges[name]
        left = [n for n in self._order if n not in self._verdicts]
        self._pending = {**self._kept, left[0]: self._edges[left[0]]} if left else None

    def judged(self):
        """The rows, each conflict's with ``material``, ``held_cells``, ``held_law_shift`` and ``held_converged``.

        ``held_cells_together`` and ``held_law_shift_together`` are those of the refit with every
        conflict held.
        """
        if self._pending is not None:
            raise RuntimeError("RangeCheck.judged: a refit is still asked for")
        out = []
        for r in self.rows:
            if r["conflict"]:
                material, cells, shift, converged = self._verdicts[r["parameter"]]
                r |= {
                    "material": material,
                    "held_cells": cells,
                    "held_law_shift": shift,
                    "held_cells_together": self._together[0],
                    "held_law_shift_together": self._together[1],
                    "held_converged": converged,
                }
            out.append(r)
        return out


def suspect_table(rig):
    """``{(parameter, "high"|"low"): effects}``: what each rig parameter's conflict can stand for."""
    return {
        (name, direction): effects
        for name, (role, _) in parameter_roles(rig).items()
        for (r, direction), effects in ROLE_SUSPECTS.items()
        if r == role
    }


def range_conflicts(draws, rig, *, level=0.90):
    """Rig parameters whose posterior lies outside the documented range.

    Parameters
    ----------
    draws : dict
        ``name -> (M,)`` posterior draws (SI); names that are not rig
        parameters are ignored.
    rig : RigDescription
    level : float
        Central interval that must lie outside the range for a conflict.

    Returns
    -------
    list of dict
        One per rig parameter in ``draws``: ``{"parameter", "low", "high",
        "median", "q_low", "q_high", "outside_sd", "conflict"}``, the worst
        first (``outside_sd``: distance of the median beyond the range in
        prior sds of its log, or of its logit for a share; 0 inside).
    """
    out = []
    a = 0.5 - level / 2.0
    for p in rig.parameters:
        if p.name not in draws:
            continue
        x = np.asarray(draws[p.name], float)
        x = x[np.isfinite(x) & (x > 0)]
        if len(x) == 0:
            continue
        med = float(np.median(x))
        qlo, qhi = (float(v) for v in np.quantile(x, [a, 1.0 - a]))
        prior = rig_prior(p)
        with np.errstate(invalid="ignore", divide="ignore"):
            if med > p.high:
                dist = float(prior.z(med) - prior.z(p.high))
            elif med < p.low:
                dist = float(prior.z(p.low) - prior.z(med))
            else:
                dist = 0.0
        if not np.isfinite(dist):  # a share at or above 1 (a run from before shares were logit-normal)
            dist = abs(float(np.log(med / (p.high if med > p.high else p.low)))) / prior.scale
        out.append(
            {
                "parameter": p.name,
                "unit": p.unit,
                "low": p.low,
                "high": p.high,
                "median": med,
                "q_low": qlo,
                "q_high": qhi,
                "outside_sd": float(dist),
                "conflict": bool(qlo > p.high or qhi < p.low),
            }
        )
    return sorted(out, key=lambda r: -r["outside_sd"])


def suspects(conflicts, rig, *, allowed):
    """The effects some range conflicts point at (:func:`suspect_table`).

    Parameters
    ----------
    conflicts : dict
        Module id -> :func:`range_conflicts` rows.
    rig : RigDescription
    allowed : list of str
        The effects that may be named.

    Returns
    -------
    list of str
        In the order the conflicts name them.
    """
    table = suspect_table(rig)
    out = []
    for rows in conflicts.values():
        for r in rows:
            if not is_gap(r):
                continue
            side = "high" if r["median"] > r["high"] else "low"
            for e in table.get((r["parameter"], side), ()):
                if e in allowed and e not in out:
                    out.append(e)
    return out


def suspect_start(effect, rows, rig):
    """Where a range-conflict suspect's refit starts (SI): its conflict moved into the effect.

    The conflicting parameters go to their documented edge and the excess
    into the effect (an extra leak takes what the enclosure's leaks have
    beyond their range; a contact resistance what the paste lacks).  From the
    base posterior's values instead the refit stays on the conductance side
    of the ridge the two share (measured on an ambient-leak bench module:
    3.1-3.9 nats below the mode this start reaches).

    Parameters
    ----------
    effect : str or None
    rows : list of dict
        The module's :func:`range_conflicts` rows.
    rig : RigDescription

    Returns
    -------
    dict
        ``name -> value`` to override the start with (empty for the other effects).
    """
    roles = parameter_roles(rig)
    out = {}
    for r in rows:
        if not is_gap(r):
            continue
        p, med = r["parameter"], r["median"]
        role, side = roles.get(p, (None, None))
        if effect == "ambient_leak" and role == "leak" and med > r["high"]:
            out[p] = r["high"]
            out["extra_leak_W_per_K"] = out.get("extra_leak_W_per_K", 0.0) + med - r["high"]
        elif effect == "contact_resistance" and role == "contact" and med < r["low"]:
            out[p] = r["low"]
            for s in (side,) if side else ("hot", "cold"):  # a paste both faces share: both contacts
                out[f"contact_R_{s}_K_per_W"] = 1.0 / med - 1.0 / r["low"]
    return out
