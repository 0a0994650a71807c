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
"""

from __future__ import annotations

import numpy as np

from tembayes.calibrate.priors import rig_prior


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
        first (``outside_sd``: log-distance of the median beyond the range in
        prior log-sds; 0 inside).
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
        sd = rig_prior(p).scale
        if med > p.high:
            dist = np.log(med / p.high) / sd
        elif med < p.low:
            dist = np.log(p.low / med) / sd
        else:
            dist = 0.0
        out.append({"parameter": p.name, "unit": p.unit, "low": p.low, "high": p.high, "median": med,
                    "q_low": qlo, "q_high": qhi, "outside_sd": float(dist),
                    "conflict": bool(qlo > p.high or qhi < p.low)})
    return sorted(out, key=lambda r: -r["outside_sd"])
