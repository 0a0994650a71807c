"""Priors of a module calibration, scaled by the module type's datasheet.

docs/data-format.md, '[module_type]': the datasheet gives the *scale* of the priors through the
standard conversions (``Datasheet.resistance/seebeck/conductance``).  Nothing
here knows the TEC1-12706 numbers, so another module type needs no code
change.

Law parameters and K (weakly informative, documented in docs/methods.md):

- ``R0_ohm``, ``S0_V_per_K``, ``K_W_per_K``: log-normal around the datasheet
  value with a log-sd of 0.3.  The conversions assume ideal material and
  miss contact and tab losses; real modules sit within ~20 % of them, so the
  data, not the prior, decide.
- ``R1_ohm_per_K``, ``S1_V_per_K2``: normal around zero with a sd of 1 %/K of
  the datasheet value.  Bi2Te3 modules have slopes of +0.1 to +0.6 %/K; the
  prior does not presume the sign.

Rig nuisance parameters: log-normal around the rig's nominal value whose
+-2 sd span the documented plausible range (``RigParameter.low/high``).  A
share (a dimensionless parameter whose range lies inside (0, 1), e.g. the
part of a leak through the tabs) is logit-normal instead: a log-normal lets
it pass 1, where the leak it splits turns negative and the rig cannot be
simulated (an unmodelled curvature drove the example's tab share to 180).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tembayes.constants import MODULE_PARAMETERS

if TYPE_CHECKING:
    from collections.abc import Callable, Mapping, Sequence

    from numpy.typing import ArrayLike

    from tembayes.data.batch import Datasheet
    from tembayes.physics.rig import RigParameter

#: Log-sd of the log-normal priors of R0, S0 and K around the datasheet values.
LEVEL_LOG_SD = 0.3
#: Sd of the slope priors relative to the datasheet level [1/K].
SLOPE_REL_SD = 0.01
#: The kind of each law's prior (MODULE_PARAMETERS order): the sampler's coordinates are their logs for the levels.
LAW_KINDS = ("lognormal", "normal", "lognormal", "normal", "lognormal")


def logit(x: ArrayLike) -> np.ndarray:
    """``log(x / (1 - x))``."""
    x = np.asarray(x, dtype=float)
    return np.log(x) - np.log1p(-x)


def expit(u: ArrayLike) -> np.ndarray:
    """The inverse of :func:`logit`."""
    return 0.5 * (1.0 + np.tanh(0.5 * np.asarray(u, dtype=float)))


@dataclass(frozen=True)
class ParameterPrior:
    """A one-dimensional prior.

    Attributes
    ----------
    name : str
    kind : str
        ``"lognormal"`` (``log x ~ N(log center, scale)``), ``"reciprocal"``
        (the same log-normal, sampled as ``1 / x``: a conductance as a
        resistance), ``"logitnormal"`` (``logit x ~ N(logit center,
        scale)``, for a share in (0, 1)), ``"normal"`` (``x ~ N(center,
        scale)``) or ``"uniform"`` (``center +- scale``).
    center, scale : float
        SI units (``scale`` is the sd of the log or logit for ``lognormal``,
        ``reciprocal`` and ``logitnormal``, the half-width for ``uniform``).
    """

    name: str
    kind: str
    center: float
    scale: float

    def to_unconstrained(self, x: ArrayLike) -> np.ndarray:
        """Map a value to the sampler's coordinate (the log, reciprocal or logit for those kinds)."""
        x = np.asarray(x, dtype=float)
        if self.kind == "lognormal":
            return np.log(x)
        if self.kind == "reciprocal":
            return 1.0 / x
        return logit(x) if self.kind == "logitnormal" else x

    def from_unconstrained(self, u: ArrayLike) -> np.ndarray:
        """Map a sampler's coordinate back to the value (SI)."""
        u = np.asarray(u, dtype=float)
        if self.kind == "lognormal":
            return np.exp(u)
        if self.kind == "reciprocal":
            with np.errstate(divide="ignore"):
                return 1.0 / u
        return expit(u) if self.kind == "logitnormal" else u

    @property
    def coordinate_center(self) -> float:
        """The prior's centre in the sampler's coordinate."""
        return float(self.to_unconstrained(self.center))

    @property
    def coordinate_sd(self) -> float:
        """The prior's sd in the sampler's coordinate (to first order for ``reciprocal``)."""
        if self.kind == "uniform":
            return self.scale / np.sqrt(3.0)
        return self.scale / self.center if self.kind == "reciprocal" else self.scale

    def z(self, x: ArrayLike) -> np.ndarray:
        """Standard score of the value ``x`` (SI) under the prior: its log or logit (as the kind has it), centred and scaled."""
        x = np.asarray(x, dtype=float)
        if self.kind in ("lognormal", "reciprocal"):
            return (np.log(x) - np.log(self.center)) / self.scale
        if self.kind == "logitnormal":
            return (logit(x) - logit(self.center)) / self.scale
        return (x - self.center) / (self.scale / np.sqrt(3.0) if self.kind == "uniform" else self.scale)

    def coordinate_precision(self, u: float) -> float:
        """The prior's curvature (Gauss-Newton) at the coordinate ``u``: 1 / its local sd squared (0 for a uniform)."""
        if self.kind == "uniform":
            return 0.0
        # log-normal in the resistance u: its log's sd is a relative sd of u
        sd = self.scale * float(u) if self.kind == "reciprocal" else self.scale
        return 1.0 / sd**2

    @property
    def coordinate_floor(self) -> float:
        """The lowest coordinate a ``reciprocal`` prior allows: 8 prior sds above its centre's value (-inf otherwise)."""
        return self.coordinate_center * float(np.exp(-8.0 * self.scale)) if self.kind == "reciprocal" else -np.inf

    def logpdf_unconstrained(self, u: ArrayLike) -> np.ndarray:
        """Log density in the sampler's coordinate (Jacobian included)."""
        u = np.asarray(u, dtype=float)
        if self.kind == "uniform":
            inside = np.abs(u - self.center) < self.scale
            return np.where(inside, -np.log(2.0 * self.scale), -np.inf)
        if self.kind == "reciprocal":
            # 1/x of a log-normal x is log-normal: its density in u itself
            return ParameterPrior(self.name, "lognormal", 1.0 / self.center, self.scale).logpdf(u)
        z = (u - self.coordinate_center) / self.scale
        return -0.5 * z * z - np.log(self.scale) - 0.5 * np.log(2.0 * np.pi)

    def logpdf(self, x: ArrayLike) -> np.ndarray:
        """Log density of the value ``x`` (SI)."""
        x = np.asarray(x, dtype=float)
        if self.kind == "reciprocal":
            return ParameterPrior(self.name, "lognormal", self.center, self.scale).logpdf(x)
        if self.kind == "lognormal":
            with np.errstate(divide="ignore", invalid="ignore"):
                out = self.logpdf_unconstrained(np.log(np.where(x > 0, x, np.nan))) - np.log(x)
            return np.where(x > 0, out, -np.inf)
        if self.kind == "logitnormal":
            inside = (x > 0) & (x < 1)
            with np.errstate(divide="ignore", invalid="ignore"):
                xi = np.where(inside, x, 0.5)
                out = self.logpdf_unconstrained(logit(xi)) - np.log(xi) - np.log1p(-xi)
            return np.where(inside, out, -np.inf)
        return self.logpdf_unconstrained(x)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Draw ``n`` values (SI) from the prior with the generator ``rng``."""
        if self.kind == "uniform":
            return self.center + self.scale * rng.uniform(-1.0, 1.0, n)
        if self.kind == "reciprocal":
            return self.center * np.exp(self.scale * rng.standard_normal(n))
        return self.from_unconstrained(self.coordinate_center + self.scale * rng.standard_normal(n))

    def to_dict(self) -> dict[str, str | float]:
        """JSON-ready dict of the prior's kind, center and scale."""
        return {"kind": self.kind, "center": self.center, "scale": self.scale}


