"""A rig file's content, and the network it gives at a resolution.

The format is the user's (``docs/rigs.md``; read and checked by
:mod:`tembayes.physics.rigread`): parameters with a nominal value and a
plausible range, nodes with a heat capacity, links with a conductance (a list
is conductances in series), measured boundaries mapped to CSV columns,
sensors mapped to nodes, and the two nodes the module sits between.
:meth:`RigFile.build` adds the module itself: its legs (K, Joule and Peltier
heat; their heat capacity is the file's ``c_legs``) and, for a calibration
model with layered plates, each plate's alumina (``g_ceramic``).

Two tables go beyond a lumped network, because the calibration model and the
virtual bench resolve a solid block more finely than a person would draw it:

``[blocks.NAME]``
    ``cells`` (two or more nodes, face to face, evenly spaced), ``g_cell``
    (between neighbouring cell centres) and ``g_face`` (from a face to its
    nearest cell centre).  :meth:`RigFile.build` with ``split = m`` (odd)
    cuts every cell into ``m``; the middle one keeps the cell's centre, so a
    sensor there reads the same depth.  A link to an end cell whose series
    starts (or ends) at that cell with the block's ``g_face`` is a contact at
    the face and moves to the outermost sub-cell; any other link of a cell is
    shared evenly by its sub-cells, unless it says ``spread = false`` (a leak
    at the face: the outermost sub-cell takes it whole).

a sensor table, ``T1_C = {node = ..., depth = ..., toward = ..., centre = ..., spacing = ...}``
    A sensor whose depth is a (held) parameter: it reads the temperature
    profile between its node's centre (at depth ``centre``) and the
    neighbouring cell ``toward``, ``spacing`` metres away.
    Optionally ``lead = "SHARE"`` (its leads draw that share of the reading
    from the room) and ``lag = "TIME"`` (it responds with that time of its own,
    in seconds, instead of the model's ``sensor_tau_s``), with or without a depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from tembayes.errors import ModelError
from tembayes.physics.rig import RigDescription, RigParameter, SensorDepth

if TYPE_CHECKING:
    from pathlib import Path
    from types import MappingProxyType

__all__ = ["RigFile", "Link", "Block", "SensorSpec", "CERAMIC", "JUNCTION_SHARE", "ADDED_NODES", "expression_names"]

#: Names :meth:`RigFile.build` gives the nodes it adds for the module's layered plates.
ADDED_NODES = ("hot_ceramic", "cold_ceramic")

#: Parameters the module brings when the calibration model layers its plates.
CERAMIC = RigParameter(
    "g_ceramic",
    50.0,
    35.0,
    70.0,
    "W/K",
    "through a module's alumina plate to its junctions (the plate's two layers)",
    held=True,
)
#: Share of a plate's heat capacity at its junctions (copper and solder); the rest is alumina.
JUNCTION_SHARE = 0.2


@dataclass(frozen=True)
class Link:
    """A conductance between two nodes, or a node and a boundary (``g``: an expression or a series list)."""

    a: str
    b: str
    g: object
    spread: bool = True


@dataclass(frozen=True)
class Block:
    """A solid block of evenly spaced cells (see the module docstring)."""

    name: str
    cells: tuple
    g_cell: object
    g_face: object


@dataclass(frozen=True)
class SensorSpec:
    """A sensor: the node it reads, its depth between two cells, its leads' share, its own response time."""

    node: str
    depth: str | None = None
    toward: str | None = None
    centre: float = 0.0
    spacing: float = 0.0
    lead: str | None = None
    lag: str | None = None


