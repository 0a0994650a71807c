"""The population model: its coordinates, member and outlier densities, and hyperprior.

Coordinates ``x`` (MODULE_PARAMETERS order), scaled by the datasheet
conversions ``R, S, K``::

    x = (log(R0/R), R1/R, log(S0/S), S1/S, log(K/K))

Levels vary by a few percent from unit to unit, so their log makes a spread a
relative sd; slopes can be near zero or of either sign, so they stay linear
[1/K].  The default interim prior is exactly Gaussian in ``x``.

Hyperparameter vector ``h`` (11,): ``(mu (5), log tau (5), logit f)`` in ``x``
units; members are ``x_j ~ N(mu_j, tau_j^2)``; each parameter is, with
probability ``eps = 1 - (1 - f)^(1/5)``, from an outlier component instead:
``N(mu_j, (lambda tau_j)^2)`` (weight ``1 - GROSS_SHARE``) or the interim
prior's marginal (weight ``GROSS_SHARE``, a broken unit).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import special

from tembayes.calibrate.priors import SLOPE_REL_SD, law_priors
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import ModelError

#: Number of module parameters.
N_PARAMS = len(MODULE_PARAMETERS)
#: Number of hyperparameters: centres, log spreads, logit outlier fraction.
N_HYPER = 2 * N_PARAMS + 1
#: Which parameters are levels (log coordinate) rather than slopes.
LEVEL = np.array([True, False, True, False, True])
#: Width of the moderate outlier component relative to the unit-to-unit spread.
OUTLIER_SCALE = 6.0
#: Share of the outlier probability given to the gross ("broken unit") component.
GROSS_SHARE = 0.2
#: Beta(a, b) prior of the module-level outlier fraction.
OUTLIER_FRACTION_PRIOR = (1.0, 9.0)
#: Typical unit-to-unit spread of a level: relative sd [-].
SPREAD_LEVEL_TYPICAL = 0.02
#: Typical unit-to-unit spread of a slope, relative to the datasheet level [1/K].
SPREAD_SLOPE_TYPICAL = 0.02 * SLOPE_REL_SD
#: Log-sd of the default spread hyperprior.
SPREAD_LOG_SD = 1.0
#: The sampler's box: centres and log spreads within this many prior sds (the
#: prior density there is < e^-72) ...
BOX_SDS = 12.0
#: ... and |logit f| below this.
LOGIT_F_MAX = 40.0

LOG_2PI = math.log(2.0 * math.pi)


def _short(name):
    return name.split("_")[0]


#: Hyperparameter names, in sampler order after conversion to SI: centres
#: (levels: population median), spreads (levels: relative sd [-], slopes: SI
#: sd), the module-level outlier fraction.
HYPER_NAMES = (
    tuple(f"mu_{p}" for p in MODULE_PARAMETERS)
    + tuple(f"tau_{_short(p)}_rel" if lev else f"tau_{p}" for p, lev in zip(MODULE_PARAMETERS, LEVEL))
    + ("outlier_fraction",)
)
#: The spreads' names in :data:`HYPER_NAMES`.
TAU_NAMES = HYPER_NAMES[N_PARAMS : 2 * N_PARAMS]


def spread_key(parameter):
    """A module parameter's ``[population]`` spread key: ``S0_V_per_K`` -> ``spread_S0_rel``."""
    return "spread" + TAU_NAMES[MODULE_PARAMETERS.index(parameter)][3:]


