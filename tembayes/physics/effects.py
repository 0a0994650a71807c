"""The effect catalogue (``docs/outputs.md``, 'Effect catalogue') as parameterised model extensions.

Every effect adds named parameters to the model.  With all of them at zero the
model is exactly the paper's; :func:`tembayes.physics.simulate.simulate`
always applies every hook, so a parameter that is absent is simply zero.

An effect acts at one of four places, through one hook each:

``tem``
    coefficients of the module element (:mod:`tembayes.physics.kernel`),
``network``
    the rig's conductances,
``sensors``
    what the temperature sensors report,
``input``
    how the measured current relates to the true one (a ``tem`` coefficient
    that the kernel applies to the input).

To add an effect: write its :class:`Effect` below with its parameters and
hook, and add it to :data:`CATALOGUE`.

``default`` is the realistic magnitude the virtual bench uses for
``tembayes simulate --effect NAME``; ``NAME=VALUE`` sets the first parameter
to VALUE and scales the others by the same factor.  ``scale`` is the size the
gap diagnosis's prior gives it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from tembayes.constants import EFFECTS
from tembayes.errors import ModelError
from tembayes.physics import kernel as K

if TYPE_CHECKING:
    from collections.abc import Iterable, Mapping

    from tembayes.physics.rig import Network, RigDescription


@dataclass(frozen=True)
class EffectParameter:
    """A parameter of an effect.

    Attributes
    ----------
    name : str
    default : float
        Bench magnitude (SI).
    scale : float
        Prior scale for the gap diagnosis (SI).
    unit : str
    doc : str
    nonnegative : bool
        Physically at least zero (a time constant, a resistance, a conductance).
    """

    name: str
    default: float
    scale: float
    unit: str
    doc: str
    nonnegative: bool = False


@dataclass(frozen=True)
class Effect:
    """An unmodelled effect as an extension of the base model.

    Attributes
    ----------
    name : str
        Catalogue name (docs/outputs.md, 'Effect catalogue').
    doc : str
    parameters : tuple of EffectParameter
    stage : {"tem", "network", "sensors", "input"}
    """

    name: str
    doc: str
    parameters: tuple
    stage: str
    hook: object = field(default=None, repr=False, compare=False)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        """Names of the effect's parameters."""
        return tuple(p.name for p in self.parameters)

    def parameter(self, name: str) -> EffectParameter:
        """The :class:`EffectParameter` called ``name``."""
        return next(p for p in self.parameters if p.name == name)

    def defaults(self, value: float | None = None) -> dict[str, float]:
        """Bench parameter values; ``value`` sets the first and scales the rest."""
        first = self.parameters[0].default
        f = 1.0 if value is None else float(value) / first
        return {p.name: p.default * f for p in self.parameters}


# --- hooks --------------------------------------------------------------------
def _get(params, name, nd, nonnegative=False):
    v = params.get(name)
    if v is None:
        return np.zeros(nd)
    v = np.broadcast_to(np.asarray(v, dtype=float), (nd,))
    # a sampler's expansion may probe a physically non-negative parameter
    # below zero: there the effect is off (the base model), not unstable
    return np.maximum(v, 0.0) if nonnegative else v


def _tem_k_temperature(P, params):
    P[:, K.P_K1] = _get(params, "K1_per_K", len(P))


def _tem_thomson(P, params):
    P[:, K.P_THOMSON] = _get(params, "thomson_fraction", len(P))


def _tem_joule_split(P, params):
    P[:, K.P_JOULE] = _get(params, "joule_hot_excess", len(P))


def _tem_quadratic(P, params):
    nd = len(P)
    P[:, K.P_R2] = P[:, K.P_R0] * _get(params, "R2_rel_per_K2", nd)
    P[:, K.P_S2] = P[:, K.P_S0] * _get(params, "S2_rel_per_K2", nd)


def _input_current(P, params):
    nd = len(P)
    P[:, K.P_IGAIN] = _get(params, "current_gain_error", nd)
    P[:, K.P_IOFFSET] = _get(params, "current_offset_A", nd)


def _module_links(rig, node):
    """Links from a module face to the rig (not to the module's own nodes)."""
    own = {*rig.tem_chain, *rig.module_faces}
    nodes = set(rig.node_names)
    out = []
    for a, b, _ in rig.links:
        if node in (a, b):
            other = b if a == node else a
            # a leak from the face to a boundary is no contact with the rig
            if other not in own and other in nodes:
                out.append(other)
    return out