@dataclass(frozen=True)
class RigFile:
    """A rig as its file gives it, checked; :meth:`build` makes the network a model simulates.

    Attributes
    ----------
    name, description : str
    path : Path or None
        The file it was read from.
    hot, cold : str
        The nodes of the module's hot and cold faces.
    parameters : tuple of RigParameter
    boundaries : mapping of str to str
        Boundary name -> CSV column (a measured temperature).
    nodes : tuple of (str, expr)
    links : tuple of Link
    blocks : tuple of Block
    sensors : mapping of str to SensorSpec
        CSV column -> sensor.
    """

    name: str
    description: str
    path: Path | None
    hot: str
    cold: str
    parameters: tuple
    boundaries: MappingProxyType
    nodes: tuple
    links: tuple
    blocks: tuple
    sensors: MappingProxyType

    def build(self, leg_cells: int = 0, split: int = 1, layers: bool = False) -> RigDescription:
        """The network at a resolution.

        Parameters
        ----------
        leg_cells : int
            0: the module lumped between its two face nodes (each carries
            half of ``c_legs``); ``n > 0``: its legs in ``n`` cells.
        split : int
            Each block cell resolved into ``split`` cells (odd, so that a
            cell centre stays at every sensor).
        layers : bool
            Each of the module's plates in two layers: the alumina at the
            face (``1 - JUNCTION_SHARE`` of its heat capacity) and the
            junctions, joined by ``g_ceramic``.

        Returns
        -------
        RigDescription
        """
        if int(leg_cells) != leg_cells or leg_cells < 0:
            raise ModelError(f"leg_cells must be a whole number >= 0, got {leg_cells}")
        if int(split) != split or split < 1 or split % 2 == 0:
            raise ModelError(f"split must be an odd whole number >= 1 (a cell centre at each sensor), got {split}")
        legs = tuple(f"leg_{i + 1}" for i in range(int(leg_cells)))
        nodes, links, sensors, depths = _split_blocks(self, int(split))
        nodes, links, sensors, faces = _add_module(self, nodes, links, sensors, legs, layers)
        return RigDescription(
            name=self._label(len(legs), int(split), layers),
            # the module's parameter joins the held ones, which are carried over in this order
            parameters=tuple(p for p in self.parameters if not p.held)
            + ((CERAMIC,) if layers else ())
            + tuple(p for p in self.parameters if p.held),
            nodes=tuple(nodes),
            links=tuple(links),
            hot=self.hot,
            cold=self.cold,
            sensors=sensors,
            legs=legs,
            faces=faces,
            depths=depths,
            leads={col: s.lead for col, s in self.sensors.items() if s.lead is not None},
            lags={col: s.lag for col, s in self.sensors.items() if s.lag is not None},
            boundaries=dict(self.boundaries),
        )

    def _label(self, legs: int, split: int, layers: bool) -> str:
        """The name with the resolution: ``reference-legs4-blocks6-layers``."""
        name = self.name + (f"-legs{legs}" if legs else "")
        if split > 1:
            sizes = {len(b.cells) for b in self.blocks}
            name += f"-blocks{sizes.pop() * split}" if len(sizes) == 1 else f"-split{split}"
        return name + ("-layers" if layers else "")


# -- expressions --------------------------------------------------------------
def _scaled(expr, k: float):
    """``k`` times an expression: every term's number times ``k``, written first."""
    if k == 1.0:
        return expr
    if isinstance(expr, list):
        return [_scaled(e, k) for e in expr]
    if isinstance(expr, (int, float)):
        return float(expr) * k
    return " + ".join("*".join([repr(coef * k), *names]) for coef, names in _terms(expr))


def canonical(expr) -> tuple:
    """An expression as sorted ``(coefficient, names)`` terms: ``"1*g"`` and ``"g"`` compare equal."""
    if isinstance(expr, (int, float)):
        return ((float(expr), ()),)
    return tuple(sorted((coef, tuple(sorted(names))) for coef, names in _terms(expr)))


def expression_names(expr) -> set[str]:
    """The parameter names an expression (a number, a text, or a series list of them) uses."""
    if isinstance(expr, (list, tuple)):
        return {n for e in expr for n in expression_names(e)}
    if not isinstance(expr, str):
        return set()
    return {n for _, names in _terms(expr) for n in names}


def _terms(expr: str) -> list:
    """The terms of an expression: ``(product of its numbers, its names in order)``."""
    out = []
    for term in expr.split("+"):
        coef, names = 1.0, []
        for part in term.split("*"):
            part = part.strip()
            try:
                coef *= float(part)
            except ValueError:
                names.append(part)
        out.append((coef, names))
    return out


def _text(expr) -> str:
    return expr if isinstance(expr, str) else repr(float(expr))


def _series_end(g, at_a: bool):
    """The element of a link's series at its ``a`` (or ``b``) end."""
    if isinstance(g, list):
        return g[0] if at_a else g[-1]
    return g


