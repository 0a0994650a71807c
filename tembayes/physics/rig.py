"""Thermal network of a test rig, built from a description.

A rig is data, not code: named physical parameters (with the plausible range
the rig documentation gives), nodes with a capacitance, links with a
conductance, two measured boundaries (``water`` and ``ambient``), the two
nodes the module sits between, and the node each sensor reads.  Another rig is
another :class:`RigDescription`; :data:`PRESETS` holds the known ones.

Capacitance and conductance entries are *expressions* over the parameters:

- a number, or a parameter name: ``"g_paste_hot"``
- a scaled name: ``"0.5*leak_top"``
- a product of a number and names: ``"0.5*leak_bottom*tab_share"``
- a sum of those: ``"c_plate_hot + 0.5*c_legs"``
- a list: conductances in series, ``["g_cooler", "g_steel_quarter"]``

The reference rig (``docs/data-format.md``, 'The reference rig') splits each steel block
into two 5 mm cells whose centres sit exactly at the sensor depths (2.5 mm
away from each face), so the four sensors read node temperatures.  Its module is
the paper's lumped element by default (``leg_cells=0``: each plate carries
half the legs' capacitance); :func:`reference_rig` with ``leg_cells=n``
resolves the legs into ``n`` cells, so Joule heat is released along the legs
at the local resistance.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from tembayes.errors import ModelError

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

BOUNDARIES = ("water", "ambient")


@dataclass(frozen=True)
class RigParameter:
    """A named physical parameter of a rig.

    Attributes
    ----------
    name : str
    nominal : float
        Centre of the prior (SI units).
    low, high : float
        Plausible range from the rig documentation (SI units); the gap
        diagnosis flags posteriors far outside it.
    unit : str
    doc : str
    held : bool
        A calibration holds it at its nominal value even though its range
        is wide (sampling it would not converge); its range's uncertainty
        can be carried over by :func:`tembayes.calibrate.discrepancy.held_nuisance_spread`.
    """

    name: str
    nominal: float
    low: float
    high: float
    unit: str
    doc: str = ""
    held: bool = False

    @property
    def is_share(self) -> bool:
        """A share: dimensionless, its documented range inside (0, 1)."""
        return self.unit == "1" and 0.0 < self.low and self.high < 1.0


@dataclass(frozen=True)
class SensorDepth:
    """Where a sensor sits between its node's centre and a neighbour.

    The reading is ``T_node + f (T_toward - T_node)`` with
    ``f = (depth - centre) / spacing``: a sensor off its cell's centre reads
    the steel's temperature profile at its own depth (linear between the
    two centres; a little beyond, for the other side).

    Attributes
    ----------
    toward : str
        The neighbouring node deeper into the block (away from the face the
        depth is measured from).
    parameter : str
        The rig parameter giving the sensor's depth below that face [m].
    centre : float
        Depth of the sensor node's centre [m].
    spacing : float
        Distance between the two nodes' centres [m].
    """

    toward: str
    parameter: str
    centre: float
    spacing: float


@dataclass(frozen=True)
class Network:
    """The arrays of a rig network for a batch of parameter draws.

    Attributes
    ----------
    nodes : tuple of str
    C : ndarray, shape (nd, N)
        Node capacitances [J/K].
    G : ndarray, shape (nd, N, N)
        Symmetric node-to-node conductances [W/K], zero diagonal.
    Gb : ndarray, shape (nd, N, 2)
        Node-to-boundary conductances (water, ambient) [W/K].
    """

    nodes: tuple
    C: np.ndarray
    G: np.ndarray
    Gb: np.ndarray

    def index(self, node: str) -> int:
        """Index of the node called ``node``."""
        return self.nodes.index(node)

    def matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``(A, Bb, Cinv)`` of ``dT/dt = A T + Bb u + Cinv Q`` [1/s, 1/s, K/J]."""
        Cinv = 1.0 / self.C
        A = self.G.copy()
        diag = self.G.sum(axis=2) + self.Gb.sum(axis=2)
        idx = np.arange(len(self.nodes))
        A[:, idx, idx] -= diag
        A *= Cinv[:, :, None]
        Bb = self.Gb * Cinv[:, :, None]
        return A, Bb, Cinv


