"""Reading rig files: a path, a shipped rig's name, or a batch's ``[rig]`` table.

:func:`read_rig_file` checks everything a rig needs before any work, and every
refusal names the file, the key and what to do
(:class:`~tembayes.errors.DataError`): unknown keys, names or parameters, a
parameter never used, a non-positive value anywhere in the parameters'
ranges, a node with no path to a boundary (which is what would make the
network singular), no sensor on one side of the module.  The format is in ``docs/rigs.md``.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import itertools
import tomllib
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from tembayes.errors import DataError, ModelError
from tembayes.physics.rig import RigParameter
from tembayes.physics.rigfile import ADDED_NODES, Block, Link, RigFile, SensorSpec, canonical

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tembayes.physics.rig import RigDescription

__all__ = ["read_rig_file", "shipped_rig", "rig_file_of", "rig_from_config", "REFERENCE", "SHIPPED"]

#: Rigs shipped with tembayes (``tembayes/rigs/NAME.toml``), by preset name.
SHIPPED = ("reference", "reference-faces", "heatsink-al", "liquid-plates")
#: Parameters one expression may name (its positivity is checked at all 2^n corners of their ranges).
MAX_NAMES = 12
#: Top-level keys and tables of a rig file.
TOP_KEYS = ("name", "description", "module", "parameters", "boundaries", "nodes", "links", "sensors", "blocks")
PARAMETER_KEYS = ("nominal", "low", "high", "unit", "doc", "held")
LINK_KEYS = ("a", "b", "g", "spread")
BLOCK_KEYS = ("cells", "g_cell", "g_face")
SENSOR_KEYS = ("node", "depth", "toward", "centre", "spacing", "lead", "lag")


@functools.lru_cache(maxsize=None)
def shipped_rig(name: str) -> RigFile:
    """A rig shipped with tembayes, by preset name (:data:`SHIPPED`); read and checked once per process."""
    if name not in SHIPPED:
        near = difflib.get_close_matches(str(name), SHIPPED, n=1)
        raise ModelError(
            f"unknown rig preset {name!r}"
            + (f" (did you mean {near[0]!r}?)" if near else "")
            + f"; shipped rigs: {', '.join(SHIPPED)}"
        )
    ref = resources.files("tembayes").joinpath("rigs", f"{name}.toml")
    with resources.as_file(ref) as path:
        return read_rig_file(path)


def read_rig_file(path: str | Path) -> RigFile:
    """Read and check a rig file.

    Parameters
    ----------
    path : str or Path

    Returns
    -------
    RigFile

    Raises
    ------
    DataError
        Naming the file, the key and what to do: unknown keys, names or
        parameters, a parameter never used, a value that is not positive
        somewhere in the parameters' ranges, a node with no path to a
        boundary, no sensor on one side of the module.
    """
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise DataError(
            path, "the rig file does not exist", "Check the path ([rig] file = ... is relative to the batch folder)"
        ) from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(path, f"the rig file cannot be read: {e}", "Give a UTF-8 text file (TOML)") from None
    except tomllib.TOMLDecodeError as e:
        raise DataError(path, f"not valid TOML: {e}", "Fix the syntax at the place named") from None
    return _Reader(path, doc).rig()


class _Reader:
    """Check one file's tables in turn; every refusal names the file and the key."""

    def __init__(self, path: Path, doc: Mapping):
        self.path = path
        self.doc = doc
        self.used = set()
        self.claimed = {}  # block cell -> its block
        self.known(doc, TOP_KEYS, "")
        self.params = self.parameters(self.table("parameters"))
        self.boundaries = {k: self.column(f"boundaries.{k}", v) for k, v in self.table("boundaries").items()}
        self.nodes = {k: self.expr(f"nodes.{k}", v, series=False) for k, v in self.table("nodes").items()}

    def fail(self, key: str, problem: str, hint: str):
        raise DataError(self.path, problem, hint, column=key)

    def known(self, table: Mapping, allowed, prefix: str):
        for key in table:
            if key not in allowed:
                near = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
                self.fail(
                    prefix + key,
                    f"unknown key '{prefix}{key}'" + (f" (did you mean '{prefix}{near[0]}'?)" if near else ""),
                    f"Use one of: {', '.join(allowed)}",
                )

    def table(self, key: str, required: bool = True) -> dict:
        v = self.doc.get(key)
        if v is None and not required:
            return {}
        if not isinstance(v, dict) or (required and not v):
            self.fail(key, f"'{key}' must be a table with at least one entry", f"Add a [{key}] section (docs/rigs.md)")
        return v

    def text(self, key: str, v) -> str:
        if not isinstance(v, str) or not v:
            self.fail(key, f"{key} must be a name in quotes, found {v!r}", f'Write it as {key.split(".")[-1]} = "name"')
        return v

    def rig(self) -> RigFile:
        blocks = tuple(self.block(k, v) for k, v in self.table("blocks", required=False).items())
        hot, cold = self.module(blocks)
        self.generated_names(blocks)
        links = tuple(self.link(i, v, blocks) for i, v in enumerate(self.links_list(self.doc.get("links"))))
        sensors = {k: self.sensor(k, v, blocks) for k, v in self.table("sensors").items()}
        self.clashes(sensors)
        self.all_used()
        rig = RigFile(
            name=self.text("name", self.doc.get("name", self.path.stem)),
            description=str(self.doc.get("description", "")),
            path=self.path,
            hot=hot,
            cold=cold,
            parameters=tuple(self.params.values()),
            boundaries=MappingProxyType(self.boundaries),
            nodes=tuple(self.nodes.items()),
            links=links,
            blocks=blocks,
            sensors=MappingProxyType(sensors),
        )
        self.network(rig)
        return rig

    # -- tables --------------------------------------------------------------
    def parameters(self, table: Mapping) -> dict:
        out = {}
        for name, spec in table.items():
            key = f"parameters.{name}"
            if not isinstance(spec, dict):
                self.fail(
                    key,
                    f"{key} must be an inline table",
                    f'Write {name} = {{nominal = ..., low = ..., high = ..., unit = "W/K"}}',
                )
            self.known(spec, PARAMETER_KEYS, key + ".")
            vals = {}
            for k in ("nominal", "low", "high"):
                v = spec.get(k)
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v) or v <= 0:
                    self.fail(
                        f"{key}.{k}",
                        f"{key}.{k} must be a positive number (SI), found {v!r}",
                        "Give the value in SI units",
                    )
                vals[k] = float(v)
            if not vals["low"] <= vals["nominal"] <= vals["high"]:
                self.fail(
                    key,
                    f"{key}: low <= nominal <= high does not hold ({vals})",
                    "Put the nominal value inside its range",
                )
            held = spec.get("held", False)
            if not isinstance(held, bool):
                self.fail(f"{key}.held", f"{key}.held must be true or false", "Write held = true or leave it out")
            out[name] = RigParameter(
                name,
                vals["nominal"],
                vals["low"],
                vals["high"],
                str(spec.get("unit", "")),
                str(spec.get("doc", "")),
                held,
            )
        return out

    def column(self, key: str, v) -> str:
        v = self.text(key, v)
        if not v.endswith("_C"):
            self.fail(
                key, f"{key} = {v!r}: a temperature column's name ends in _C", 'Name the CSV column, e.g. "T_amb_C"'
            )
        return v

    def module(self, blocks) -> tuple[str, str]:
        both = sorted(set(self.boundaries) & set(self.nodes) | set(self.nodes) & set(ADDED_NODES))
        if both:
            self.fail(
                f"nodes.{both[0]}",
                f"'{both[0]}' is a boundary or a name tembayes gives the module's plates",
                "Rename the node",
            )
        table = self.table("module")
        self.known(table, ("hot", "cold"), "module.")
        hot, cold = (self.node(f"module.{k}", table.get(k)) for k in ("hot", "cold"))
        if hot == cold:
            self.fail("module.cold", "the module's hot and cold nodes are the same", "Name two different nodes")
        for k, n in (("hot", hot), ("cold", cold)):
            if any(n in b.cells for b in blocks):
                self.fail(
                    f"module.{k}",
                    f"module.{k} = {n!r} is a cell of a block",
                    "The module's faces are nodes of their own (its plates)",
                )
        return hot, cold

    def generated_names(self, blocks):
        """Names the build gives new nodes (block cells cut finer, leg cells) are not the file's."""
        for n in self.nodes:
            pre, _, num = n.rpartition("_")
            if num.isdigit() and (pre == "leg" or any(pre == b.name for b in blocks)):
                self.fail(
                    f"nodes.{n}",
                    f"node name '{n}' is one tembayes gives a new node (a block's or the legs' cell)",
                    "Rename the node",
                )

    def node(self, key: str, v, boundary_ok: bool = False) -> str:
        v = self.text(key, v)
        ok = list(self.nodes) + (list(self.boundaries) if boundary_ok else [])
        if v not in ok:
            near = difflib.get_close_matches(v, ok, n=1, cutoff=0.6)
            self.fail(
                key,
                f"{key} = {v!r} is not a node"
                + (" or boundary" if boundary_ok else "")
                + (f" (did you mean {near[0]!r}?)" if near else ""),
                "Define it under [nodes] (or [boundaries])",
            )
        return v

    def expr(self, key: str, v, series: bool = True):
        """A capacity or conductance expression, checked (see docs/rigs.md, 'The format')."""
        if isinstance(v, list):
            if not series:
                self.fail(key, f"{key} is a list; only a link's conductance may be a series", "Give one expression")
            if not v:
                self.fail(key, f"{key} is an empty series", "List at least one conductance")
            return [self.expr(key, e, series=False) for e in v]
        if isinstance(v, bool) or not isinstance(v, (int, float, str)):
            self.fail(key, f"{key} = {v!r} is not an expression", 'Write a number, a parameter name or e.g. "0.5*leak"')
        if not isinstance(v, str):
            if not np.isfinite(v) or v <= 0:
                self.fail(key, f"{key} = {v!r} is not positive", "Capacities and conductances are positive")
            return float(v)
        for term in v.split("+"):
            for part in term.split("*"):
                self.factor(key, v, part.strip())
        if len({n for _, ns in canonical(v) for n in ns}) > MAX_NAMES:
            self.fail(key, f"{key} = {v!r} names more than {MAX_NAMES} parameters", "Split it over more links or nodes")
        return v

    def factor(self, key: str, expr: str, part: str):
        if part in self.params:
            self.used.add(part)
            return
        try:
            number = float(part)
        except ValueError:
            near = difflib.get_close_matches(part, list(self.params), n=1, cutoff=0.6)
            self.fail(
                key,
                f"{key} = {expr!r} names unknown parameter '{part}'"
                + (f" (did you mean {near[0]!r}?)" if near else ""),
                "Define it under [parameters]",
            )
        if not np.isfinite(number):
            self.fail(key, f"{key} = {expr!r}: '{part}' is not a finite number", "Write a finite number")

    def links_list(self, v) -> list:
        if not isinstance(v, list) or not v or not all(isinstance(x, dict) for x in v):
            self.fail("links", "'links' must be one or more [[links]] tables", "Add [[links]] sections with a, b and g")
        return v

    def link(self, i: int, spec: Mapping, blocks) -> Link:
        key = f"links[{i + 1}]"
        self.known(spec, LINK_KEYS, key + ".")
        a, b = (self.node(f"{key}.{k}", spec.get(k), boundary_ok=True) for k in ("a", "b"))
        if a in self.boundaries and b in self.boundaries or a == b:
            self.fail(key, f"{key} joins {a} to {b}", "A link joins two nodes, or a node and a boundary")
        cells = {c for blk in blocks for c in blk.cells}
        if a in cells and b in cells:
            self.fail(
                key,
                f"{key} joins two block cells ({a}, {b})",
                "A block's cells are joined by its g_cell; blocks meet through other nodes",
            )
        if "g" not in spec:
            self.fail(f"{key}.g", f"{key} has no conductance g", 'Add g = "name" (W/K)')
        spread = spec.get("spread", True)
        if not isinstance(spread, bool):
            self.fail(f"{key}.spread", f"{key}.spread must be true or false", "Write spread = false or leave it out")
        return Link(a, b, self.expr(f"{key}.g", spec["g"]), spread)

    def block(self, name: str, spec) -> Block:
        key = f"blocks.{name}"
        if not isinstance(spec, dict):
            self.fail(key, f"{key} must be a table", "Write [blocks.NAME] with cells, g_cell and g_face")
        self.known(spec, BLOCK_KEYS, key + ".")
        cells = spec.get("cells")
        if not isinstance(cells, list) or len(cells) < 2:
            self.fail(
                f"{key}.cells",
                f"{key}.cells must list two or more nodes, face to face",
                'Write cells = ["upper", "lower"]',
            )
        cells = tuple(self.node(f"{key}.cells", c) for c in cells)
        if len(set(cells)) != len(cells):
            self.fail(f"{key}.cells", f"{key}.cells names a node twice", "List each cell once")
        for k in ("g_cell", "g_face"):
            if k not in spec:
                self.fail(f"{key}.{k}", f"{key} has no {k}", f'Add {k} = "name" (W/K)')
        for c in cells:
            if c in self.claimed:
                self.fail(
                    f"{key}.cells",
                    f"node '{c}' is a cell of blocks {self.claimed[c]} and {name}",
                    "Give each cell one block",
                )
            self.claimed[c] = name
        return Block(
            name,
            cells,
            self.expr(f"{key}.g_cell", spec["g_cell"], series=False),
            self.expr(f"{key}.g_face", spec["g_face"], series=False),
        )

    def sensor(self, column: str, spec, blocks) -> SensorSpec:
        key = f"sensors.{column}"
        self.column(key, column)
        if not isinstance(spec, dict):
            return SensorSpec(self.node(key, spec))
        self.known(spec, SENSOR_KEYS, key + ".")
        node = self.node(f"{key}.node", spec.get("node"))
        lead = self.lead(key, spec["lead"]) if "lead" in spec else None
        lag = self.lag(key, spec["lag"]) if "lag" in spec else None
        if "depth" not in spec:
            extra = sorted(set(spec) - {"node", "lead", "lag"})
            if extra:
                self.fail(
                    f"{key}.{extra[0]}",
                    f"{key}.{extra[0]} is given without a depth parameter",
                    'Add depth = "PARAMETER" or remove it',
                )
            return SensorSpec(node, lead=lead, lag=lag)
        depth = self.text(f"{key}.depth", spec["depth"])
        if depth not in self.params:
            self.fail(
                f"{key}.depth",
                f"{key}.depth names unknown parameter '{depth}'",
                "Define it under [parameters] (in metres)",
            )
        self.used.add(depth)
        toward = self.node(f"{key}.toward", spec.get("toward"))
        block = next((b for b in blocks if node in b.cells), None)
        if block is None or toward not in block.cells or abs(block.cells.index(toward) - block.cells.index(node)) != 1:
            self.fail(
                f"{key}.toward",
                f"{key}.toward must be the neighbouring cell of '{node}' in its block",
                "Name the next cell of the block",
            )
        nums = {}
        for k in ("centre", "spacing"):
            v = spec.get(k)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                self.fail(
                    f"{key}.{k}", f"{key}.{k} must be a positive length [m], found {v!r}", f"Give the {k} in metres"
                )
            nums[k] = float(v)
        return SensorSpec(node, depth, toward, nums["centre"], nums["spacing"], lead, lag)

    def lag(self, key: str, name) -> str:
        """The response time of a sensor of its own (``sensors.COLUMN.lag``): unit "s"."""
        name = self.text(f"{key}.lag", name)
        p = self.params.get(name)
        if p is None:
            self.fail(
                f"{key}.lag", f"{key}.lag names unknown parameter '{name}'", "Define it under [parameters] (in s)"
            )
        if p.unit != "s":
            self.fail(
                f"{key}.lag",
                f"{key}.lag names '{name}' (unit {p.unit!r}): a sensor's response time is in seconds",
                'Give that parameter unit = "s" (e.g. nominal = 1.0, low = 0.1, high = 3.0)',
            )
        self.used.add(name)
        return name

    def lead(self, key: str, name) -> str:
        """The share parameter of a sensor's leads (``sensors.COLUMN.lead``): unit "1", its range inside 0..1."""
        name = self.text(f"{key}.lead", name)
        p = self.params.get(name)
        if p is None:
            self.fail(f"{key}.lead", f"{key}.lead names unknown parameter '{name}'", "Define it under [parameters]")
        if p.unit != "1" or not p.high < 1.0:
            self.fail(
                f"{key}.lead",
                f"{key}.lead names '{name}' (unit {p.unit!r}, high {p.high:g}): a lead's share is a fraction",
                'Give that parameter unit = "1" and a range inside 0 ... 1 (e.g. low = 0.0001, high = 0.01)',
            )
        self.used.add(name)
        return name

    def clashes(self, sensors):
        seen = {}
        for key, col in [(f"boundaries.{k}", v) for k, v in self.boundaries.items()] + [
            (f"sensors.{c}", c) for c in sensors
        ]:
            if col in seen:
                self.fail(
                    key,
                    f"column {col!r} is read twice ({seen[col]} and {key})",
                    "Give every measured temperature its own column",
                )
            seen[col] = key

    def all_used(self):
        if "c_legs" not in self.params:
            self.fail(
                "parameters.c_legs",
                "no parameter c_legs",
                'Add c_legs = {nominal = ..., low = ..., high = ..., unit = "J/K", doc = "all legs together"}',
            )
        self.used.add("c_legs")
        for name in self.params:
            if name not in self.used:
                self.fail(
                    f"parameters.{name}",
                    f"parameter '{name}' is never used",
                    "Use it in a node, link or block, or remove it",
                )

    # -- the network as a whole -----------------------------------------------
    def network(self, rig: RigFile):
        """Every node reaches a boundary, a sensor on each side, positive values.

        With every conductance positive, a path from each node to a boundary
        (through the module if need be) is what makes the network regular:
        the boundaries then set every temperature.
        """
        adj = {n: set() for n in self.nodes}
        grounded = set()
        for ln in rig.links:
            for u, v in ((ln.a, ln.b), (ln.b, ln.a)):
                if u in adj:
                    (adj[u].add(v) if v in adj else grounded.add(u))
        for b in rig.blocks:
            for u, v in zip(b.cells[:-1], b.cells[1:]):
                adj[u].add(v)
                adj[v].add(u)
        side = {s: _reach(adj, start) for s, start in (("hot", rig.hot), ("cold", rig.cold))}
        for s in ("hot", "cold"):
            if not any(spec.node in side[s] for spec in rig.sensors.values()):
                self.fail(
                    "sensors",
                    f"no sensor on the module's {s} side (nodes joined to '{getattr(rig, s)}')",
                    f"Add a sensor on a node of the {s} side",
                )
        adj[rig.hot].add(rig.cold)  # the legs
        adj[rig.cold].add(rig.hot)
        for n in self.nodes:
            if not _reach(adj, n) & grounded:
                self.fail(
                    f"nodes.{n}", f"node '{n}' has no path to a boundary", "Link it (or its neighbours) to a boundary"
                )
        for desc in (rig.build(), rig.build(4, 3, layers=True)):
            self.values(desc)

    def values(self, desc: RigDescription):
        """Every capacity and conductance positive at every corner of its parameters' ranges."""
        for name, expr in desc.nodes:
            if not self.positive(desc, expr):
                self.fail(
                    f"nodes.{name}",
                    f"the capacity of node '{name}' is not positive somewhere in the parameters' ranges",
                    "Check its expression",
                )
        for a, b, expr in desc.links:
            if not all(self.positive(desc, e) for e in (expr if isinstance(expr, list) else [expr])):
                self.fail(
                    "links",
                    f"the conductance {a}-{b} is not positive somewhere in the parameters' ranges",
                    "Check its expression",
                )

    def positive(self, desc: RigDescription, expr) -> bool:
        # a sum of products of parameters is extreme at a corner of their ranges
        params = {p.name: p for p in desc.parameters}
        names = sorted({n for _, ns in canonical(expr) for n in ns})
        corners = np.array(list(itertools.product((0, 1), repeat=len(names))))
        vals = {n: np.where(corners[:, k] == 1, params[n].high, params[n].low) for k, n in enumerate(names)}
        return bool(np.all(np.asarray(desc.evaluate(expr, vals)) > 0))


