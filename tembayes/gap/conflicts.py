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

:data:`SUSPECTS` maps a conflict to the effects it can stand for
(:func:`suspects`); a suspect's refit starts from the conflict moved into
the effect (:func:`suspect_start`).
"""

from __future__ import annotations

import numpy as np

from tembayes.calibrate.priors import rig_prior

#: A rig parameter calibrated beyond its documented range (``high`` or
#: ``low``) and the effects it can stand for: an extra leak absorbs more heat
#: exchange with ambient; a plate capacitance the size of a block absorbs a
#: sensor lag or a contact resistance (both delay the blocks' response); a
#: paste conductance below any paste absorbs a contact resistance.
SUSPECTS = {
    ("leak_top", "high"): ("ambient_leak",),
    ("leak_bottom", "high"): ("ambient_leak",),
    ("c_plate_hot", "high"): ("sensor_lag", "contact_resistance"),
    ("c_plate_cold", "high"): ("sensor_lag", "contact_resistance"),
    ("g_paste_hot", "low"): ("contact_resistance",),
    ("g_paste_cold", "low"): ("contact_resistance",),
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


def suspects(conflicts, *, allowed):
    """The effects some range conflicts point at (:data:`SUSPECTS`).

    Parameters
    ----------
    conflicts : dict
        Module id -> :func:`range_conflicts` rows.
    allowed : list of str
        The effects that may be named.

    Returns
    -------
    list of str
        In the order the conflicts name them.
    """
    out = []
    for rows in conflicts.values():
        for r in rows:
            if not r["conflict"]:
                continue
            side = "high" if r["median"] > r["high"] else "low"
            for e in SUSPECTS.get((r["parameter"], side), ()):
                if e in allowed and e not in out:
                    out.append(e)
    return out


def suspect_start(effect, rows):
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

    Returns
    -------
    dict
        ``name -> value`` to override the start with (empty for the other effects).
    """
    out = {}
    for r in rows:
        if not r["conflict"]:
            continue
        p, med = r["parameter"], r["median"]
        if effect == "ambient_leak" and p in ("leak_top", "leak_bottom") and med > r["high"]:
            out[p] = r["high"]
            out["extra_leak_W_per_K"] = out.get("extra_leak_W_per_K", 0.0) + med - r["high"]
        elif effect == "contact_resistance" and p in ("g_paste_hot", "g_paste_cold") and med < r["low"]:
            out[p] = r["low"]
            out[f"contact_R_{p.rsplit('_', 1)[1]}_K_per_W"] = 1.0 / med - 1.0 / r["low"]
    return out