def _network_contact(net, rig, params):
    nd = net.C.shape[0]
    # between the module's outer face and the block: with layered plates, outside the alumina
    hot, cold = rig.module_faces
    for side, node in (("cold", cold), ("hot", hot)):
        r = _get(params, f"contact_R_{side}_K_per_W", nd, nonnegative=True)
        if not np.any(r):
            continue
        i = net.index(node)
        for other in _module_links(rig, node):
            j = net.index(other)
            g = net.G[:, i, j]
            g_new = 1.0 / (1.0 / g + r)
            net.G[:, i, j] = g_new
            net.G[:, j, i] = g_new


def _network_ambient(net, rig, params):
    extra = _get(params, "extra_leak_W_per_K", net.C.shape[0], nonnegative=True)
    if not np.any(extra):
        return
    # into the room the rig leaks to, spread in proportion to the leaks it already has
    # (not through a heat sink: its fins are the rig's main path, not a leak)
    layout = rig.layout
    k = tuple(rig.boundaries).index(layout.leak_boundary)
    leaky = np.isin(np.array(rig.node_names), layout.leaks)
    amb = net.Gb[:, :, k] * leaky
    share = amb / amb.sum(axis=1, keepdims=True)
    net.Gb[:, :, k] += share * extra[:, None]


#: Where a simulation of sampled data puts unobserved points after each current step: at these
#: fractions of the way to the first sample after it.  The lag below is exact for an input linear
#: between points, and in the first second after a step a module plate's temperature is far from
#: linear: at 1 Hz, with the step and that sample alone, the lag's first reading after a 0.7 A
#: step came out 0.07-0.24 K short.  Finer fractions change it by under 1 mK.
STEP_FRACTIONS = (1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 3 / 8, 1 / 2, 5 / 8, 3 / 4, 7 / 8)


def _sensor_lag(time, Y, params, own=None):
    """First-order sensor lag on ``Y`` (nd, nch, nt), in place (compiled: a hot path).

    ``time``: ``(nt,)`` or each draw's own ``(nd, nt)`` [s].  ``own``: ``(nd, nch)``
    time constants of sensors that have their own (a rig file's ``lag``), NaN
    where a channel takes ``sensor_tau_s``.
    """
    nd, nch = Y.shape[0], Y.shape[1]
    tau = np.repeat(_get(params, "sensor_tau_s", nd, nonnegative=True)[:, None], nch, axis=1)
    if own is not None:
        own = np.broadcast_to(np.asarray(own, np.float64), (nd, nch))
        tau = np.where(np.isnan(own), tau, np.maximum(own, 0.0))
    if np.any(tau):
        t = np.broadcast_to(np.asarray(time, np.float64), (nd, Y.shape[2]))
        K.first_order_lag(K.writable(t, np.float64), Y, np.ascontiguousarray(tau, np.float64))


CATALOGUE = {
    e.name: e
    for e in (
        Effect(
            "k_temperature",
            "the module's thermal conductance depends on temperature: K(T) = K (1 + K1 (T - T_ref))",
            (EffectParameter("K1_per_K", 0.0015, 0.005, "1/K", "relative slope of K"),),
            "tem",
            _tem_k_temperature,
        ),
        Effect(
            "thomson",
            "Peltier heat at each junction's own Seebeck coefficient plus Thomson heat T dS/dT I dT in the legs",
            (EffectParameter("thomson_fraction", 1.0, 1.0, "1", "0 = S(T_mean) at both junctions, 1 = full"),),
            "tem",
            _tem_thomson,
        ),
        Effect(
            "sensor_lag",
            "the temperature sensors respond with a first-order lag",
            (EffectParameter("sensor_tau_s", 6.0, 10.0, "s", "sensor time constant", True),),
            "sensors",
            _sensor_lag,
        ),
        Effect(
            "contact_resistance",
            "extra thermal resistance between the module and a block",
            (
                EffectParameter("contact_R_cold_K_per_W", 0.06, 0.1, "K/W", "module cold face to bottom block", True),
                EffectParameter("contact_R_hot_K_per_W", 0.0, 0.1, "K/W", "module hot face to top block", True),
            ),
            "network",
            _network_contact,
        ),
        Effect(
            "joule_split",
            "Joule heat not split equally: a fraction 0.5 + delta is released at the hot side",
            (EffectParameter("joule_hot_excess", 0.05, 0.15, "1", "delta, excess hot-side fraction"),),
            "tem",
            _tem_joule_split,
        ),
        Effect(
            "current_offset",
            "the current measurement has a gain and offset error: I_meas = (1 + g) I + o",
            (
                EffectParameter("current_gain_error", 0.01, 0.03, "1", "gain error g"),
                EffectParameter("current_offset_A", 0.005, 0.02, "A", "offset o"),
            ),
            "input",
            _input_current,
        ),
        Effect(
            "quadratic_laws",
            "R_m and S_m curved in T: R0 R2 x^2 and S0 S2 x^2 added to the linear laws",
            (
                EffectParameter("R2_rel_per_K2", 2e-5, 6e-5, "1/K^2", "relative curvature of R"),
                EffectParameter("S2_rel_per_K2", -3e-5, 8e-5, "1/K^2", "relative curvature of S"),
            ),
            "tem",
            _tem_quadratic,
        ),
        Effect(
            "ambient_leak",
            "more heat exchange with ambient than the rig model allows",
            (EffectParameter("extra_leak_W_per_K", 0.06, 0.2, "W/K", "extra conductance to ambient", True),),
            "network",
            _network_ambient,
        ),
    )
}