def law_priors(datasheet: Datasheet) -> tuple[ParameterPrior, ...]:
    """Priors of ``R0, R1, S0, S1, K`` (contract order) from a datasheet.

    Parameters
    ----------
    datasheet : tembayes.data.Datasheet

    Returns
    -------
    tuple of ParameterPrior
    """
    R, S, K = datasheet.resistance(), datasheet.seebeck(), datasheet.conductance()
    centres = (R, 0.0, S, 0.0, K)
    scales = (LEVEL_LOG_SD, SLOPE_REL_SD * R, LEVEL_LOG_SD, SLOPE_REL_SD * S, LEVEL_LOG_SD)
    return tuple(ParameterPrior(*a) for a in zip(MODULE_PARAMETERS, LAW_KINDS, centres, scales))


@dataclass(frozen=True)
class LawPrior:
    """The laws' prior of a module when it is not the datasheet's: a known type's population.

    Attributes
    ----------
    priors : tuple of ParameterPrior
        ``R0, R1, S0, S1, K`` (contract order), each of the kind the
        datasheet prior gives it (log-normal levels, normal slopes), so the
        sampler's coordinates do not change.
    source : str
        Where it came from, as ``summary.json`` records it (e.g. ``"population of runs/lot42"``).
    """

    priors: tuple
    source: str

    def __post_init__(self):
        expected = tuple(zip(MODULE_PARAMETERS, LAW_KINDS))
        got = tuple((p.name, p.kind) for p in self.priors)
        if got != expected:
            raise ValueError(f"a law prior gives {got}; expected {expected}")

    def to_json(self) -> dict:
        """``{"source", "priors": {name: {"kind", "center", "scale"}}}``."""
        return {"source": self.source, "priors": {p.name: p.to_dict() for p in self.priors}}

    @classmethod
    def from_json(cls, doc: Mapping) -> LawPrior:
        """The inverse of :meth:`to_json` (the laws in contract order, whatever the file's key order)."""
        v = doc["priors"]
        priors = tuple(
            ParameterPrior(k, v[k]["kind"], float(v[k]["center"]), float(v[k]["scale"])) for k in MODULE_PARAMETERS
        )
        return cls(priors, str(doc["source"]))


