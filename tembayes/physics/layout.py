"""Where a rig's sensors sit: sides of the module, the face sensors, heat paths.

Every stage that reads temperatures by role asks the rig's graph, not a list
of column names: the sensor next to each module face (their difference
carries the module's response), which sensors are on the hot and which on
the cold side, and the series heat paths from a boundary through the
sensors to a face (the preflight's sensor-order check).

    >>> from tembayes.physics import REFERENCE
    >>> REFERENCE.layout.face                      # doctest: +SKIP
    ('T2_C', 'T3_C')
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.linalg import eigh

from tembayes.constants import BASE_COLUMNS

if TYPE_CHECKING:
    from tembayes.physics.rig import RigDescription

__all__ = ["Layout", "sensor_layout", "conduction_modes", "DEFAULT_MODULE_K"]

#: Module conductance assumed where none is given [W/K]: a 40 mm, 6 A module (TEC1-12706's datasheet: 0.54 W/K).
DEFAULT_MODULE_K = 0.5
#: A link to the room conducting less than this at nominal values is a leak [W/K] (a heat
#: sink's fan-cooled fins, a main heat path, conduct watts per kelvin; an enclosure, hundredths).
LEAK_MAX_W_PER_K = 0.25


@dataclass(frozen=True)
class Layout:
    """A rig's measured columns and the sensors' places in its network.

    Attributes
    ----------
    sensors : tuple of str
        Sensor columns, in the rig file's order.
    boundaries : tuple of str
        Boundary columns, in the rig's boundary order.
    boundary_names : tuple of str
        The boundaries' names in the rig, in the same order.
    nodes : dict of str to str
        Sensor column -> the node it reads.
    hot_side, cold_side : tuple of str
        Sensor columns on each side of the module, nearest the face first.
    face : tuple of (str, str)
        ``(hot, cold)``: the sensor nearest each module face.
    paths : tuple of tuple of str
        Series heat paths, one per side with a boundary: the boundary
        column that feeds the side most, then that side's sensors from the
        farthest to the face sensor.
    leak_boundary : str
        The boundary (its name in the rig) linked to the most nodes: the
        room the rig leaks to.
    leaks : tuple of str
        Nodes linked to the room by a leak (below :data:`LEAK_MAX_W_PER_K`),
        where the ``ambient_leak`` effect adds its conductance.
    slowest_tau_s : float
        The network's slowest time constant at nominal values, the module a
        conductance of :data:`DEFAULT_MODULE_K` [s]: how fast the rig settles.
    """

    sensors: tuple
    boundaries: tuple
    boundary_names: tuple
    nodes: dict
    hot_side: tuple
    cold_side: tuple
    face: tuple
    paths: tuple
    leak_boundary: str
    leaks: tuple
    slowest_tau_s: float

    @property
    def room_index(self) -> int:
        """Index of the room's boundary (:attr:`leak_boundary`) in the rig's boundary order."""
        return self.boundary_names.index(self.leak_boundary)

    @property
    def room(self) -> str:
        """The room's boundary column (:attr:`leak_boundary`'s)."""
        return self.boundaries[self.room_index]

    @property
    def controlled(self) -> tuple[str, ...]:
        """The boundary columns other than the room's: what a rig's operator sets (all of them if the room is alone)."""
        return tuple(c for c in self.boundaries if c != self.room) or (self.room,)

    @property
    def faces_held(self) -> bool:
        """Whether both module sides are fed most by a boundary other than the room (plates on a liquid loop).

        The current then barely moves the mean temperature; the boundaries' setpoints do.
        """
        return len(self.paths) == 2 and all(path[0] != self.room for path in self.paths)

    @property
    def temperatures(self) -> tuple[str, ...]:
        """All temperature columns: sensors, then boundaries."""
        return self.sensors + self.boundaries

    @property
    def csv_columns(self) -> tuple[str, ...]:
        """The columns an experiment CSV on this rig must carry."""
        return BASE_COLUMNS + self.temperatures

    def describe(self, column: str) -> str:
        """A short label for a temperature column: ``"T2_C (hot side, at the module face, node top_6)"``."""
        if column in self.boundaries:
            return f"{column} (boundary)"
        side = "hot side" if column in self.hot_side else "cold side"
        at = ", at the module face" if column in self.face else ""
        return f"{column} ({side}{at}, node {self.nodes[column]})"


def sensor_layout(rig: RigDescription) -> Layout:
    """The :class:`Layout` of ``rig``, read from its links.

    A sensor belongs to the side whose module face it is fewer links from
    (the legs are not links, and boundaries are not crossed).
    """
    neighbours, feeds = _graph(rig)
    hops = {side: _hops(neighbours, face) for side, face in zip(("hot", "cold"), rig.module_faces)}
    ordered = _sides(rig, hops, far=len(neighbours) + 1)
    paths = []
    for side in ("hot", "cold"):
        bnd = _main_feed(feeds, hops[side])
        if ordered[side] and bnd is not None:
            paths.append((rig.boundaries[bnd], *ordered[side][::-1]))
    linked = {bnd: sum(any(b == bnd for b, _ in f) for f in feeds.values()) for bnd in rig.boundaries}
    room = max(reversed(tuple(linked)), key=linked.get)
    hot_side, cold_side = ordered["hot"], ordered["cold"]
    return Layout(
        sensors=tuple(rig.sensors),
        boundaries=tuple(rig.boundaries.values()),
        boundary_names=tuple(rig.boundaries),
        nodes=dict(rig.sensors),
        hot_side=hot_side,
        cold_side=cold_side,
        face=(hot_side[0] if hot_side else None, cold_side[0] if cold_side else None),
        paths=tuple(paths),
        leak_boundary=room,
        leaks=tuple(n for n, f in feeds.items() if any(b == room and g < LEAK_MAX_W_PER_K for b, g in f)),
        slowest_tau_s=float(1.0 / conduction_modes(rig)[0].min()),
    )


def _graph(rig: RigDescription) -> tuple[dict, dict]:
    """``(neighbours, feeds)``: node -> linked nodes; node -> ``[(boundary, nominal conductance [W/K])]``."""
    neighbours = {n: [] for n in rig.node_names}
    feeds = {}
    nominal = rig.nominal()
    for a, b, expr in rig.links:
        if a in rig.boundaries or b in rig.boundaries:
            node, bnd = (b, a) if a in rig.boundaries else (a, b)
            feeds.setdefault(node, []).append((bnd, float(rig.evaluate(expr, nominal))))
        else:
            neighbours[a].append(b)
            neighbours[b].append(a)
    return neighbours, feeds


def _sides(rig: RigDescription, hops: dict, far: int) -> dict:
    """``{"hot": columns, "cold": columns}``: each side's sensors, nearest its face first."""
    sides = {"hot": [], "cold": []}
    for col, node in rig.sensors.items():
        dh, dc = hops["hot"].get(node, far), hops["cold"].get(node, far)
        sides["hot" if dh <= dc else "cold"].append((min(dh, dc), col))
    return {k: tuple(c for _, c in sorted(v, key=lambda x: x[0])) for k, v in sides.items()}


