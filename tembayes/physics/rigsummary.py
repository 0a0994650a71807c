"""What a rig file means before a test: its network at nominal values, time constants and hold time.

``tembayes rig`` prints and draws this.  The module between the rig's hot and
cold nodes is a conductance ``K`` (a typical 40 mm module's by default); a
current step changes the heat it pumps (``+P`` at the hot face, ``-P`` at the
cold face) and its Joule heat (half at each face).  The hold a staircase
needs is the time after such a step until every sensor is within
:data:`SETTLED` of its final move (relative to the largest sensor's move),
for the slower of the two heat patterns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tembayes.physics.layout import DEFAULT_MODULE_K, conduction_modes
from tembayes.physics.rigfile import RigFile

__all__ = ["RigSummary", "summarise_rig", "SETTLED"]

#: A sensor has settled when its distance from the final value is this share of the largest sensor's move.
SETTLED = (0.01, 0.001)


@dataclass(frozen=True)
class RigSummary:
    """A rig at its nominal values.

    Attributes
    ----------
    rig : RigFile
    module_k : float
        The module conductance assumed [W/K].
    nodes : tuple of (str, float)
        Node and heat capacity [J/K] (the module's plates each carry half the legs').
    links : tuple of (str, str, float)
        Link ends and conductance [W/K] (a series evaluated).
    time_constants : ndarray
        The network's time constants, slowest first [s].
    hold_times : dict of float to float
        Share left (:data:`SETTLED`) -> the hold a step needs for every sensor to settle to it [s].
    """

    rig: RigFile
    module_k: float
    nodes: tuple
    links: tuple
    time_constants: np.ndarray
    hold_times: dict

    def to_json(self) -> dict:
        """``rig.json``: the file's content, the network at nominal values, time constants and hold times."""
        r = self.rig
        return {
            "name": r.name,
            "description": r.description,
            "module": {"hot": r.hot, "cold": r.cold, "assumed_K_W_per_K": self.module_k},
            "parameters": [
                {"name": p.name, "nominal": p.nominal, "low": p.low, "high": p.high, "unit": p.unit, "doc": p.doc}
                | ({"held": True} if p.held else {})
                for p in r.parameters
            ],
            "boundaries": dict(r.boundaries),
            "sensors": {c: s.node for c, s in r.sensors.items()},
            "sensor_leads": {c: s.lead for c, s in r.sensors.items() if s.lead is not None},
            "sensor_lags": {c: s.lag for c, s in r.sensors.items() if s.lag is not None},
            "csv_columns": ["time_s", "current_A", "voltage_V", *r.sensors, *r.boundaries.values()],
            "nodes": [{"name": n, "capacity_J_per_K": c} for n, c in self.nodes],
            "links": [{"a": a, "b": b, "conductance_W_per_K": g} for a, b, g in self.links],
            "time_constants_s": [float(t) for t in self.time_constants],
            "hold_time_s": {f"{1 - share:.3g}": t for share, t in self.hold_times.items()},
        }


def summarise_rig(rig: RigFile, module_k: float = DEFAULT_MODULE_K) -> RigSummary:
    """The rig's network, time constants and hold times at nominal values (see the module docstring).

    Parameters
    ----------
    rig : RigFile
    module_k : float
        The module's thermal conductance [W/K].

    Returns
    -------
    RigSummary
    """
    desc = rig.build()
    lam, W, s, net = conduction_modes(desc, module_k)  # the module a conductance between its faces
    names = net.nodes
    vals = {p.name: np.atleast_1d(p.nominal) for p in desc.parameters}
    links = tuple((a, b, float(np.atleast_1d(desc.evaluate(g, vals))[0])) for a, b, g in desc.links)
    C = net.C[0]
    h, c = names.index(rig.hot), names.index(rig.cold)
    tau = 1.0 / lam
    read = [names.index(n) for n in desc.sensors.values()]
    half = np.zeros(len(names))
    half[[h, c]] = 0.5
    pumped = np.zeros(len(names))
    pumped[h], pumped[c] = 1.0, -1.0
    holds = {share: max(_settle_time(W, s, lam, q, read, share) for q in (pumped, half)) for share in SETTLED}
    nodes = tuple((n, float(C[i])) for i, n in enumerate(names))
    return RigSummary(rig, float(module_k), nodes, links, np.sort(tau)[::-1], holds)


def _settle_time(W, s, lam, q, read, share) -> float:
    """First time after a heat step ``q`` [W] from which every sensor stays within ``share`` of the largest move."""
    modes = W.T @ (s * q) / lam  # each mode's final amplitude
    final = (s[:, None] * W)[read] @ modes
    t = np.geomspace(1.0, 50.0 / lam.min(), 4000)
    left = (s[:, None] * W)[read] @ (modes[:, None] * np.exp(-lam[:, None] * t[None, :]))
    bad = np.max(np.abs(left), axis=0) > share * np.max(np.abs(final))
    return float(t[np.flatnonzero(bad)[-1] + 1]) if bad.any() else float(t[0])