def module_law_priors(datasheet: Datasheet, law_prior: LawPrior | None) -> tuple[ParameterPrior, ...]:
    """The laws' prior a calibration uses: ``law_prior``'s, else the datasheet's (:func:`law_priors`)."""
    return law_priors(datasheet) if law_prior is None else law_prior.priors


def law_log_prior(priors: Sequence[ParameterPrior]) -> Callable[[ArrayLike], np.ndarray]:
    """Callable ``f(theta) -> log prior`` of the law parameters under ``priors`` (:func:`module_law_priors`).

    ``theta`` has shape ``(n, 5)``, in
    :data:`~tembayes.constants.MODULE_PARAMETERS` order (SI).
    """
    assert tuple(p.name for p in priors) == MODULE_PARAMETERS

    def log_prior(theta):
        theta = np.atleast_2d(np.asarray(theta, dtype=float))
        return sum(p.logpdf(theta[:, j]) for j, p in enumerate(priors))

    return log_prior


def rig_prior(parameter: RigParameter, linear: bool = False, shunt: bool = False) -> ParameterPrior:
    """Prior of a :class:`~tembayes.physics.rig.RigParameter`.

    Centred on the nominal value, its documented range spanning +-2 sd of
    the log, or of the logit for a share (unit ``"1"``, range inside (0, 1)).
    A conductance (unit ``"W/K"``) is sampled as its resistance: the
    junctions' temperature difference is linear in a series resistance and
    curved in its log, and on the example's TEM2 that curvature (the hot
    paste, posterior 31-94 W/K) was what kept independence proposals from
    being accepted.

    ``shunt``: a conductance that carries little of the module's heat (a
    leak to the room, :meth:`~tembayes.physics.rig.RigDescription.face_heat_share`)
    is sampled in its log instead.  The temperatures are nearly linear in a
    shunt's conductance, and a sensor's lead share (linear too) pulls the
    same readings towards the room: in the leak's resistance their ridge
    curved, the sampler crawled along it and the expansion missed it (three
    liquid-plate modules out-of-model: autocorrelation times 220-1560
    steps, PSIS k_hat 1.0-5.4; in the log, one of them 310 steps and 0.57).

    ``linear``: uniform over the documented range, sampled as itself -- for
    a parameter the predictions are linear in, whose data may leave it near
    the range's low end (a sensor's lead share, ``T + s (T_room - T)``).
    In its logit such a share's posterior is a funnel towards zero, a decade
    wide, that the sampler crawls along: on the heat-sink rig's bench 4 of 8
    modules ended unconverged (autocorrelation times up to 1460 steps).
    """
    if linear:
        half = 0.5 * (parameter.high - parameter.low)
        return ParameterPrior(parameter.name, "uniform", parameter.low + half, half)
    if parameter.is_share:
        span = float(np.diff(logit([parameter.low, parameter.high]))[0])
        return ParameterPrior(parameter.name, "logitnormal", parameter.nominal, span / 4.0)
    kind = "reciprocal" if parameter.unit == "W/K" and not shunt else "lognormal"
    return ParameterPrior(parameter.name, kind, parameter.nominal, np.log(parameter.high / parameter.low) / 4.0)


def effect_priors(names: Sequence[str]) -> tuple[ParameterPrior, ...]:
    """Priors of the parameters of catalogue effects added to a calibration.

    Zero is the base model.  A signed parameter gets ``N(0, scale)``; one that
    is physically non-negative (a sensor time constant, a contact resistance,
    an extra leak) a uniform prior on ``[0, 3 scale]``, ``scale`` being the
    catalogue's prior size of the effect
    (:class:`~tembayes.physics.effects.EffectParameter`).

    Parameters
    ----------
    names : sequence of str
        Effect names (docs/outputs.md, 'Effect catalogue').

    Returns
    -------
    tuple of ParameterPrior
    """
    from tembayes.physics import effects as E

    out = []
    for name in names:
        for p in E.get(name).parameters:
            if p.nonnegative:
                out.append(ParameterPrior(p.name, "uniform", 1.5 * p.scale, 1.5 * p.scale))
            else:
                out.append(ParameterPrior(p.name, "normal", 0.0, p.scale))
    return tuple(out)
