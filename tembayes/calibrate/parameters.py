"""The sampled parameters of a module calibration and their coordinates.

The sampler works in unconstrained-ish coordinates ``x``: the log of every
positive parameter (R0, S0, K and the rig's conductances and capacitances),
the logit of a share, the reciprocal of a conductance sampled as a resistance,
the slopes and the step shift as they are.  :class:`ParameterSpace` maps a
batch of coordinate vectors ``X`` of shape ``(nw, p)`` to the parameter
mapping the models take and gives the prior's log density (Jacobian
included, so a posterior over ``x`` is the posterior over the parameters).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING

import numpy as np

from tembayes.calibrate.priors import ParameterPrior

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence


@dataclass(frozen=True)
class ParameterSpace:
    """Sampled parameters, their priors and the fixed rest.

    Attributes
    ----------
    priors : tuple of ParameterPrior
        One per coordinate, in coordinate order.
    fixed : dict
        Model parameters held at a value (SI), e.g. the rig's steel.
    """

    priors: tuple
    fixed: dict = field(default_factory=dict)

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the sampled parameters, in coordinate order."""
        return tuple(p.name for p in self.priors)

    @property
    def ndim(self) -> int:
        """Number of sampled coordinates."""
        return len(self.priors)

    def index(self, name: str) -> int:
        """Coordinate index of the parameter ``name``."""
        return self.names.index(name)

    def to_x(self, values: Mapping[str, float]) -> np.ndarray:
        """Coordinate vector of a mapping ``name -> value`` (SI)."""
        return np.array([p.to_unconstrained(values[p.name]) for p in self.priors], dtype=float)

    def values(self, X: np.ndarray) -> dict[str, np.ndarray]:
        """``name -> ndarray (nw,)`` of every coordinate, in SI."""
        X = np.atleast_2d(X)
        return {p.name: p.from_unconstrained(X[:, j]) for j, p in enumerate(self.priors)}

    def params(self, X: np.ndarray, names: Sequence[str] | None = None) -> dict:
        """Model parameter mapping for coordinate vectors ``X`` ``(nw, p)``.

        ``names`` restricts the sampled parameters passed on (e.g. to leave
        out noise parameters); the fixed ones are always included.
        """
        vals = self.values(X)
        if names is not None:
            vals = {k: v for k, v in vals.items() if k in names}
        return {**self.fixed, **vals}

    @cached_property
    def _prior_arrays(self):
        kinds = np.array([p.kind for p in self.priors])
        gauss = np.isin(kinds, ("normal", "lognormal", "logitnormal"))
        recip = kinds == "reciprocal"
        centre = np.array([p.coordinate_center for p in self.priors])
        return gauss, recip, centre, np.array([p.scale for p in self.priors])

    def log_prior(self, X: np.ndarray) -> np.ndarray:
        """Log prior density of coordinate vectors ``(nw, p)`` -> ``(nw,)``."""
        X = np.atleast_2d(X)
        gauss, recip, centre, scale = self._prior_arrays
        z = (X[:, gauss] - centre[gauss]) / scale[gauss]
        out = (-0.5 * z * z).sum(axis=1) - np.sum(np.log(scale[gauss]) + 0.5 * np.log(2.0 * np.pi))
        if np.any(recip):
            # a log-normal conductance sampled as its resistance u: log-normal in u
            u = X[:, recip]
            positive = np.all(u > 0, axis=1)
            with np.errstate(divide="ignore", invalid="ignore"):
                lu = np.log(np.where(u > 0, u, 1.0))
            z = (lu - np.log(centre[recip])) / scale[recip]
            r = (-0.5 * z * z - lu).sum(axis=1) - np.sum(np.log(scale[recip]) + 0.5 * np.log(2.0 * np.pi))
            out = np.where(positive, out + r, -np.inf)
        uni = ~(gauss | recip)
        if np.any(uni):
            inside = np.all(np.abs(X[:, uni] - centre[uni]) < scale[uni], axis=1)
            out = np.where(inside, out - np.sum(np.log(2.0 * scale[uni])), -np.inf)
        return out

    def clip(self, X: np.ndarray) -> np.ndarray:
        """Pull coordinates inside their bounds: a uniform's interval, a resistance above its floor (8 prior sds)."""
        X = np.array(X, dtype=float)
        for j, p in enumerate(self.priors):
            if p.kind == "uniform":
                lim = p.scale * (1 - 1e-9)
                X[..., j] = np.clip(X[..., j], p.center - lim, p.center + lim)
            elif p.kind == "reciprocal":
                X[..., j] = np.maximum(X[..., j], p.coordinate_floor)
        return X

    def sample_prior(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, p)`` coordinate draws from the prior."""
        return np.column_stack([p.to_unconstrained(p.sample(rng, n)) for p in self.priors])

    def with_prior(self, prior: ParameterPrior) -> ParameterSpace:
        """A copy with one coordinate's prior replaced (same name)."""
        return ParameterSpace(tuple(prior if p.name == prior.name else p for p in self.priors), dict(self.fixed))