@dataclass(frozen=True)
class RigDescription:
    """A rig as data: parameters, nodes, links, module position and sensors.

    Attributes
    ----------
    name : str
    parameters : tuple of RigParameter
    nodes : tuple of (str, expr)
        Node name and capacitance expression [J/K].
    links : tuple of (str, str, expr)
        Two node names (or a boundary name) and a conductance expression [W/K].
    hot, cold : str
        The nodes of the module's hot and cold plates.
    sensors : mapping of str to str
        CSV sensor channel (``"T1_C"``...) to the node it reads.
    legs : tuple of str
        Nodes of the module's legs from the hot to the cold plate, for a
        module resolved into cells (the virtual bench); empty for the paper's
        lumped module.  Leg nodes have a capacitance but no links: the module
        element conducts along them.
    physics : mapping of str to float
        Values of effect parameters this description includes (e.g.
        ``thomson_fraction = 1``): :func:`~tembayes.physics.simulate.build`
        uses them unless a parameter mapping gives its own.
    depths : mapping of str to SensorDepth
        Sensors whose depth is a parameter (read between two nodes, see
        :meth:`readout`); the others read their node.
    faces : tuple of str
        ``(hot face, cold face)``: the module's outer nodes, where it meets the
        rig, for plates resolved into layers (the alumina outside the
        junctions' copper); empty when the plates are the faces.
    """

    name: str
    parameters: tuple
    nodes: tuple
    links: tuple
    hot: str
    cold: str
    sensors: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    legs: tuple = ()
    physics: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    depths: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    faces: tuple = ()

    def __post_init__(self):
        names = [p.name for p in self.parameters]
        if len(set(names)) != len(names):
            raise ModelError(f"rig '{self.name}': duplicate parameter names")
        node_names = [n for n, _ in self.nodes]
        if len(set(node_names)) != len(node_names):
            raise ModelError(f"rig '{self.name}': duplicate node names")
        known = set(node_names)
        for a, b, expr in self.links:
            for end in (a, b):
                if end not in known and end not in BOUNDARIES:
                    raise ModelError(f"rig '{self.name}': link end '{end}' is not a node or boundary")
            if a in BOUNDARIES and b in BOUNDARIES:
                raise ModelError(f"rig '{self.name}': link {a}-{b} joins two boundaries")
            self._check_expr(expr)
        for _, expr in self.nodes:
            self._check_expr(expr)
        for node in (self.hot, self.cold):
            if node not in known:
                raise ModelError(f"rig '{self.name}': module node '{node}' is not a node")
        if self.faces and (len(self.faces) != 2 or not set(self.faces) <= known):
            raise ModelError(f"rig '{self.name}': faces must be two nodes (hot, cold), got {self.faces}")
        for node in self.legs:
            if node not in known or node in (self.hot, self.cold):
                raise ModelError(f"rig '{self.name}': leg node '{node}' is not a separate node")
        for ch, node in self.sensors.items():
            if node not in known:
                raise ModelError(f"rig '{self.name}': sensor {ch} reads unknown node '{node}'")
        for ch, d in self.depths.items():
            if ch not in self.sensors or d.toward not in known or d.parameter not in names:
                raise ModelError(
                    f"rig '{self.name}': depth of {ch} needs a sensor, a node to read towards and a parameter; got {d}"
                )
        object.__setattr__(self, "sensors", MappingProxyType(dict(self.sensors)))
        object.__setattr__(self, "physics", MappingProxyType(dict(self.physics)))
        object.__setattr__(self, "depths", MappingProxyType(dict(self.depths)))

    # -- parameters ---------------------------------------------------------
    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of the rig's parameters."""
        return tuple(p.name for p in self.parameters)

    def parameter(self, name: str) -> RigParameter:
        """The :class:`RigParameter` called ``name`` (ModelError if the rig has none)."""
        for p in self.parameters:
            if p.name == name:
                return p
        raise ModelError(f"rig '{self.name}' has no parameter '{name}'; it has {self.parameter_names}")

    def nominal(self) -> dict[str, float]:
        """Nominal parameter values as a dict (SI)."""
        return {p.name: p.nominal for p in self.parameters}

    def with_nominal(self, **values: float) -> RigDescription:
        """A copy with some nominal values replaced (e.g. from batch.toml overrides)."""
        params = []
        for p in self.parameters:
            if p.name in values:
                v = float(values.pop(p.name))
                if not np.isfinite(v) or v <= 0:
                    raise ModelError(f"rig parameter '{p.name}' must be a positive number, got {v}")
                p = RigParameter(p.name, v, min(p.low, v), max(p.high, v), p.unit, p.doc, p.held)
            params.append(p)
        if values:
            import difflib

            name = sorted(values)[0]
            near = difflib.get_close_matches(name, self.parameter_names, n=1, cutoff=0.6)
            raise ModelError(
                f"unknown rig parameter '{name}'"
                + (f" (did you mean '{near[0]}'?)" if near else "")
                + f"; rig '{self.name}' has {', '.join(self.parameter_names)}"
            )
        return dataclasses.replace(self, parameters=tuple(params))

    @property
    def module_faces(self) -> tuple[str, str]:
        """``(hot, cold)`` outer nodes of the module: :attr:`faces`, or the plates."""
        return tuple(self.faces) or (self.hot, self.cold)

    @property
    def tem_chain(self) -> tuple[str, ...]:
        """Node names of (hot plate, leg cells..., cold plate)."""
        return (self.hot, *self.legs, self.cold)

    def readout(
        self, channels: Sequence[str], values: Mapping[str, float | np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """How each channel reads the nodes: ``T = T[a] + f (T[b] - T[a])``.

        Parameters
        ----------
        channels : sequence of str
            Sensor columns.
        values : mapping of str to float or ndarray of shape (nd,), optional
            Parameter values; missing ones take their nominal value.

        Returns
        -------
        a, b : ndarray of int, shape (nch,)
            Node indices (``b = a`` for a sensor that reads its node).
        f : ndarray, shape (nd, nch)
            Share of node ``b`` [1]; 0 at a sensor's nominal depth.
        """
        names = self.node_names
        values = values or {}
        a = np.array([names.index(self.sensors[c]) for c in channels], dtype=np.int64)
        b = np.array(
            [names.index(self.depths[c].toward) if c in self.depths else i for c, i in zip(channels, a)], dtype=np.int64
        )
        cols = [
            (np.atleast_1d(np.asarray(values.get(d.parameter, self.parameter(d.parameter).nominal), float)) - d.centre)
            / d.spacing
            if (d := self.depths.get(c))
            else np.zeros(1)
            for c in channels
        ]
        f = np.column_stack(np.broadcast_arrays(*cols)) if cols else np.zeros((1, 0))
        return a, b, f

    # -- network ------------------------------------------------------------
    @property
    def node_names(self) -> tuple[str, ...]:
        """Names of the network's nodes, in order."""
        return tuple(n for n, _ in self.nodes)

    def _check_expr(self, expr):
        if isinstance(expr, (list, tuple)):
            if not expr:
                raise ModelError(f"rig '{self.name}': empty series expression")
            for e in expr:
                self._check_expr(e)
            return
        if isinstance(expr, (int, float)):
            if expr <= 0:
                raise ModelError(f"rig '{self.name}': non-positive constant {expr}")
            return
        if not isinstance(expr, str):
            raise ModelError(f"rig '{self.name}': bad expression {expr!r}")
        for term in expr.split("+"):
            names = 0
            for part in term.split("*"):
                part = part.strip()
                if part in self.parameter_names:
                    names += 1
                    continue
                try:
                    float(part)
                except ValueError:
                    if part.replace("_", "").isalnum() and not part[0].isdigit():
                        raise ModelError(
                            f"rig '{self.name}': expression '{expr}' names unknown parameter '{part}'"
                        ) from None
                    raise ModelError(f"rig '{self.name}': bad factor '{part}' in '{expr}'") from None
            if names == 0:
                raise ModelError(f"rig '{self.name}': term '{term.strip()}' of '{expr}' names no parameter")

    def _eval(self, expr, values):
        if isinstance(expr, (list, tuple)):
            return 1.0 / sum(1.0 / self._eval(e, values) for e in expr)
        if isinstance(expr, (int, float)):
            return np.float64(expr)
        total = 0.0
        for term in expr.split("+"):
            value = 1.0
            for part in term.split("*"):
                part = part.strip()
                try:
                    value = value * float(part)
                except ValueError:
                    value = value * values[part]
            total = total + value
        return total

    def network(self, values: Mapping[str, float | np.ndarray] | None = None) -> Network:
        """Build the network arrays.

        Parameters
        ----------
        values : mapping of str to float or ndarray of shape (nd,), optional
            Parameter values (SI); missing ones take their nominal value.

        Returns
        -------
        Network
        """
        vals = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in self.nominal().items()}
        for k, v in (values or {}).items():
            if k in vals:
                vals[k] = np.atleast_1d(np.asarray(v, dtype=float))
        nd = max((v.shape[0] for v in vals.values()), default=1)
        names = self.node_names
        N = len(names)
        C = np.empty((nd, N))
        for i, (_, expr) in enumerate(self.nodes):
            C[:, i] = self._eval(expr, vals)
        G = np.zeros((nd, N, N))
        Gb = np.zeros((nd, N, 2))
        for a, b, expr in self.links:
            g = self._eval(expr, vals)
            if a in BOUNDARIES or b in BOUNDARIES:
                node, bnd = (b, a) if a in BOUNDARIES else (a, b)
                Gb[:, names.index(node), BOUNDARIES.index(bnd)] += g
            else:
                i, j = names.index(a), names.index(b)
                G[:, i, j] += g
                G[:, j, i] += g
        if np.any(~np.isfinite(C)) or np.any(C <= 0):
            raise ModelError(f"rig '{self.name}': non-positive or non-finite capacitance")
        return Network(names, C, G, Gb)


# --- the reference rig -------------------------------------------------------
K_STEEL = 16.2  # AISI 304 [W/(m K)]
AREA = 0.040 * 0.040  # block and module footprint [m^2]
RHO_C = 7900.0 * 500.0  # volumetric heat capacity of the steel [J/(m^3 K)]


def _steel_g(d):
    return K_STEEL * AREA / d


_REFERENCE_PARAMETERS = (
    RigParameter("g_cooler", 12.5, 10.0, 15.0, "W/K", "water cooler to top block face"),
    RigParameter("g_paste_hot", 35.0, 20.0, 50.0, "W/K", "thermal paste, module hot face"),
    RigParameter("g_paste_cold", 35.0, 20.0, 50.0, "W/K", "thermal paste, module cold face"),
    RigParameter("c_plate_hot", 4.5, 4.0, 5.0, "J/K", "hot alumina plate"),
    RigParameter("c_plate_cold", 4.5, 4.0, 5.0, "J/K", "cold alumina plate"),
    RigParameter("c_legs", 1.25, 1.0, 1.5, "J/K", "all legs of the module together"),
    RigParameter("leak_top", 0.02, 0.01, 0.03, "W/K", "top block to ambient (enclosure)"),
    RigParameter("leak_bottom", 0.04, 0.02, 0.06, "W/K", "bottom block to ambient (enclosure, tabs)"),
    RigParameter(
        "tab_share",
        0.5,
        0.2,
        0.9,
        "1",
        "share of leak_bottom through the tabs the block rests on (at its bottom face); "
        "the rest leaves through the side walls",
    ),
    RigParameter(
        "c_half_block",
        RHO_C * AREA * 0.005,
        0.97 * RHO_C * AREA * 0.005,
        1.03 * RHO_C * AREA * 0.005,
        "J/K",
        "5 mm of a steel block (rho c V)",
    ),
    RigParameter(
        "g_steel_quarter",
        _steel_g(0.0025),
        0.95 * _steel_g(0.0025),
        1.05 * _steel_g(0.0025),
        "W/K",
        "2.5 mm of steel (k A / d)",
    ),
    RigParameter(
        "g_steel_half",
        _steel_g(0.005),
        0.95 * _steel_g(0.005),
        1.05 * _steel_g(0.005),
        "W/K",
        "5 mm of steel (k A / d)",
    ),
)

#: The module's plates as two layers (``reference_rig(layers=True)``): the
#: alumina, then the copper and solder where the junctions are, joined by the
#: ceramic's conductance (0.6-1 mm of alumina, k ~ 25 W/(m K), over 40 x 40 mm:
#: 35-70 W/K).  A calibration holds it at the nominal value: in series with the
#: paste the data barely tell the two apart, and sampled it bent the R0-S0-K
#: ridge until a module did not converge in 60 000 steps (held, the same module
#: converged in 25 000); its range's uncertainty is carried over to the laws
#: instead (``--discrepancy robust``).
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
#: Nominal depth of every sensor below its block's nearer face [m].
SENSOR_DEPTH = 2.5e-3
#: The sensors' depths: the hole's depth and the thermistor's seat in it are
#: known to about a quarter of a millimetre.  In a heat-flux path of steel a
#: quarter millimetre is ~0.1 K at 10 W, which the calibration cannot tell
#: from the junctions' temperature difference, so the laws' R0-S0-K ridge
#: moves with it; a calibration holds the depths at nominal and carries their
#: range over (``--discrepancy robust``).
DEPTHS = tuple(
    RigParameter(
        f"depth_{s}",
        SENSOR_DEPTH,
        SENSOR_DEPTH - 0.25e-3,
        SENSOR_DEPTH + 0.25e-3,
        "m",
        f"depth of {s} below its block's nearer face",
        held=True,
    )
    for s in ("T1", "T2", "T3", "T4")
)


def reference_rig(leg_cells: int = 0, block_cells: int = 2, layers: bool = False) -> RigDescription:
    """The reference identification rig.

    Parameters
    ----------
    leg_cells : int, optional
        0 (default): the paper's lumped module between two plate nodes, each
        plate carrying half the legs' capacitance.  ``n > 0``: the legs
        resolved into ``n`` cells (Joule heat along the legs at the local
        resistance, conduction along them).
    block_cells : int, optional
        Cells per steel block: 2 (default, the paper-sized model: cell
        centres at the sensor depths), or 6, 10, 14, ... (``2 (2k + 1)``, so
        that a cell centre still sits at each sensor's depth, 2.5 mm from a
        face).  Heat diffuses through 10 mm of steel in ~25 s, so the step
        transients need more than two cells per block.
    layers : bool, optional
        Each plate as two layers: the alumina (``1 - JUNCTION_SHARE`` of its
        heat capacity, next to the paste) and the junctions' copper, joined
        by ``g_ceramic`` (:data:`CERAMIC`).  The paper's plate is one node at
        the junctions, so the alumina's resistance lands in the paste's and
        its heat capacity at the junctions.
    """
    if int(leg_cells) != leg_cells or leg_cells < 0:
        raise ModelError(f"leg_cells must be a whole number >= 0, got {leg_cells}")
    nb = block_cells
    if int(nb) != nb or nb < 2 or (nb - 2) % 4:
        raise ModelError(f"block_cells must be 2, 6, 10, 14, ... (a cell centre at each sensor), got {block_cells}")
    nb = int(nb)
    legs = tuple(f"leg_{i + 1}" for i in range(leg_cells))
    plate_extra = "" if legs else " + 0.5*c_legs"
    if nb == 2:
        top = ["top_upper", "top_lower"]
        bottom = ["bottom_upper", "bottom_lower"]
    else:
        top = [f"top_{i + 1}" for i in range(nb)]  # top_1 at the water cooler
        bottom = [f"bottom_{i + 1}" for i in range(nb)]  # bottom_1 at the module
    f = 2.0 / nb  # cell size in units of a 5 mm half block
    c_cell = "c_half_block" if nb == 2 else f"{f!r}*c_half_block"
    g_cell = "g_steel_half" if nb == 2 else f"{1.0 / f!r}*g_steel_half"
    g_face = "g_steel_quarter" if nb == 2 else f"{1.0 / f!r}*g_steel_quarter"
    leak = "0.5" if nb == 2 else repr(1.0 / nb)
    if layers:
        share, rest = repr(JUNCTION_SHARE), repr(1.0 - JUNCTION_SHARE)
        hot = [("hot_ceramic", f"{rest}*c_plate_hot"), ("hot_plate", f"{share}*c_plate_hot" + plate_extra)]
        cold = [("cold_plate", f"{share}*c_plate_cold" + plate_extra), ("cold_ceramic", f"{rest}*c_plate_cold")]
        hot_face, cold_face = "hot_ceramic", "cold_ceramic"
        half = "2.0*g_ceramic"
    else:
        hot = [("hot_plate", "c_plate_hot" + plate_extra)]
        cold = [("cold_plate", "c_plate_cold" + plate_extra)]
        hot_face, cold_face, half = "hot_plate", "cold_plate", None
    nodes = (
        *((n, c_cell) for n in top),
        *hot,
        *((leg, f"{1.0 / leg_cells!r}*c_legs") for leg in legs),
        *cold,
        *((n, c_cell) for n in bottom),
    )
    links = [("water", top[0], ["g_cooler", g_face])]
    links += [(a, b, g_cell) for a, b in zip(top[:-1], top[1:])]
    links += [(top[-1], hot_face, [g_face, "g_paste_hot"] + ([half] if layers else []))]
    links += [(cold_face, bottom[0], ([half] if layers else []) + ["g_paste_cold", g_face])]
    if layers:
        links += [("hot_ceramic", "hot_plate", half), ("cold_plate", "cold_ceramic", half)]
    links += [(a, b, g_cell) for a, b in zip(bottom[:-1], bottom[1:])]
    links += [(n, "ambient", f"{leak}*leak_top") for n in top]
    # the bottom block rests on tabs: part of its leak leaves at the bottom face
    links += [(n, "ambient", f"{leak}*leak_bottom + -{leak}*leak_bottom*tab_share") for n in bottom]
    links += [(bottom[-1], "ambient", "leak_bottom*tab_share")]
    k = (nb - 2) // 4  # the cell whose centre is 2.5 mm from a face
    name = "reference"
    if legs:
        name += f"-legs{leg_cells}"
    if nb != 2:
        name += f"-blocks{nb}"
    if layers:
        name += "-layers"
    return RigDescription(
        name=name,
        parameters=_REFERENCE_PARAMETERS + ((CERAMIC,) if layers else ()) + DEPTHS,
        nodes=nodes,
        links=tuple(links),
        hot="hot_plate",
        cold="cold_plate",
        sensors={"T1_C": top[k], "T2_C": top[nb - 1 - k], "T3_C": bottom[k], "T4_C": bottom[nb - 1 - k]},
        legs=legs,
        faces=(hot_face, cold_face) if layers else (),
        depths={
            ch: SensorDepth(deeper, f"depth_{ch[:2]}", SENSOR_DEPTH, 0.010 / nb)
            for ch, deeper in (
                ("T1_C", top[k + 1]),
                ("T2_C", top[nb - 2 - k]),
                ("T3_C", bottom[k + 1]),
                ("T4_C", bottom[nb - 2 - k]),
            )
        },
    )


#: The reference rig with the paper's lumped module.
REFERENCE = reference_rig()

#: Known rigs by preset name (``[rig] preset = ...`` in batch.toml): builders
#: taking ``leg_cells``.
PRESETS = MappingProxyType({"reference": reference_rig})


def rig_from_config(
    config: Mapping | None,
    leg_cells: int = 0,
    block_cells: int = 2,
    *,
    layers: bool = False,
    physics: Mapping[str, float] | None = None,
) -> RigDescription:
    """The rig a batch.toml ``[rig]`` table asks for.

    Parameters
    ----------
    config : mapping
        ``{"preset": "reference", <parameter>: <value>, ...}``; values in SI
        units override the preset's nominal values (e.g. ``g_cooler = 11.0``).
    leg_cells, block_cells : int, optional
        Resolution of the module's legs and of the blocks (see
        :func:`reference_rig`).
    layers : bool, optional
        The module's plates in two layers (see :func:`reference_rig`).
    physics : mapping, optional
        Effect parameter values the description includes (``RigDescription.physics``).

    Returns
    -------
    RigDescription

    Raises
    ------
    ModelError
        Unknown preset or parameter, or a non-positive value.
    """
    config = dict(config or {})
    preset = config.pop("preset", "reference")
    if not isinstance(preset, str) or preset not in PRESETS:
        raise ModelError(f"unknown rig preset {preset!r}; known presets: {sorted(PRESETS)}")
    rig = PRESETS[preset](leg_cells, block_cells, layers)
    if config:
        bad = [k for k, v in config.items() if isinstance(v, bool) or not isinstance(v, (int, float))]
        if bad:
            raise ModelError(f"rig override(s) {bad} must be numbers")
        rig = rig.with_nominal(**config)
    if physics:
        rig = dataclasses.replace(rig, physics=dict(physics))
    return rig