assert tuple(CATALOGUE) == EFFECTS  # the contract's names, in its order

#: Every effect parameter name -> its effect name.
EFFECT_PARAMETERS = {p.name: e.name for e in CATALOGUE.values() for p in e.parameters}


def get(name: str) -> Effect:
    """The catalogue effect called ``name``."""
    try:
        return CATALOGUE[name]
    except KeyError:
        raise ModelError(f"unknown effect '{name}'; the catalogue has: {', '.join(CATALOGUE)}") from None


def parse_effects(specs: Iterable[str] | None) -> dict[str, dict[str, float]]:
    """Parse ``["k_temperature", "sensor_lag=4"]`` into effect parameter values.

    Returns
    -------
    dict
        Effect name -> {parameter name: value}.
    """
    out = {}
    for spec in specs or ():
        name, _, value = str(spec).partition("=")
        effect = get(name.strip())
        if value:
            try:
                v = float(value)
            except ValueError:
                raise ModelError(f"effect '{spec}': VALUE must be a number") from None
            if not np.isfinite(v):
                raise ModelError(f"effect '{spec}': VALUE must be finite")
        else:
            v = None
        if effect.name in out:
            raise ModelError(f"effect '{effect.name}' given twice")
        out[effect.name] = effect.defaults(v)
    return out


def apply_tem(P: np.ndarray, params: Mapping[str, float | np.ndarray]) -> None:
    """Write every ``tem`` and ``input`` effect coefficient into ``P`` (in place)."""
    for e in CATALOGUE.values():
        if e.stage in ("tem", "input"):
            e.hook(P, params)


def apply_network(net: Network, rig: RigDescription, params: Mapping[str, float | np.ndarray]) -> None:
    """Apply every ``network`` effect to ``net`` (in place)."""
    for e in CATALOGUE.values():
        if e.stage == "network":
            e.hook(net, rig, params)


def apply_sensors(
    time: np.ndarray,
    Y: np.ndarray,
    params: Mapping[str, float | np.ndarray],
    own_lags: np.ndarray | None = None,
) -> None:
    """Apply every ``sensors`` effect to the sensor readings ``Y`` (nd, nch, nt) in place.

    ``time``: the sample times ``(nt,)``, or each draw's ``(nd, nt)`` when the draws' grids differ [s].
    ``own_lags``: ``(nd, nch)`` response times [s] of sensors with their own
    (:meth:`~tembayes.physics.rig.RigDescription.sensor_lags`), NaN for the others.
    """
    for e in CATALOGUE.values():
        if e.stage == "sensors":
            e.hook(time, Y, params, own_lags)


def has_sensor_effect(params: Mapping[str, float | np.ndarray], own_lags: np.ndarray | None = None) -> bool:
    """True if a sensor-stage effect has a non-zero parameter in ``params`` or a sensor lags on its own."""
    if own_lags is not None and np.any(np.nan_to_num(np.asarray(own_lags, float)) > 0):
        return True
    return any(
        e.stage == "sensors" and any(np.any(np.asarray(params.get(p.name, 0.0)) != 0) for p in e.parameters)
        for e in CATALOGUE.values()
    )