def _main_feed(feeds: dict, reached: dict) -> str | None:
    """The boundary that feeds the nodes ``reached`` most (largest total nominal conductance), or None."""
    total = {}
    for node in reached:
        for bnd, g in feeds.get(node, ()):
            total[bnd] = total.get(bnd, 0.0) + g
    return max(total, key=total.get) if total else None


def conduction_modes(rig: RigDescription, module_k: float = DEFAULT_MODULE_K) -> tuple:
    """The modes of ``C dT/dt = -L T`` at nominal values, the module a conductance along its chain.

    Parameters
    ----------
    rig : RigDescription
    module_k : float
        The module's thermal conductance [W/K], face to face.

    Returns
    -------
    lam : ndarray, shape (N,)
        Rates [1/s], ascending (time constants ``1 / lam``).
    W : ndarray, shape (N, N)
        Eigenvectors of ``C^-1/2 L C^-1/2`` (columns).
    s : ndarray, shape (N,)
        ``C^-1/2`` [K^(1/2) / J^(1/2)]: node temperatures of a mode are ``s * W[:, k]``.
    network : Network
    """
    net = rig.network()
    chain = [net.index(n) for n in rig.tem_chain]
    G = net.G[0].copy()
    g = module_k * (len(chain) - 1)
    for a, b in zip(chain[:-1], chain[1:]):
        G[a, b] += g
        G[b, a] += g
    L = np.diag(G.sum(axis=1) + net.Gb[0].sum(axis=1)) - G
    s = 1.0 / np.sqrt(net.C[0])
    lam, W = eigh(s[:, None] * L * s[None, :])
    return lam, W, s, net


def _hops(neighbours: dict, start: str) -> dict:
    """Links from ``start`` to every node reachable from it (breadth first)."""
    dist = {start: 0}
    queue = deque([start])
    while queue:
        n = queue.popleft()
        for m in neighbours[n]:
            if m not in dist:
                dist[m] = dist[n] + 1
                queue.append(m)
    return dist
