"""Simulate an experiment for many parameter sets at once.

    >>> from tembayes.physics import Inputs, simulate
    >>> sim = simulate(Inputs.from_experiment(exp), params)   # doctest: +SKIP
    >>> sim.sensors.shape                                     # (draws, 4, samples)

``params`` maps names to scalars or arrays of shape ``(nd,)``:

- the module laws and conductance (docs/outputs.md, 'Module parameters', SI): ``R0_ohm``,
  ``R1_ohm_per_K``, ``S0_V_per_K``, ``S1_V_per_K2``, ``K_W_per_K`` (required);
- any rig parameter (:class:`~tembayes.physics.rig.RigParameter`), nominal if
  absent;
- any effect parameter (:mod:`tembayes.physics.effects`), zero if absent.

Unknown names are an error, so a typo cannot silently fall back to a default.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tembayes.constants import MODULE_PARAMETERS, T_REF
from tembayes.errors import ModelError
from tembayes.physics import effects
from tembayes.physics import kernel as K
from tembayes.physics.rigread import REFERENCE

if TYPE_CHECKING:
    from collections.abc import Mapping

    from tembayes.data.experiment import Experiment
    from tembayes.physics.rig import RigDescription

#: Default absolute local error tolerance of the integrator [K].
ATOL = 2e-4


@dataclass(frozen=True)
class Inputs:
    """The measured inputs of an experiment (SI).

    Attributes
    ----------
    time : ndarray, shape (nt,)
        [s], strictly increasing.
    current : ndarray, shape (nt,)
        Measured module current [A].
    boundaries : ndarray, shape (nb, nt)
        Measured boundary temperatures [K], in the rig's boundary order
        (:attr:`~tembayes.physics.rig.RigDescription.boundaries`); a 1-D
        array is one boundary.
    """

    time: np.ndarray
    current: np.ndarray
    boundaries: np.ndarray

    def __post_init__(self):
        set_ = object.__setattr__
        for name in ("time", "current"):
            set_(self, name, np.ascontiguousarray(getattr(self, name), dtype=float))
        set_(self, "boundaries", np.ascontiguousarray(np.atleast_2d(np.asarray(self.boundaries, dtype=float))))
        n = self.time.shape
        if self.current.shape != n:
            raise ModelError(f"Inputs.current: expected shape {n}, found {self.current.shape}")
        if self.boundaries.ndim != 2 or self.boundaries.shape[1:] != n:
            raise ModelError(f"Inputs.boundaries: expected shape (nb, {n[0]}), found {self.boundaries.shape}")
        if len(self.time) < 2 or np.any(np.diff(self.time) <= 0):
            raise ModelError("Inputs.time must have at least 2 strictly increasing samples")

    @classmethod
    def from_experiment(cls, exp: Experiment, rig: RigDescription | None = None) -> Inputs:
        """Inputs of a loaded :class:`tembayes.data.Experiment`, its boundaries in ``rig``'s order (by column name).

        Without ``rig``, the experiment's own boundary order.
        """
        if rig is None:
            return cls(exp.time, exp.current, exp.boundaries)
        return cls(exp.time, exp.current, [exp.channel(c) for c in rig.boundaries.values()])

    def slice(self, start: int | None, stop: int | None) -> Inputs:
        """Samples ``start:stop``."""
        s = slice(start, stop)
        return Inputs(self.time[s], self.current[s], self.boundaries[:, s])


@dataclass(frozen=True)
class Simulation:
    """Result of :func:`simulate` (SI).

    Attributes
    ----------
    time : ndarray, shape (nt,)
    channels : tuple of str
        Sensor channel names: the rig's sensor columns, in its order.
    sensors : ndarray, shape (nd, nch, nt)
        Sensor readings [K] (after any sensor effect).
    voltage : ndarray, shape (nd, nt)
        Module terminal voltage [V].
    t_hot, t_cold : ndarray, shape (nd, nt)
        Module hot and cold plate (junction) temperatures [K].
    steps : ndarray, shape (nd,)
        Accepted integrator steps per draw.
    """

    time: np.ndarray
    channels: tuple
    sensors: np.ndarray
    voltage: np.ndarray
    t_hot: np.ndarray
    t_cold: np.ndarray
    steps: np.ndarray

    @property
    def delta_t(self) -> np.ndarray:
        """Junction temperature difference ``t_hot - t_cold`` [K]."""
        return self.t_hot - self.t_cold


def _as_draws(params):
    arrs = {k: np.atleast_1d(np.asarray(v, dtype=float)) for k, v in params.items()}
    sizes = {a.shape[0] for a in arrs.values() if a.shape[0] != 1}
    if len(sizes) > 1 or any(a.ndim != 1 for a in arrs.values()):
        shapes = {k: a.shape for k, a in arrs.items()}
        raise ModelError(f"parameter arrays must all have shape (nd,) or be scalars; found {shapes}")
    nd = sizes.pop() if sizes else 1
    return {k: np.broadcast_to(a, (nd,)) for k, a in arrs.items()}, nd


def check_params(
    params: Mapping[str, float | np.ndarray], rig: RigDescription = REFERENCE
) -> tuple[dict[str, np.ndarray], int]:
    """Validate a parameter mapping; return it as arrays of shape ``(nd,)`` and ``nd``."""
    missing = [k for k in MODULE_PARAMETERS if k not in params]
    if missing:
        raise ModelError(f"missing module parameter(s) {missing}; need {list(MODULE_PARAMETERS)}")
    known = set(MODULE_PARAMETERS) | set(rig.parameter_names) | set(effects.EFFECT_PARAMETERS)
    unknown = sorted(set(params) - known)
    if unknown:
        raise ModelError(
            f"unknown parameter(s) {unknown}; known: module {list(MODULE_PARAMETERS)}, "
            f"rig '{rig.name}' {list(rig.parameter_names)}, effects {sorted(effects.EFFECT_PARAMETERS)}"
        )
    arrs, nd = _as_draws(params)
    for k in ("R0_ohm", "S0_V_per_K", "K_W_per_K"):
        if np.any(~np.isfinite(arrs[k])) or np.any(arrs[k] <= 0):
            raise ModelError(f"{k} must be positive and finite, got {arrs[k][:5]}")
    for k, a in arrs.items():
        if np.any(~np.isfinite(a)):
            raise ModelError(f"parameter {k} is not finite: {a[:5]}")
    return arrs, nd


def tem_vectors(params: Mapping[str, np.ndarray], nd: int, tref: float = T_REF) -> np.ndarray:
    """Kernel parameter vectors ``(nd, N_P)`` from a checked parameter mapping."""
    P = np.zeros((nd, K.N_P))
    P[:, K.P_R0] = params["R0_ohm"]
    P[:, K.P_R1] = params["R1_ohm_per_K"]
    P[:, K.P_S0] = params["S0_V_per_K"]
    P[:, K.P_S1] = params["S1_V_per_K2"]
    P[:, K.P_K0] = params["K_W_per_K"]
    P[:, K.P_TREF] = tref
    effects.apply_tem(P, params)
    return P


def build(params: Mapping[str, float | np.ndarray], rig: RigDescription = REFERENCE) -> dict:
    """Kernel arrays for a parameter mapping (the rig's ``physics`` values where the mapping has none).

    Returns
    -------
    dict
        ``A``, ``Bb``, ``Cinv``, ``P``, ``tem`` (chain node indices),
        ``network`` and the checked ``params`` with ``nd``.
    """
    params, nd = check_params({**rig.physics, **params}, rig)
    net = rig.network({k: v for k, v in params.items() if k in rig.parameter_names})
    if net.C.shape[0] != nd:
        net = type(net)(net.nodes, *(np.broadcast_to(a, (nd,) + a.shape[1:]).copy() for a in (net.C, net.G, net.Gb)))
    effects.apply_network(net, rig, params)
    A, Bb, Cinv = net.matrices()
    tem = np.array([net.index(n) for n in rig.tem_chain], dtype=np.int64)
    return dict(A=A, Bb=Bb, Cinv=Cinv, P=tem_vectors(params, nd), tem=tem, network=net, params=params, nd=nd)


def simulate(
    inputs: Inputs,
    params: Mapping[str, float | np.ndarray],
    *,
    rig: RigDescription = REFERENCE,
    y0: np.ndarray | None = None,
    steady_start: bool = True,
    atol: float = ATOL,
    hmax: float | None = None,
) -> Simulation:
    """Simulate an experiment for ``nd`` parameter sets.

    Parameters
    ----------
    inputs : Inputs
        Measured current [A] and boundary temperatures [K] over time [s].
    params : mapping of str to float or ndarray of shape (nd,)
        Model parameters (see the module docstring).
    rig : RigDescription, optional
        The rig; the reference rig by default.
    y0 : ndarray, shape (nd, N) or (N,), optional
        Initial node temperatures [K]; default: all nodes at the first
        boundary's first temperature, refined to the steady state (``steady_start``).
    steady_start : bool, optional
        Start from the steady state at the first sample's inputs (the rig at
        rest before the experiment), default True.
    atol : float, optional
        Absolute local error tolerance [K].
    hmax : float, optional
        Largest internal step [s]; default the longest sampling interval.

    Returns
    -------
    Simulation
    """
    if not isinstance(inputs, Inputs):
        raise TypeError(f"inputs must be tembayes.physics.Inputs, got {type(inputs).__name__}")
    _check_boundaries(inputs.boundaries, rig)
    m = build(params, rig)
    nd = m["nd"]
    names = m["network"].nodes
    N = len(names)
    channels = tuple(rig.sensors)
    a, b, f = rig.readout(channels, m["params"])
    rec = np.concatenate([a, [names.index(rig.hot), names.index(rig.cold)], b]).astype(np.int64)
    if y0 is None:
        Y0 = np.full((nd, N), inputs.boundaries[0, 0])
    else:
        Y0 = np.array(np.broadcast_to(np.asarray(y0, dtype=float), (nd, N)))
    if hmax is None:
        hmax = float(np.max(np.diff(inputs.time)))
    out, volt, stats = K.integrate(
        inputs.time,
        inputs.current,
        inputs.boundaries,
        m["A"],
        m["Bb"],
        m["Cinv"],
        m["tem"],
        m["P"],
        rec,
        Y0,
        bool(steady_start),
        float(atol),
        float(hmax),
    )
    if np.any(stats[:, 3] == 2):
        raise ModelError(
            f"the integrator gave up (more than {K.MAX_STEPS_PER_POINT} steps per sample: the "
            "parameters make the network too stiff or unstable); check the parameters"
        )
    if np.any(stats[:, 3]):
        raise ModelError("the steady-state start did not converge; check the parameters")
    if not np.all(np.isfinite(volt)):
        raise ModelError("the simulation diverged (non-finite values); check the parameters")
    nch = len(channels)
    sensors = out[:, :, :nch] + f[:, None, :] * (out[:, :, nch + 2 :] - out[:, :, :nch])
    sensors = np.ascontiguousarray(sensors.transpose(0, 2, 1))
    rig.read_leads(sensors, channels, m["params"], inputs.boundaries)
    effects.apply_sensors(inputs.time, sensors, m["params"], rig.sensor_lags(channels, m["params"]))
    return Simulation(
        time=inputs.time,
        channels=channels,
        sensors=sensors,
        voltage=volt,
        t_hot=out[:, :, nch],
        t_cold=out[:, :, nch + 1],
        steps=stats[:, 0].astype(np.int64),
    )


def _check_boundaries(boundaries: np.ndarray, rig: RigDescription) -> None:
    if boundaries.shape[0] != len(rig.boundaries):
        raise ModelError(
            f"the inputs have {boundaries.shape[0]} boundary temperature(s), rig '{rig.name}' has "
            f"{len(rig.boundaries)} ({', '.join(rig.boundaries.values())})"
        )


def integrate_on_grids(
    m: dict,
    grids: np.ndarray,
    current: np.ndarray,
    boundaries: np.ndarray,
    rec: np.ndarray,
    atol: float,
    hmax: float,
    y0: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Run the kernel on a time grid per draw, from the steady state at the first point (or from ``y0``).

    Parameters
    ----------
    m : dict
        :func:`build` output.
    grids : ndarray, shape (nd, nt)
        Time points per draw [s].
    current : ndarray, shape (nd, nt)
        Current at the points [A].
    boundaries : ndarray, shape (nb, nt)
        Boundary temperatures at the points [K] in the rig's order (shared
        by the draws).
    rec : ndarray of int
        Nodes to record.
    atol, hmax : float
    y0 : ndarray, shape (nd, N), optional
        Initial state of every node [K]; default the steady state at the
        first point's inputs.

    Returns
    -------
    out : ndarray, shape (nd, nt, len(rec))
    volt : ndarray, shape (nd, nt)
    failed : ndarray of bool, shape (nd,)
        No steady start, step budget exceeded or non-finite values; those
        draws are NaN.
    steps : ndarray, shape (nd,)
        Accepted integrator steps per draw.
    """
    nd = m["nd"]
    boundaries = np.atleast_2d(np.asarray(boundaries, float))
    U = np.repeat(boundaries[None], nd, axis=0)
    steady = y0 is None
    Y0 = np.full((nd, len(m["network"].nodes)), float(boundaries[0, 0])) if steady else np.array(y0, dtype=float)
    out, volt, stats = K.integrate_grids(
        grids, current, U, m["A"], m["Bb"], m["Cinv"], m["tem"], m["P"], rec, Y0, steady, float(atol), float(hmax)
    )
    failed = (stats[:, 3] != 0) | ~np.all(np.isfinite(volt), axis=1)
    out[failed] = np.nan
    volt[failed] = np.nan
    return out, volt, failed, stats[:, 0].copy()
