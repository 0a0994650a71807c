"""Thermal network of a test rig, built from a description.

A rig is data, not code: named physical parameters (with the plausible range
the rig documentation gives), nodes with a capacitance, links with a
conductance, measured boundaries, the two nodes the module sits between, and
the node each sensor reads.  Rig files (:mod:`tembayes.physics.rigread`, :mod:`tembayes.physics.rigfile`)
describe it; :class:`RigDescription` is the network at one resolution.

Capacitance and conductance entries are *expressions* over the parameters:

- a number, or a parameter name: ``"g_paste_hot"``
- a scaled name: ``"0.5*leak_top"``
- a product of a number and names: ``"0.5*leak_bottom*tab_share"``
- a sum of those: ``"c_plate_hot + 0.5*c_legs"``
- a list: conductances in series, ``["g_cooler", "g_steel_quarter"]``
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING

import numpy as np

from tembayes.errors import ModelError
from tembayes.physics.layout import Layout, sensor_layout

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence


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
    def spread_sd(self) -> float:
        """The sd of the coordinate of a uniform draw over the documented range.

        The coordinate is the log, or for a share (:attr:`is_share`) the logit,
        so that a value moved by it (:meth:`moved`) stays positive, and a share
        below one: ``log(high/low)/sqrt(12)``, or ``(logit(high) - logit(low))/sqrt(12)``.
        The uncertainty a held parameter is given wherever it is carried
        (the laws' carry-over, the predictive's anchoring).
        """
        if self.is_share:
            return float((_logit(self.high) - _logit(self.low)) / np.sqrt(12.0))
        return float(np.log(self.high / self.low) / np.sqrt(12.0))

    def moved(self, value, d):
        """``value`` moved by ``d`` in its coordinate (see :attr:`spread_sd`)."""
        if self.is_share:
            return 1.0 / (1.0 + np.exp(-(_logit(value) + d)))
        return value * np.exp(d)

    @property
    def is_share(self) -> bool:
        """A share: dimensionless, its documented range inside (0, 1)."""
        return self.unit == "1" and 0.0 < self.low and self.high < 1.0


def _logit(p):
    p = np.asarray(p, float)
    return np.log(p / (1.0 - p))


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
    Gb : ndarray, shape (nd, N, nb)
        Node-to-boundary conductances [W/K], boundaries in the rig's order.
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
        CSV sensor column to the node it reads.
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
    leads : mapping of str to str
        Sensors whose leads conduct to the room: column -> the share
        parameter (see :meth:`lead_shares`); the others read their node alone.
    lags : mapping of str to str
        Sensors with a response time of their own: column -> its parameter [s]
        (see :meth:`sensor_lags`); the others respond with the model's
        ``sensor_tau_s``, if it has one.
    faces : tuple of str
        ``(hot face, cold face)``: the module's outer nodes, where it meets the
        rig, for plates resolved into layers (the alumina outside the
        junctions' copper); empty when the plates are the faces.
    boundaries : mapping of str to str
        Measured boundary temperatures: name -> CSV column.
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
    leads: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    lags: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))
    faces: tuple = ()
    boundaries: MappingProxyType = field(default_factory=lambda: MappingProxyType({}))

    def __post_init__(self):
        names = [p.name for p in self.parameters]
        if len(set(names)) != len(names):
            raise ModelError(f"rig '{self.name}': duplicate parameter names")
        node_names = [n for n, _ in self.nodes]
        if len(set(node_names)) != len(node_names):
            raise ModelError(f"rig '{self.name}': duplicate node names")
        known = set(node_names)
        if not self.boundaries:
            raise ModelError(f"rig '{self.name}': no boundary (a measured temperature the network is held to)")
        for a, b, expr in self.links:
            for end in (a, b):
                if end not in known and end not in self.boundaries:
                    raise ModelError(f"rig '{self.name}': link end '{end}' is not a node or boundary")
            if a in self.boundaries and b in self.boundaries:
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
        for ch, share in self.leads.items():
            if ch not in self.sensors or share not in names:
                raise ModelError(
                    f"rig '{self.name}': the lead of {ch} needs a sensor and a share parameter; got {share}"
                )
        for ch, tau in self.lags.items():
            if ch not in self.sensors or tau not in names:
                raise ModelError(
                    f"rig '{self.name}': the lag of {ch} needs a sensor and a time-constant parameter; got {tau}"
                )
        object.__setattr__(self, "sensors", MappingProxyType(dict(self.sensors)))
        object.__setattr__(self, "leads", MappingProxyType(dict(self.leads)))
        object.__setattr__(self, "lags", MappingProxyType(dict(self.lags)))
        object.__setattr__(self, "physics", MappingProxyType(dict(self.physics)))
        object.__setattr__(self, "depths", MappingProxyType(dict(self.depths)))
        object.__setattr__(self, "boundaries", MappingProxyType(dict(self.boundaries)))

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

    @functools.cached_property
    def layout(self) -> Layout:
        """The rig's columns and where its sensors sit (:func:`~tembayes.physics.layout.sensor_layout`)."""
        return sensor_layout(self)

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

    def lead_shares(
        self, channels: Sequence[str], values: Mapping[str, float | np.ndarray] | None = None
    ) -> np.ndarray:
        """Share of each channel's reading that is the room's, ``(nd, nch)`` (0 without a lead).

        A sensor whose leads conduct to the room reads ``T + s (T_room - T)``
        (``T`` its :meth:`readout`): in steady state its body sits between what
        it touches and the room in proportion to the two conductances, ``s =
        g_lead / (g_contact + g_lead)``.  The room is the layout's (:attr:`Layout.room_index`).
        """
        return self._per_channel(self.leads, channels, values, 0.0)

    @property
    def lead_parameters(self) -> frozenset:
        """Names of the share parameters the sensors' leads read (:attr:`leads`' values)."""
        return frozenset(self.leads.values())

    @property
    def lag_parameters(self) -> frozenset:
        """Names of the sensors' own response times (:attr:`lags`' values)."""
        return frozenset(self.lags.values())

    def sensor_lags(
        self, channels: Sequence[str], values: Mapping[str, float | np.ndarray] | None = None
    ) -> np.ndarray | None:
        """Each channel's own response time [s], ``(nd, nch)``, NaN where it has none; None if no channel has one.

        The value goes to :func:`~tembayes.physics.effects.apply_sensors`, which lags those
        channels by their own time and the others by ``sensor_tau_s``.
        """
        if not any(c in self.lags for c in channels):
            return None
        return self._per_channel(self.lags, channels, values, np.nan)

    def _per_channel(self, names: Mapping[str, str], channels, values, without: float) -> np.ndarray:
        """``(nd, nch)``: each channel's parameter ``names[channel]`` (nominal if not in ``values``), else ``without``."""
        values = values or {}
        cols = [
            np.atleast_1d(np.asarray(values.get(p, self.parameter(p).nominal), float))
            if (p := names.get(c))
            else np.full(1, without)
            for c in channels
        ]
        return np.column_stack(np.broadcast_arrays(*cols)) if cols else np.zeros((1, 0))

    def read_leads(
        self,
        sensors: np.ndarray,
        channels: Sequence[str],
        values: Mapping[str, float | np.ndarray],
        boundaries: np.ndarray,
    ) -> None:
        """Move the readings of sensors with leads towards the room (:meth:`lead_shares`), in place.

        Parameters
        ----------
        sensors : ndarray, shape (nd, nch, nt)
            The channels' :meth:`readout` of the nodes [K].
        channels : sequence of str
        values : mapping
            Parameter values (the share parameters among them).
        boundaries : ndarray, shape (nb, nt)
            The boundary temperatures at the same points [K], in the rig's order.
        """
        if not any(c in self.leads for c in channels):
            return
        shares = self.lead_shares(channels, values)
        room = np.asarray(boundaries, float)[self.layout.room_index]
        sensors += shares[:, :, None] * (room[None, None, :] - sensors)

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
            for part in term.split("*"):
                part = part.strip()
                if part in self.parameter_names:
                    continue
                try:
                    float(part)
                except ValueError:
                    if part.replace("_", "").isalnum() and not part[0].isdigit():
                        raise ModelError(
                            f"rig '{self.name}': expression '{expr}' names unknown parameter '{part}'"
                        ) from None
                    raise ModelError(f"rig '{self.name}': bad factor '{part}' in '{expr}'") from None

    def evaluate(self, expr, values: Mapping[str, float | np.ndarray]):
        """An expression's value for parameter ``values`` (a series list: the series conductance)."""
        if isinstance(expr, (list, tuple)):
            return 1.0 / sum(1.0 / self.evaluate(e, values) for e in expr)
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

    def face_heat_share(self, name: str) -> float:
        """Largest share of a module face's heat that the links through parameter ``name`` carry.

        At nominal values and in steady state, one watt enters the hot face
        (then the cold face) with every boundary held and the module left
        out; the share is the heat through the links whose conductance
        ``name`` sets, summed link by link (a parameter in several links in
        series counts each).  A leak to the room carries a small share (the
        temperatures are nearly linear in its conductance); a series path (a
        paste, a heat sink's fins, a block's only way out) carries all of it
        (linear in its resistance).  A face whose side reaches no boundary but
        through the module gives 1: every link there is in series with the module.
        """
        nominal = self.nominal()
        up = {**nominal, name: nominal[name] * (1.0 + 1e-6)}
        moved = []
        for a, b, expr in self.links:
            g = float(self.evaluate(expr, nominal))
            if self.evaluate(expr, up) != g:
                moved.append((a, b, g))
        share = 0.0
        for T in self._face_temperatures:
            if T is None:
                return 1.0
            share = max(share, sum(g * abs(T.get(a, 0.0) - T.get(b, 0.0)) for a, b, g in moved))
        return float(share)

    @functools.cached_property
    def _face_temperatures(self) -> tuple[dict[str, float] | None, ...]:
        """Per module face, the nominal network's steady temperatures [K/W] for one watt into it.

        Boundaries held at 0, the module left out; None for a face whose side
        reaches no boundary but through the module.
        """
        net = self.network()
        G, Gb = net.G[0], net.Gb[0]
        L = np.diag(G.sum(axis=1) + Gb.sum(axis=1)) - G
        out = []
        for face in self.module_faces:
            side = [net.index(face)]
            for i in side:  # the nodes the face reaches without the module (the list grows as it is walked)
                side += [j for j in np.flatnonzero(G[i] > 0) if j not in side]
            if not Gb[side].any():
                out.append(None)
                continue
            q = np.zeros(len(side))
            q[0] = 1.0
            T = dict.fromkeys(self.boundaries, 0.0)
            T.update(zip((net.nodes[i] for i in side), np.linalg.solve(L[np.ix_(side, side)], q)))
            out.append(T)
        return tuple(out)

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
            C[:, i] = self.evaluate(expr, vals)
        G = np.zeros((nd, N, N))
        bounds = tuple(self.boundaries)
        Gb = np.zeros((nd, N, len(bounds)))
        for a, b, expr in self.links:
            g = self.evaluate(expr, vals)
            if a in bounds or b in bounds:
                node, bnd = (b, a) if a in bounds else (a, b)
                Gb[:, names.index(node), bounds.index(bnd)] += g
            else:
                i, j = names.index(a), names.index(b)
                G[:, i, j] += g
                G[:, j, i] += g
        if np.any(~np.isfinite(C)) or np.any(C <= 0):
            raise ModelError(f"rig '{self.name}': non-positive or non-finite capacitance")
        return Network(names, C, G, Gb)