def _reach(adj, start) -> set:
    seen, todo = {start}, [start]
    while todo:
        for v in adj[todo.pop()]:
            if v not in seen:
                seen.add(v)
                todo.append(v)
    return seen


# -- a batch's rig --------------------------------------------------------------
def rig_source(text: str) -> dict:
    """The ``[rig]`` table a command-line RIG names: ``{"file": absolute path}`` for a TOML file, else ``{"preset": name}``."""
    if str(text).endswith(".toml") or Path(text).is_file():
        return {"file": str(Path(text).resolve())}
    return {"preset": str(text)}


def rig_file_of(config: Mapping | None) -> RigFile:
    """The rig file a batch.toml ``[rig]`` table names (``preset`` or an absolute ``file``), without its overrides."""
    config = dict(config or {})
    if "file" in config:
        if "preset" in config:
            raise ModelError("[rig] names both a preset and a file; keep one of them")
        return read_rig_file(Path(str(config["file"])))
    return shipped_rig(config.get("preset", "reference"))


def rig_from_config(
    config: Mapping | None,
    leg_cells: int = 0,
    block_split: int = 1,
    *,
    layers: bool = False,
    physics: Mapping[str, float] | None = None,
) -> RigDescription:
    """The rig a batch.toml ``[rig]`` table asks for, at a resolution.

    Parameters
    ----------
    config : mapping
        ``{"preset": NAME}`` or ``{"file": PATH}``, plus parameter values in SI
        units that override the file's nominal ones (e.g. ``g_cooler = 11.0``).
    leg_cells, block_split : int, optional
        Resolution of the module's legs and of the rig's blocks (see :meth:`RigFile.build`).
    layers : bool, optional
        The module's plates in two layers.
    physics : mapping, optional
        Effect parameter values the description includes (``RigDescription.physics``).

    Returns
    -------
    RigDescription

    Raises
    ------
    ModelError
        Unknown preset or parameter, or a non-positive value.
    DataError
        A rig file that cannot be read or is malformed.
    """
    overrides = {k: v for k, v in dict(config or {}).items() if k not in ("preset", "file")}
    bad = [k for k, v in overrides.items() if isinstance(v, bool) or not isinstance(v, (int, float))]
    if bad:
        raise ModelError(f"rig override(s) {bad} must be numbers")
    rig = rig_file_of(config).build(leg_cells, block_split, layers)
    if overrides:
        rig = rig.with_nominal(**overrides)
    if physics:
        rig = dataclasses.replace(rig, physics=dict(physics))
    return rig


#: The reference rig at the paper's resolution (two cells per block, the module lumped).
REFERENCE = shipped_rig("reference").build()