class Coordinates:
    """SI parameters <-> population coordinates ``x`` (module docstring).

    Parameters
    ----------
    datasheet : tembayes.data.Datasheet
        Its ``R`` [ohm], ``S`` [V/K] and ``K`` [W/K] scale the coordinates.
    """

    def __init__(self, datasheet):
        R, S, K = datasheet.resistance(), datasheet.seebeck(), datasheet.conductance()
        self.ref = np.array([R, R, S, S, K], dtype=float)

    def to_x(self, theta):
        """SI parameters ``(..., 5)`` -> ``x``."""
        theta = np.asarray(theta, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(LEVEL, np.log(np.where(LEVEL, theta, 1.0) / self.ref), theta / self.ref)

    def to_theta(self, x):
        """``x (..., 5)`` -> SI parameters."""
        x = np.asarray(x, dtype=float)
        return np.where(LEVEL, self.ref * np.exp(np.where(LEVEL, x, 0.0)), self.ref * x)

    def log_jacobian(self, theta):
        """``log |d theta / d x|`` per row of ``theta`` (n, 5)."""
        theta = np.asarray(theta, dtype=float)
        return np.log(theta[:, LEVEL]).sum(axis=1) + np.log(self.ref[~LEVEL]).sum()

    def tau_to_x(self, name, value):
        """A spread in :attr:`PopulationResult.hyper` units -> ``x`` units."""
        j = TAU_NAMES.index(name)
        return value if LEVEL[j] else value / self.ref[j]


def _spread_spec(name, spec):
    """``(median, log_sd)`` of one ``spread_prior`` entry, checked."""
    if name not in TAU_NAMES:
        raise ModelError(f"spread_prior: unknown spread '{name}'; expected one of {TAU_NAMES}")
    try:
        median, log_sd = (float(v) for v in spec)
    except (TypeError, ValueError):
        raise ModelError(f"spread_prior['{name}'] must be (median, log_sd), got {spec!r}") from None
    if not (median > 0 and log_sd > 0 and np.isfinite(median) and np.isfinite(log_sd)):
        raise ModelError(f"spread_prior['{name}'] needs median > 0 and log_sd > 0, got {spec!r}")
    return median, log_sd


class Population:
    """Hyperprior and population density, shared by the two-stage and joint fits.

    Parameters
    ----------
    datasheet : tembayes.data.Datasheet
        Sets the coordinates and the hyperprior scales.
    spread_prior : dict, optional
        Spread name (:data:`TAU_NAMES`) -> ``(median, log_sd)`` of a
        log-normal prior, median in :attr:`PopulationResult.hyper` units.
    outlier_fraction_prior : (float, float)
        Beta(a, b) prior of the module-level outlier fraction.
    outlier_scale : float
        Width of the moderate outlier component in spreads (> 1).
    """

    ndim = N_HYPER

    def __init__(
        self,
        datasheet,
        *,
        spread_prior=None,
        outlier_fraction_prior=OUTLIER_FRACTION_PRIOR,
        outlier_scale=OUTLIER_SCALE,
    ):
        self.coords = Coordinates(datasheet)
        priors = law_priors(datasheet)
        self.mu_mean = self.coords.to_x(np.array([p.center for p in priors]))
        self.mu_mean = np.where(LEVEL, self.mu_mean, 0.0)  # slope priors are centred on zero
        self.mu_sd = np.array([p.scale if lev else p.scale / r for p, lev, r in zip(priors, LEVEL, self.coords.ref)])
        typical = np.where(LEVEL, SPREAD_LEVEL_TYPICAL, SPREAD_SLOPE_TYPICAL)
        self.logtau_mean = np.log(typical)
        self.logtau_sd = np.full(N_PARAMS, SPREAD_LOG_SD)
        for name, spec in (spread_prior or {}).items():
            median, log_sd = _spread_spec(name, spec)
            j = TAU_NAMES.index(name)
            self.logtau_mean[j] = np.log(self.coords.tau_to_x(name, median))
            self.logtau_sd[j] = log_sd
        a, b = (float(v) for v in outlier_fraction_prior)
        if not (a > 0 and b > 0):
            raise ModelError(f"outlier_fraction_prior must be Beta(a, b) with a, b > 0, got {outlier_fraction_prior!r}")
        self.beta = (a, b)
        if not outlier_scale > 1:
            raise ModelError(f"outlier_scale must be > 1, got {outlier_scale!r}")
        self.lam = float(outlier_scale)
        # the gross ("broken unit") component: the interim prior's marginals
        self.gross_mean = np.ascontiguousarray(self.mu_mean)
        self.gross_sd = np.ascontiguousarray(self.mu_sd)

    @staticmethod
    def component_log_weights(logeps, log1m):
        """Per-parameter log weights (W, 3) of member, moderate and gross components."""
        return np.ascontiguousarray(
            np.stack([log1m, logeps + math.log1p(-GROSS_SHARE), logeps + math.log(GROSS_SHARE)], axis=1)
        )

    def unpack(self, h):
        """``h`` (W, >=11) -> mu (W,5), tau (W,5), f, log eps, log(1-eps) (W,)."""
        mu = h[:, :N_PARAMS]
        with np.errstate(over="ignore", under="ignore"):
            tau = np.exp(h[:, N_PARAMS : 2 * N_PARAMS])
        f = special.expit(h[:, 2 * N_PARAMS])
        log1m = special.log_expit(-h[:, 2 * N_PARAMS]) / N_PARAMS  # log(1 - eps), eps = 1 - (1 - f)^(1/5)
        with np.errstate(divide="ignore"):
            logeps = np.log(-np.expm1(log1m))
        return mu, tau, f, logeps, log1m

    def log_prior(self, h):
        """Log hyperprior density of natural hyperparameters ``h`` (W, 11) -> (W,); -inf outside the box."""
        mu, logtau, lf = h[:, :N_PARAMS], h[:, N_PARAMS : 2 * N_PARAMS], h[:, 2 * N_PARAMS]
        lp = -0.5 * (((mu - self.mu_mean) / self.mu_sd) ** 2).sum(axis=1)
        lp -= 0.5 * (((logtau - self.logtau_mean) / self.logtau_sd) ** 2).sum(axis=1)
        a, b = self.beta
        # Beta(a, b) on f, in logit coordinates: f^a (1-f)^b
        lp += a * special.log_expit(lf) + b * special.log_expit(-lf)
        bad = (np.abs(logtau - self.logtau_mean) > BOX_SDS * self.logtau_sd).any(axis=1) | (np.abs(lf) > LOGIT_F_MAX)
        bad |= (np.abs(mu - self.mu_mean) > BOX_SDS * self.mu_sd).any(axis=1)
        bad |= ~np.isfinite(h[:, : self.ndim]).all(axis=1)
        return np.where(bad, -np.inf, lp)

    def log_density(self, x, mu, tau, logeps, log1m):
        """Population log density of module coordinates and of membership.

        Parameters
        ----------
        x : ndarray (W, N, 5)
        mu, tau : ndarray (W, 5)
        logeps, log1m : ndarray (W,)

        Returns
        -------
        log_mix, log_member : ndarray (W, N)
            ``log p(x | alpha)`` and ``log P(member in all parameters | x, alpha)``.
        """
        lw = self.component_log_weights(logeps, log1m)[:, None, None, :]
        z = (x - mu[:, None, :]) / tau[:, None, :]
        lt = np.log(tau)[:, None, :]
        zg = (x - self.gross_mean) / self.gross_sd
        a = lw[..., 0] - 0.5 * z * z - lt - 0.5 * LOG_2PI
        b = lw[..., 1] - 0.5 * (z / self.lam) ** 2 - lt - math.log(self.lam) - 0.5 * LOG_2PI
        g = lw[..., 2] - 0.5 * zg * zg - np.log(self.gross_sd) - 0.5 * LOG_2PI
        mix = np.logaddexp(np.logaddexp(a, b), g)
        return mix.sum(axis=2), (a - mix).sum(axis=2)

    def to_si(self, h):
        """Natural hyperparameters (..., 11) -> dict :data:`HYPER_NAMES` -> SI values."""
        ref = self.coords.ref
        out = {}
        for j, name in enumerate(HYPER_NAMES[:N_PARAMS]):
            out[name] = ref[j] * (np.exp(h[..., j]) if LEVEL[j] else h[..., j])
        for j, name in enumerate(TAU_NAMES):
            t = np.exp(h[..., N_PARAMS + j])
            out[name] = t if LEVEL[j] else ref[j] * t
        out["outlier_fraction"] = special.expit(h[..., 2 * N_PARAMS])
        return out