def _with_end(g, at_a: bool, new):
    items = list(g) if isinstance(g, list) else [g]
    items[0 if at_a else -1] = new
    return items if isinstance(g, list) else items[0]


# -- building -----------------------------------------------------------------
def _split_blocks(rig: RigFile, m: int):
    """Nodes, links, sensors and depths with every block cell cut into ``m``."""
    owner = {c: (b, i) for b in rig.blocks for i, c in enumerate(b.cells)}

    def subs(cell):
        b, i = owner[cell]
        return [f"{b.name}_{i * m + j + 1}" for j in range(m)] if m > 1 else [cell]

    nodes = []
    for name, c in rig.nodes:
        nodes += [(s, _scaled(c, 1.0 / m)) for s in subs(name)] if name in owner else [(name, c)]
    links = []
    for b in rig.blocks:
        chain = [s for c in b.cells for s in subs(c)]
        links += [(u, v, _scaled(b.g_cell, float(m))) for u, v in zip(chain[:-1], chain[1:])]
    for ln in rig.links:
        links += _split_link(ln, owner, subs, m)
    sensors, depths = {}, {}
    for col, s in rig.sensors.items():
        cells = subs(s.node) if s.node in owner else [s.node]
        mid = len(cells) // 2
        sensors[col] = cells[mid]
        if s.depth is not None:
            b, i = owner[s.node]
            step = 1 if b.cells.index(s.toward) > i else -1
            toward = cells[mid + step] if m > 1 else s.toward
            depths[col] = SensorDepth(toward, s.depth, s.centre, s.spacing / m)
    return nodes, links, sensors, depths


def _split_link(ln: Link, owner, subs, m: int) -> list:
    ends = [e for e in (ln.a, ln.b) if e in owner]
    if not ends:
        return [(ln.a, ln.b, ln.g)]
    cell = ends[0]  # the reader refuses a link between two block cells
    at_a = cell == ln.a
    b, i = owner[cell]
    outer = subs(cell)[0 if i == 0 else -1]
    other = ln.b if at_a else ln.a

    def link(node, g):
        return (node, other, g) if at_a else (other, node, g)

    if i in (0, len(b.cells) - 1) and canonical(_series_end(ln.g, at_a)) == canonical(b.g_face):
        return [link(outer, _with_end(ln.g, at_a, _scaled(b.g_face, float(m))))]
    if not ln.spread:
        return [link(outer, ln.g)]
    return [link(s, _scaled(ln.g, 1.0 / m)) for s in subs(cell)]


def _add_module(rig: RigFile, nodes: list, links: list, sensors: dict, legs: tuple, layers: bool):
    """The module's legs (and its plates' alumina layers) added between its face nodes."""
    extra = "" if legs else " + 0.5*c_legs"
    face = dict(zip((rig.hot, rig.cold), ADDED_NODES)) if layers else {}
    out = []
    for name, c in nodes:
        if name not in (rig.hot, rig.cold):
            out.append((name, c))
            continue
        junction = _scaled(c, JUNCTION_SHARE) if layers else c
        plate = [(name, f"{_text(junction)}{extra}" if extra else junction)]
        if layers:  # the alumina on the rig's side of the junctions
            alumina = (face[name], _scaled(c, 1.0 - JUNCTION_SHARE))
            plate = [alumina, *plate] if name == rig.hot else [*plate, alumina]
        out += plate
        if name == rig.hot:
            out += [(leg, f"{1.0 / len(legs)!r}*c_legs") for leg in legs]
    if not layers:
        return out, links, sensors, ()
    half = "2.0*g_ceramic"
    moved = [_through_alumina(a, b, g, face, half) for a, b, g in links]
    moved += [(face[rig.hot], rig.hot, half), (rig.cold, face[rig.cold], half)]
    # a sensor on a plate touches its outside, the alumina
    sensors = {col: face.get(node, node) for col, node in sensors.items()}
    return out, moved, sensors, (face[rig.hot], face[rig.cold])


def _through_alumina(a, b, g, face, half):
    """A link to a plate, moved to the plate's alumina with the alumina's half in series at that end."""
    if a not in face and b not in face:
        return (a, b, g)
    items = list(g) if isinstance(g, list) else [g]
    if a in face:
        a, items = face[a], [half, *items]
    if b in face:
        b, items = face[b], [*items, half]
    return (a, b, items)
