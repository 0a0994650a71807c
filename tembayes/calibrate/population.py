"""The batch (population) stage: what the modules of one type have in common.

Each module of a batch has been calibrated on its own (emcee) under a broad
*interim prior* (:func:`tembayes.calibrate.priors.law_log_prior`).  This stage
reuses those posterior draws -- population inference as in Hogg, Myers & Bovy
(2010, ApJ 725, 2166) and Foreman-Mackey, Hogg & Morton (2014, ApJ 795, 64):
the interim prior is divided out with importance weights, so module ``i``
contributes the marginal likelihood

    L_i(alpha) = E_{theta ~ posterior_i} [ p(theta | alpha) / pi_interim(theta) ]
                 / E_{theta ~ posterior_i} [ 1 / pi_interim(theta) ]

of the hyperparameters ``alpha``, which emcee samples.

Coordinates
-----------
The population lives in ``x`` (MODULE_PARAMETERS order), scaled by the
datasheet conversions ``R, S, K`` (:class:`tembayes.data.Datasheet`):

    x = (log(R0/R), R1/R, log(S0/S), S1/S, log(K/K))

Levels are positive and vary by a few percent from unit to unit, so a log
coordinate makes their spread a relative sd.  Slopes can be near zero or of
either sign, so they stay linear, divided by the datasheet level [1/K] (the
scale of the interim prior).  The default interim prior is exactly Gaussian in
``x``.

Population model
----------------
* **Members**: ``x_j ~ N(mu_j, tau_j^2)`` independently for j = 1..5, with
  unknown centres ``mu`` and unit-to-unit spreads ``tau``.  A diagonal
  population because a batch of 3-10 modules cannot identify 10 correlations;
  the predictive marginals are right, cross-parameter correlations between
  units (e.g. through leg geometry) are not modelled.
* **Outliers, per parameter**: each parameter of each module is, with
  probability ``eps``, not from the member distribution but from an outlier
  component; a module is an outlier if any of its parameters is.  Why per
  parameter: a module-level outlier component that is broad in all five
  parameters pays for the four parameters that *are* in the population and
  fails to flag a unit off in one only (a back-of-envelope estimate,
  confirmed by simulation).  The outlier component of parameter j is

  - with weight 1 - :data:`GROSS_SHARE` (0.8), "off by several spreads":
    ``N(mu_j, (lambda tau_j)^2)``, ``lambda`` = :data:`OUTLIER_SCALE` = 6
    (half its mass within 4 spreads, 90 % within 10).  In simulated batches a
    component of this kind flagged 3-5 spread deviations better than the
    broad interim prior (whose density is 10-90 spreads wide), and a larger
    ``lambda`` (4 -> 6 -> 8) lowered the members' outlier_prob at little
    cost for the outliers;
  - with weight :data:`GROSS_SHARE`, "a broken unit": the interim prior's
    marginal of that parameter (log-sd 0.3 around the datasheet for the
    levels).  Without it a gross outlier (tens of spreads) would be explained
    by the ``lambda`` component only by inflating ``tau`` (for 8 modules and
    a 30-spread outlier, x2 at lambda = 6); with it, it does not touch the
    spreads.

* **Outlier fraction** ``f`` (module level) ``~ Beta(1, 9)``
  (:data:`OUTLIER_FRACTION_PRIOR`, mean 10 %), and
  ``eps = 1 - (1 - f)^(1/5)`` so that ``f`` is the prior probability that a
  module is off in at least one parameter.

Hyperpriors (weakly informative, scaled by the datasheet, no module-type
numbers):

* ``mu_j``: the interim prior's own marginals
  (:func:`~tembayes.calibrate.priors.law_priors`: log-sd 0.3 on the levels,
  sd ``SLOPE_REL_SD`` on the slopes).
* ``tau_j``: log-normal with log-sd 1 (a factor 2.7) around a typical
  manufacturing spread: 2 % for the levels, ``0.02 * SLOPE_REL_SD`` [1/K] for
  the slopes (a few % of a temperature coefficient of up to ~1 %/K).  An
  informative prior, e.g. the spreads learned from an earlier batch of the same
  type (:meth:`PopulationResult.spread_prior`), can be passed as
  ``spread_prior``.

What a batch can say
--------------------
``outlier_prob`` is a posterior probability under this model, so it is only
as sharp as the evidence.  A unit 4 spreads off in one parameter is not, on
its own, strong evidence against "the spread is larger than typical" when the
spread has to be learned from the same few units, and the model does not know
by how much an outlier is off.  Measured on the study of
``analyses/population_checks.py`` (200 batches of 3 and 8 modules, half with
an outlier 3-5 spreads off, or S0 +-4 %):

* default priors: the study's targets are not met for 3 modules (no outlier
  gets > 0.5; from three units alone the spreads are the prior's) and met for
  a minority of 8-module batches; batches without an outlier rarely flag
  anybody (> 0.3 in 0 % of 3-module and ~8 % of 8-module batches);
* with the spreads known from an earlier batch of the type
  (``spread_prior=earlier.spread_prior(widen=1.5)``) the outlier is ranked
  top in 72-92 % of batches, and clear deviations (~10 spreads, tests) meet
  the targets;
* the Bayes-optimal classifier that knows the true population *and* the
  outlier mechanism meets them in 64-100 % of batches -- the ceiling for any
  method on that design.

With two modules the spreads are essentially the hyperprior's and the two
units are exchangeable: each gets about the same ``outlier_prob`` (low unless
they differ grossly), and the predictive is wide.

Importance sums vs Gaussian approximation: where a parameter's population
spread is smaller than a module's posterior sd (typically S1), few posterior
draws fall where the population density is, and the importance weights of a
few hundred thinned draws have an effective sample size of only ~5-40
(``diagnostics["weight_ess"]``): importance sums are noisy there, while the
Gaussian approximation of the (near-Gaussian) module posteriors is exact in
that limit.  Hence the default below.

Computation
-----------
* ``method="gaussian"``: each module's likelihood is approximated by a
  Gaussian in ``x`` (moments of the draws weighted by ``1 / pi_interim``).
  The integral over the module's parameters is then closed-form for each of
  the 3^5 member/moderate/gross patterns, with the full 5x5 covariance.  The
  sum over patterns (compiled) starts from the member pattern; "parameter j
  off" is a rank-one update of its precision matrix, so each ratio is exact.
  The parameter that looks most off is summed over exactly, recursively, until
  every remaining ratio is below e^-3; those enter as ``prod (1 + rho)``,
  exact for uncorrelated module posteriors.  Checked against all 243
  patterns: < 1e-3 nat per module (tests).  About 1 us per module and walker,
  so it scales to hundreds of modules.
* ``method="importance"``: the importance sums over (evenly thinned) draws;
  consistent for any posterior shape, cost proportional to modules x draws
  (8 modules x 256 draws: ~10x the Gaussian method).
* ``method="auto"`` (default): Gaussian, then checked against the importance
  sums at hyperparameter draws; if they disagree (log-likelihood differences
  that would reweight the hyper draws to < 80 % effective sample size, or any
  ``outlier_prob`` differing by more than 0.03 plus three Monte Carlo
  standard errors of the sums; modules whose sums have a weight ESS < 50 at
  a hyper draw are left out there, see above) the run is repeated with
  importance sums (warned).

Outputs
-------
``outlier_prob[i]`` is Rao-Blackwellised: ``1 - mean`` over hyper draws of
``P(module i a member in all five parameters | its data, alpha)``, which the
likelihood terms give in closed form (importance sums for that method), with
a Monte Carlo se from the arviz ESS of those per-draw values.  The
predictive describes a new module of the type that is a *member*:
``x ~ N(mu, tau^2)`` per hyper draw, back in SI (``predictive``, what
``summary()`` reports as the contract's ``population``); a new unit drawn from
the whole mixture, outliers included, is ``predictive_with_outliers``.

Sampling: emcee with differential-evolution moves (the posterior of a small
batch can be bimodal: "tight spread plus one outlier" vs "wider spread"),
``vectorize=True``, seeded from the caller's ``numpy.random.Generator``, run
until >= 50 autocorrelation times after a burn-in of a quarter of the run,
split R-hat <= 1.01 and bulk ESS >= 1000 (arviz, walkers as chains) for every
hyperparameter, within ``max_steps`` / ``max_seconds``; otherwise
``converged`` is False and a :class:`PopulationConvergenceWarning` is issued.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import emcee
import numpy as np
import numba
from numba import njit, prange
from scipy import optimize, special

from tembayes.calibrate.priors import SLOPE_REL_SD, law_log_prior, law_priors
from tembayes.constants import MODULE_PARAMETERS
from tembayes.errors import ModelError

#: Number of module parameters.
N_PARAMS = len(MODULE_PARAMETERS)
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
#: A module needs at least this many posterior draws.
MIN_DRAWS = 20
#: Convergence: run length in autocorrelation times, R-hat, bulk ESS.
TAU_FACTOR, RHAT_MAX, ESS_MIN = 50.0, 1.01, 1000.0
#: The "auto" check: minimum ESS fraction of reweighting the hyper draws from
#: the Gaussian to the importance likelihood, maximum outlier_prob difference.
CHECK_ESS_FRACTION, CHECK_OUTLIER_DIFF = 0.8, 0.03
#: ... using only modules whose importance sums have at least this weight ESS.
CHECK_MIN_ESS = 50.0
#: Importance sums in the sampler use at most this many draws over all modules.
IMPORTANCE_BUDGET = 20000

_LOG2PI = math.log(2.0 * math.pi)
#: Module x walker evaluations below which the compiled terms run on one
#: thread (on the 2-vCPU development machine threads did not pay off even for
#: 500 modules x 16 walkers).
PARALLEL_MIN = 65536


class PopulationConvergenceWarning(UserWarning):
    """The population sampler ran out of budget before converging."""


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
_TAU_NAMES = HYPER_NAMES[N_PARAMS:2 * N_PARAMS]


# --------------------------------------------------------------------------- result


@dataclass(frozen=True)
class PopulationResult:
    """The batch-level posterior.

    Attributes
    ----------
    module_ids : tuple of str
        Modules in input order.
    outlier_prob : dict
        Module id -> posterior probability that the module does not belong to
        the population (off in at least one parameter), averaged over the
        hyperparameter draws.
    predictive : ndarray, shape (n, 5)
        Draws of the parameters of a new module of the type that is a
        *member* (outlier component excluded), SI, MODULE_PARAMETERS order.
    predictive_with_outliers : ndarray, shape (n, 5)
        The same including the outlier component (a new unit may be off).
    hyper : dict
        :data:`HYPER_NAMES` -> ndarray (nwalkers, ndraws) after burn-in:
        ``mu_<param>`` [SI; population median for R0, S0, K], ``tau_R0_rel``,
        ``tau_S0_rel``, ``tau_K_rel`` [-] (relative sd), ``tau_R1_ohm_per_K``
        [ohm/K], ``tau_S1_V_per_K2`` [V/K^2], ``outlier_fraction`` [-].
    diagnostics : dict
        ``converged``, ``rhat_max``, ``ess_bulk_min``, ``tau_max`` [steps],
        ``n_steps``, ``n_burn``, ``nwalkers``, ``acceptance_min``,
        ``weight_ess`` (module -> importance-weight ESS at the posterior-median
        hyperparameters), ``weight_ess_min``, ``interim_weight_ess_min``,
        ``outlier_prob_mcse`` (module -> Monte Carlo se), ``method``,
        ``check`` (Gaussian vs importance, if run), ``emcee_seed`` (the
        RandomState seed drawn from the caller's Generator), ``versions``,
        ``targets`` (the convergence targets used), ``elapsed_s``.
    """

    module_ids: tuple
    outlier_prob: dict
    predictive: np.ndarray
    hyper: dict
    diagnostics: dict
    predictive_with_outliers: np.ndarray = None

    def summary(self) -> dict:
        """Mean, sd, 5 % and 95 % quantiles of :attr:`predictive` (SI).

        Returns
        -------
        dict
            Contract parameter name -> ``{"mean", "sd", "q05", "q95"}``.
        """
        out = {}
        for j, name in enumerate(MODULE_PARAMETERS):
            v = self.predictive[:, j]
            q05, q95 = np.quantile(v, [0.05, 0.95])
            out[name] = {"mean": float(v.mean()), "sd": float(v.std(ddof=1)),
                         "q05": float(q05), "q95": float(q95)}
        return out

    def spread_prior(self, widen=1.0) -> dict:
        """The spreads learned here as a prior for another batch of the type.

        Parameters
        ----------
        widen : float
            Factor on the log-sd (>= 1 to allow for batch-to-batch change).

        Returns
        -------
        dict
            Spread name (``tau_...``, see :attr:`hyper`) -> ``(median, log_sd)``,
            the format of ``fit_population(spread_prior=...)``.
        """
        out = {}
        for k in _TAU_NAMES:
            lv = np.log(self.hyper[k].ravel())
            out[k] = (float(np.exp(np.median(lv))), float(widen * lv.std(ddof=1)))
        return out


# --------------------------------------------------------------------------- coordinates and model


class _Coordinates:
    """SI parameters <-> population coordinates ``x`` (see module docstring)."""

    def __init__(self, datasheet):
        R, S, K = datasheet.resistance(), datasheet.seebeck(), datasheet.conductance()
        self.ref = np.array([R, R, S, S, K], dtype=float)

    def to_x(self, theta):
        theta = np.asarray(theta, dtype=float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(LEVEL, np.log(np.where(LEVEL, theta, 1.0) / self.ref), theta / self.ref)

    def to_theta(self, x):
        x = np.asarray(x, dtype=float)
        return np.where(LEVEL, self.ref * np.exp(np.where(LEVEL, x, 0.0)), self.ref * x)

    def log_jacobian(self, theta):
        """``log |d theta / d x|`` per row of ``theta`` (n, 5)."""
        theta = np.asarray(theta, dtype=float)
        return np.log(theta[:, LEVEL]).sum(axis=1) + np.log(self.ref[~LEVEL]).sum()

    def tau_to_x(self, name, value):
        """A spread in :attr:`PopulationResult.hyper` units -> ``x`` units."""
        j = _TAU_NAMES.index(name)
        return value if LEVEL[j] else value / self.ref[j]


class _Population:
    """Hyperprior and population density, shared by the two-stage and joint fits.

    The sampler's hyperparameter vector ``h`` (11,) is
    ``(mu (5, x units), log tau (5, x units), logit f)``.
    """

    ndim = 2 * N_PARAMS + 1

    def __init__(self, datasheet, *, spread_prior=None, outlier_fraction_prior=OUTLIER_FRACTION_PRIOR,
                 outlier_scale=OUTLIER_SCALE):
        self.coords = _Coordinates(datasheet)
        priors = law_priors(datasheet)
        self.mu_mean = self.coords.to_x(np.array([p.center for p in priors]))
        self.mu_mean = np.where(LEVEL, self.mu_mean, 0.0)  # slope priors are centred on zero
        self.mu_sd = np.array([p.scale if lev else p.scale / r for p, lev, r in zip(priors, LEVEL, self.coords.ref)])
        typical = np.where(LEVEL, SPREAD_LEVEL_TYPICAL, SPREAD_SLOPE_TYPICAL)
        self.logtau_mean = np.log(typical)
        self.logtau_sd = np.full(N_PARAMS, SPREAD_LOG_SD)
        for name, spec in (spread_prior or {}).items():
            if name not in _TAU_NAMES:
                raise ModelError(f"spread_prior: unknown spread '{name}'; expected one of {_TAU_NAMES}")
            try:
                median, log_sd = (float(v) for v in spec)
            except (TypeError, ValueError):
                raise ModelError(f"spread_prior['{name}'] must be (median, log_sd), got {spec!r}") from None
            if not (median > 0 and log_sd > 0 and np.isfinite(median) and np.isfinite(log_sd)):
                raise ModelError(f"spread_prior['{name}'] needs median > 0 and log_sd > 0, got {spec!r}")
            j = _TAU_NAMES.index(name)
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
        return np.ascontiguousarray(np.stack([log1m, logeps + math.log1p(-GROSS_SHARE),
                                              logeps + math.log(GROSS_SHARE)], axis=1))

    def unpack(self, h):
        """``h`` (W, >=11) -> mu (W,5), tau (W,5), f, log eps, log(1-eps) (W,)."""
        mu = h[:, :N_PARAMS]
        with np.errstate(over="ignore", under="ignore"):
            tau = np.exp(h[:, N_PARAMS:2 * N_PARAMS])
        f = special.expit(h[:, 2 * N_PARAMS])
        log1m = special.log_expit(-h[:, 2 * N_PARAMS]) / N_PARAMS  # log(1 - eps), eps = 1 - (1 - f)^(1/5)
        with np.errstate(divide="ignore"):
            logeps = np.log(-np.expm1(log1m))
        return mu, tau, f, logeps, log1m

    def log_prior(self, h):
        """Log hyperprior density in the sampler's coordinates (W,)."""
        mu, logtau, lf = h[:, :N_PARAMS], h[:, N_PARAMS:2 * N_PARAMS], h[:, 2 * N_PARAMS]
        lp = -0.5 * (((mu - self.mu_mean) / self.mu_sd) ** 2).sum(axis=1)
        lp -= 0.5 * (((logtau - self.logtau_mean) / self.logtau_sd) ** 2).sum(axis=1)
        a, b = self.beta
        # Beta(a, b) on f, in logit coordinates: f^a (1-f)^b
        lp += a * special.log_expit(lf) + b * special.log_expit(-lf)
        # keep the sampler in a numerically safe box (the prior density there is < e^-72)
        bad = (np.abs(logtau - self.logtau_mean) > 12 * self.logtau_sd).any(axis=1) | (np.abs(lf) > 40)
        bad |= (np.abs(mu - self.mu_mean) > 12 * self.mu_sd).any(axis=1)
        bad |= ~np.isfinite(h[:, :self.ndim]).all(axis=1)
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
        a = lw[..., 0] - 0.5 * z * z - lt - 0.5 * _LOG2PI
        b = lw[..., 1] - 0.5 * (z / self.lam) ** 2 - lt - math.log(self.lam) - 0.5 * _LOG2PI
        g = lw[..., 2] - 0.5 * zg * zg - np.log(self.gross_sd) - 0.5 * _LOG2PI
        mix = np.logaddexp(np.logaddexp(a, b), g)
        return mix.sum(axis=2), (a - mix).sum(axis=2)

    def to_si(self, h):
        """Sampler coordinates (..., 11) -> dict of SI hyperparameters."""
        ref = self.coords.ref
        out = {}
        for j, name in enumerate(HYPER_NAMES[:N_PARAMS]):
            out[name] = ref[j] * (np.exp(h[..., j]) if LEVEL[j] else h[..., j])
        for j, name in enumerate(_TAU_NAMES):
            t = np.exp(h[..., N_PARAMS + j])
            out[name] = t if LEVEL[j] else ref[j] * t
        out["outlier_fraction"] = special.expit(h[..., 2 * N_PARAMS])
        return out


# --------------------------------------------------------------------------- compiled likelihood terms


@njit(cache=True)
def _logaddexp(a, b):
    if a == -np.inf:
        return b
    if a > b:
        return a + math.log1p(math.exp(b - a))
    return b + math.log1p(math.exp(a - b))


#: Below this ratio (e^-3) a parameter's off patterns enter the Gaussian terms
#: in product form instead of being summed over exactly (error ~ rho^2).
_RHO_EXACT = math.exp(-3.0)


@njit(cache=True)
def _rho_parts(pkk, uk, d, c, lwdiff):
    """Ratio of "parameter k off" to the base pattern: rho = exp(a) / sqrt(g).

    The off component changes A_kk by ``d`` and the mean of x_k by ``c``
    (a rank-one update); with P = A^-1 and u = P r of the base pattern
    (``pkk = P_kk``, ``uk = u_k``): g = 1 + d P_kk and
    a = lwdiff - (-2 c u_k + c^2 P_kk - d (u_k - c P_kk)^2 / g) / 2.
    Returns (a, g); g <= 0 (impossible for a positive definite update) gives
    a = -inf.
    """
    g = 1.0 + d * pkk
    if not g > 0.0:
        return -np.inf, 1.0
    e = uk - c * pkk
    return lwdiff - 0.5 * (-2.0 * c * uk + c * c * pkk - d * e * e / g), g


@njit(cache=True)
def _pattern_sum(ll0, lw, w, dm, dg, cg, Pst, ust, lr1, lr2, f_mask, f_base, f_kstar, f_state, f_total):
    """Log of the sum over all member/moderate/gross patterns of one module.

    Frame 0 holds the member pattern: log density ``ll0``, precision matrix
    ``Pst[0]`` and precision times residual ``ust[0]``.  In each frame the
    parameter that looks most off (largest ratio, :func:`_rho_parts`) is summed
    over exactly -- member, moderate, gross; child frames by rank-one
    updates of P and u -- until every remaining parameter's ratio is below
    ``_RHO_EXACT``; those enter in product form, ``prod (1 + rho)``.  A
    module off in one parameter costs one level, one off everywhere all 3^5
    patterns.  A depth-first walk with an explicit stack (numba cannot cache
    recursive functions, numba#6061).
    """
    D = Pst.shape[1]
    f_mask[0] = 0
    f_base[0] = ll0
    L = 0
    entering = True
    while True:
        if entering:
            entering = False
            # ratios in linear space (two exp and two sqrt per parameter: the hot
            # path); an exponent that could overflow counts as infinitely off
            best = -1.0
            kstar = -1
            for k in range(D):
                if (f_mask[L] >> k) & 1:
                    continue
                a1, g1 = _rho_parts(Pst[L, k, k], ust[L, k], dm[k], 0.0, lw[w, 1] - lw[w, 0])
                a2, g2 = _rho_parts(Pst[L, k, k], ust[L, k], dg[k], cg[k], lw[w, 2] - lw[w, 0])
                if a1 < 500.0 and a2 < 500.0:
                    rho = math.exp(a1) / math.sqrt(g1) + math.exp(a2) / math.sqrt(g2)
                else:
                    rho = np.inf
                lr1[L, k] = rho
                if rho > best:
                    best = rho
                    kstar = k
            if kstar < 0 or best < _RHO_EXACT:
                prod = 1.0
                for k in range(D):
                    if not (f_mask[L] >> k) & 1:
                        prod *= 1.0 + lr1[L, k]
                result = f_base[L] + math.log(prod)
                if L == 0:
                    return result
                L -= 1
                f_total[L] = _logaddexp(f_total[L], result)
                continue
            # k* is summed over exactly: its two log ratios (safe for huge exponents)
            a1, g1 = _rho_parts(Pst[L, kstar, kstar], ust[L, kstar], dm[kstar], 0.0, lw[w, 1] - lw[w, 0])
            a2, g2 = _rho_parts(Pst[L, kstar, kstar], ust[L, kstar], dg[kstar], cg[kstar], lw[w, 2] - lw[w, 0])
            lr1[L, kstar] = a1 - 0.5 * math.log(g1)
            lr2[L, kstar] = a2 - 0.5 * math.log(g2)
            f_kstar[L] = kstar
            f_state[L] = 0
            f_total[L] = -np.inf
        s = f_state[L]
        if s == 3:  # all three states of k* done
            result = f_total[L]
            if L == 0:
                return result
            L -= 1
            f_total[L] = _logaddexp(f_total[L], result)
            continue
        kstar = f_kstar[L]
        c1 = L + 1
        f_mask[c1] = f_mask[L] | (1 << kstar)
        if s == 0:  # k* a member: same P and u
            for a in range(D):
                ust[c1, a] = ust[L, a]
                for b in range(D):
                    Pst[c1, a, b] = Pst[L, a, b]
            f_base[c1] = f_base[L]
        else:  # k* off: A_k*k* changes by d, the mean of x_k* by c
            d = dm[kstar] if s == 1 else dg[kstar]
            c = 0.0 if s == 1 else cg[kstar]
            pkk = Pst[L, kstar, kstar]
            den = 1.0 + d * pkk
            f = (ust[L, kstar] - c * pkk) / den
            for a in range(D):
                va = Pst[L, a, kstar]
                ust[c1, a] = ust[L, a] - c * va - d * va * f
                for b in range(D):
                    Pst[c1, a, b] = Pst[L, a, b] - d * va * Pst[L, b, kstar] / den
            f_base[c1] = f_base[L] + (lr1[L, kstar] if s == 1 else lr2[L, kstar])
        f_state[L] = s + 1
        L = c1
        entering = True


@njit(cache=True)
def _gauss_one(m, C, i, mu, tau, w, lam, lw, gm, gs, L, r, y, dm, dg, cg, Pst, ust, lr1, lr2, fi, ff):
    """Marginal likelihood of module i at walker w for a Gaussian module likelihood N(m_i, C_i).

    Member pattern: N(m_i; mu, A), A = C_i + diag(tau^2).  "Parameter j off"
    changes A_jj (moderate: tau_j -> lam tau_j; gross: tau_j -> gs_j and mean
    mu_j -> gm_j), a rank-one update, so each pattern's ratio to its base is
    exact in closed form (:func:`_rho_parts`); :func:`_pattern_sum` sums them.
    ``lw`` (W, 3): per-parameter log weights of member, moderate, gross.

    Returns (log L_i, log P(member in all parameters | ...)).
    """
    D = m.shape[1]
    logdet = 0.0
    # Cholesky of A into L, forward solve r -> y
    for k in range(D):
        r[k] = m[i, k] - mu[w, k]
        for j in range(k):
            v = C[i, k, j]
            for l in range(j):
                v -= L[k, l] * L[j, l]
            L[k, j] = v / L[j, j]
        v = C[i, k, k] + tau[w, k] * tau[w, k]
        for l in range(k):
            v -= L[k, l] * L[k, l]
        if not v > 0.0:
            return -np.inf, 0.0
        L[k, k] = math.sqrt(v)
        logdet += math.log(L[k, k])
        a = r[k]
        for l in range(k):
            a -= L[k, l] * y[l]
        y[k] = a / L[k, k]
    quad = 0.0
    for k in range(D):
        quad += y[k] * y[k]
    # L <- L^-1 (lower triangular, in place), then P = L^-T L^-1 and u = P r into frame 0
    for j in range(D):
        L[j, j] = 1.0 / L[j, j]
        for k in range(j + 1, D):
            v = 0.0
            for l in range(j, k):
                v -= L[k, l] * L[l, j]
            L[k, j] = v / L[k, k]  # L[k, k] is still the original diagonal here
    for a in range(D):
        for b in range(a, D):
            v = 0.0
            for k in range(b, D):
                v += L[k, a] * L[k, b]
            Pst[0, a, b] = v
            Pst[0, b, a] = v
    for a in range(D):
        v = 0.0
        for b in range(D):
            v += Pst[0, a, b] * r[b]
        ust[0, a] = v
    ll0 = D * lw[w, 0] - 0.5 * quad - logdet - 0.5 * D * math.log(2.0 * math.pi)
    for k in range(D):
        t2 = tau[w, k] * tau[w, k]
        dm[k] = (lam * lam - 1.0) * t2  # moderate: variance change, same mean
        dg[k] = gs[k] * gs[k] - t2  # gross: variance and mean change
        cg[k] = gm[k] - mu[w, k]
    total = _pattern_sum(ll0, lw, w, dm, dg, cg, Pst, ust, lr1, lr2, fi[0], ff[0], fi[1], fi[2], ff[1])
    if not math.isfinite(total):
        return -np.inf, 0.0
    return total, ll0 - total


@njit(cache=True)
def _gauss_chunk(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, t0, t1):
    D = m.shape[1]
    N = out_ll.shape[1]
    L = np.zeros((D, D))
    r = np.empty(D)
    y = np.empty(D)
    dm = np.empty(D)
    dg = np.empty(D)
    cg = np.empty(D)
    Pst = np.empty((D + 1, D, D))  # per stack frame: precision matrix, precision x residual
    ust = np.empty((D + 1, D))
    lr1 = np.empty((D + 1, D))
    lr2 = np.empty((D + 1, D))
    fi = np.zeros((3, D + 1), dtype=np.int64)  # frame mask, k*, state
    ff = np.zeros((2, D + 1))  # frame base, running total
    for t in range(t0, t1):
        w = t // N
        i = t % N
        a, b = _gauss_one(m, C, i, mu, tau, w, lam, lw, gm, gs, L, r, y, dm, dg, cg, Pst, ust, lr1, lr2, fi, ff)
        out_ll[w, i] = a
        out_lmem[w, i] = b


@njit(cache=True)
def _gauss_terms_serial(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem):
    _gauss_chunk(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, 0, out_ll.size)


@njit(cache=True, parallel=True)
def _gauss_terms_parallel(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, n_chunks):
    T = out_ll.size
    for c in prange(n_chunks):
        _gauss_chunk(m, C, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, c * T // n_chunks, (c + 1) * T // n_chunks)


@njit(cache=True)
def _importance_chunk(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, t0, t1):
    """Importance sums over module draws (self-normalised weights exp(lw0)).

    out_ll[w, i] = log sum_m exp(lw0_m) p(x_m | alpha);
    out_lmem[w, i] = log of the member share of that sum.
    """
    N = out_ll.shape[1]
    D = x.shape[1]
    c0 = 0.5 * math.log(2.0 * math.pi)
    loglam = math.log(lam)
    logtau = np.empty(D)
    lgross = np.empty(D)
    for j in range(D):
        lgross[j] = -math.log(gs[j]) - c0
    for t in range(t0, t1):
        w = t // N
        i = t % N
        for j in range(D):
            logtau[j] = math.log(tau[w, j])
        # the three components' weights over their density's normalisation (linear space)
        k0 = math.exp(lw[w, 0] - c0)
        k1 = math.exp(lw[w, 1] - c0 - loglam)
        bm, am = -np.inf, 0.0  # streaming log-sum-exp: mixture
        bq, aq = -np.inf, 0.0  # member
        for k in range(start[i], start[i + 1]):
            smix = lw0[k]
            smem = lw0[k]
            for j in range(D):
                z = (x[k, j] - mu[w, j]) / tau[w, j]
                zg = (x[k, j] - gm[j]) / gs[j]
                a = lw[w, 0] - 0.5 * z * z - logtau[j] - c0
                smem += a
                if z * z < 1400.0 and zg * zg < 1400.0:  # no underflow: one log for the three terms
                    smix += math.log((k0 * math.exp(-0.5 * z * z) + k1 * math.exp(-0.5 * z * z / (lam * lam)))
                                     / tau[w, j] + math.exp(lw[w, 2] - 0.5 * zg * zg + lgross[j]))
                else:
                    zo = z / lam
                    b = lw[w, 1] - 0.5 * zo * zo - logtau[j] - loglam - c0
                    g = lw[w, 2] - 0.5 * zg * zg + lgross[j]
                    smix += _logaddexp(_logaddexp(a, b), g)
            if smix > bm:
                am = am * math.exp(bm - smix) + 1.0 if bm > -np.inf else 1.0
                bm = smix
            else:
                am += math.exp(smix - bm)
            if smem > bq:
                aq = aq * math.exp(bq - smem) + 1.0 if bq > -np.inf else 1.0
                bq = smem
            else:
                aq += math.exp(smem - bq)
        ll = bm + math.log(am)
        out_ll[w, i] = ll
        out_lmem[w, i] = bq + math.log(aq) - ll


@njit(cache=True)
def _importance_terms_serial(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem):
    _importance_chunk(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, 0, out_ll.size)


@njit(cache=True, parallel=True)
def _importance_terms_parallel(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem, n_chunks):
    T = out_ll.size
    for c in prange(n_chunks):
        _importance_chunk(x, lw0, start, mu, tau, lam, lw, gm, gs, out_ll, out_lmem,
                          c * T // n_chunks, (c + 1) * T // n_chunks)


class _GaussianTerms:
    """Module likelihoods as Gaussians in x: ``m`` (N, 5), ``C`` (N, 5, 5) (see :func:`_gauss_one`)."""

    name = "gaussian"

    def __init__(self, m, C):
        self.m = np.ascontiguousarray(m)
        self.C = np.ascontiguousarray(C)
        self.n = len(m)

    def __call__(self, pop, mu, tau, logeps, log1m):
        W = len(mu)
        ll = np.empty((W, self.n))
        lmem = np.empty((W, self.n))
        args = (self.m, self.C, np.ascontiguousarray(mu), np.ascontiguousarray(tau), pop.lam,
                pop.component_log_weights(logeps, log1m), pop.gross_mean, pop.gross_sd, ll, lmem)
        if ll.size < PARALLEL_MIN:  # thread start-up costs more than it saves
            _gauss_terms_serial(*args)
        else:
            _gauss_terms_parallel(*args, 4 * numba.get_num_threads())
        return ll, lmem


class _ImportanceTerms:
    """Importance sums over the (thinned) draws of each module."""

    name = "importance"

    def __init__(self, xs, lws):
        self.n = len(xs)
        self.x = np.ascontiguousarray(np.concatenate(xs))
        self.lw0 = np.ascontiguousarray(np.concatenate(lws))
        self.start = np.concatenate([[0], np.cumsum([len(v) for v in xs])]).astype(np.int64)
        self.draws_per_module = [len(v) for v in xs]

    def __call__(self, pop, mu, tau, logeps, log1m):
        W = len(mu)
        ll = np.empty((W, self.n))
        lmem = np.empty((W, self.n))
        args = (self.x, self.lw0, self.start, np.ascontiguousarray(mu), np.ascontiguousarray(tau), pop.lam,
                pop.component_log_weights(logeps, log1m), pop.gross_mean, pop.gross_sd, ll, lmem)
        if len(self.x) * W < 16 * PARALLEL_MIN:
            _importance_terms_serial(*args)
        else:
            _importance_terms_parallel(*args, 4 * numba.get_num_threads())
        return ll, lmem

    def weight_ess(self, pop, h):
        """Importance-weight ESS per module at one hyperparameter point ``h`` (11,)."""
        mu, tau, _, logeps, log1m = pop.unpack(h[None, :])
        out = []
        for i in range(self.n):
            sl = slice(self.start[i], self.start[i + 1])
            lmix, _ = pop.log_density(self.x[sl][None], mu, tau, logeps, log1m)
            lw = self.lw0[sl] + lmix[0]
            w = np.exp(lw - lw.max())
            out.append(float(w.sum() ** 2 / (w * w).sum()))
        return np.array(out)


@njit(cache=True)
def _log_expit(x):
    return -math.log1p(math.exp(-x)) if x > 0 else x - math.log1p(math.exp(x))


@njit(cache=True)
def _hyper_prep(u, mbar, cbar, sqrt_n, mu_mean, mu_sd, lt_mean, lt_sd, a, b):
    """Sampler coordinates -> population parameters and log prior + Jacobian (compiled).

    Same density as :meth:`_Population.log_prior` plus the log Jacobian of
    :class:`_HyperPosterior`'s reparameterisation; -inf outside the box
    (every hyperparameter within 12 prior sds, where the prior is > e^-72):
    far outside it the closed-form pattern ratios would lose all precision.
    """
    W = u.shape[0]
    D = mbar.shape[0]
    mu = np.empty((W, D))
    tau = np.empty((W, D))
    logeps = np.empty(W)
    log1m = np.empty(W)
    lp = np.empty(W)
    for w in range(W):
        lf = u[w, 2 * D]
        v = a * _log_expit(lf) + b * _log_expit(-lf)
        bad = not (abs(lf) <= 40.0)
        for j in range(D):
            lt = u[w, D + j]
            zt = (lt - lt_mean[j]) / lt_sd[j]
            if not (abs(zt) <= 12.0):
                bad = True
                break
            t = math.exp(lt)
            sc = math.sqrt(t * t + cbar[j]) / sqrt_n
            mu[w, j] = mbar[j] + sc * u[w, j]
            tau[w, j] = t
            zm = (mu[w, j] - mu_mean[j]) / mu_sd[j]
            if not (abs(zm) <= 12.0):
                bad = True
                break
            v += -0.5 * zm * zm - 0.5 * zt * zt + math.log(sc)
        if bad or not math.isfinite(v):
            lp[w] = -np.inf
            for j in range(D):
                mu[w, j] = mu_mean[j]
                tau[w, j] = math.exp(lt_mean[j])
            logeps[w] = -1.0
            log1m[w] = -1.0
            continue
        lp[w] = v
        log1m[w] = _log_expit(-lf) / D  # log(1 - eps) with (1 - eps)^D = 1 - f
        logeps[w] = math.log(-math.expm1(log1m[w]))
    return mu, tau, logeps, log1m, lp


class _HyperPosterior:
    """Log posterior of the hyperparameters, in the sampler's coordinates.

    The sampler moves ``u = (nu, log tau, logit f)`` with
    ``mu = mbar + nu * sqrt(tau^2 + cbar) / sqrt(N)``: given the spreads, the
    centre is known to about that sd, so ``nu`` is roughly standard normal
    whatever ``tau`` is.  Without this the (mu, log tau) funnel of small
    batches slows emcee down (measured: autocorrelation time ~55 -> ~40).
    """

    def __init__(self, pop, terms, m, C):
        self.pop = pop
        self.terms = terms
        self.mbar = m.mean(axis=0)
        self.cbar = np.median(np.einsum("ijj->ij", C), axis=0)
        self.sqrt_n = math.sqrt(len(m))
        self._prior_args = (self.mbar, self.cbar, self.sqrt_n, pop.mu_mean, pop.mu_sd, pop.logtau_mean,
                            pop.logtau_sd, pop.beta[0], pop.beta[1])

    def _scale(self, logtau):
        with np.errstate(over="ignore"):
            return np.sqrt(np.exp(2.0 * logtau) + self.cbar) / self.sqrt_n

    def natural(self, u):
        """Sampler coordinates (..., 11) -> natural ``(mu, log tau, logit f)``."""
        u = np.asarray(u, dtype=float)
        h = u.copy()
        h[..., :N_PARAMS] = self.mbar + self._scale(u[..., N_PARAMS:2 * N_PARAMS]) * u[..., :N_PARAMS]
        return h

    def from_natural(self, h):
        u = np.asarray(h, dtype=float).copy()
        u[..., :N_PARAMS] = (h[..., :N_PARAMS] - self.mbar) / self._scale(h[..., N_PARAMS:2 * N_PARAMS])
        return u

    def log_natural(self, h):
        """Log posterior density of natural hyperparameters (W, 11) -> (W,) (reference implementation)."""
        lp = self.pop.log_prior(h)
        out = np.full(len(h), -np.inf)
        ok = np.isfinite(lp)
        if ok.any():
            mu, tau, _, logeps, log1m = self.pop.unpack(h[ok])
            ll, _ = self.terms(self.pop, mu, tau, logeps, log1m)
            out[ok] = lp[ok] + ll.sum(axis=1)
        return np.where(np.isfinite(out), out, -np.inf)

    def __call__(self, u):
        """Log posterior density in sampler coordinates (W, 11) -> (W,) (the sampler's hot path)."""
        mu, tau, logeps, log1m, lp = _hyper_prep(np.ascontiguousarray(u, dtype=float), *self._prior_args)
        ok = np.isfinite(lp)
        if not ok.all():
            if not ok.any():
                return lp
            mu, tau, logeps, log1m = mu[ok], tau[ok], logeps[ok], log1m[ok]
        ll, _ = self.terms(self.pop, mu, tau, logeps, log1m)
        lp[ok] += ll.sum(axis=1)
        return np.where(np.isfinite(lp), lp, -np.inf)


# --------------------------------------------------------------------------- input checks


def _check_modules(mapping, what):
    if not isinstance(mapping, dict):
        raise ModelError(f"{what} must be a dict module id -> ..., got {type(mapping).__name__}")
    if len(mapping) < 2:
        raise ModelError(f"a population needs at least 2 modules, got {len(mapping)} ({list(mapping)})")
    return tuple(mapping)


def _validate_draws(draws):
    ids = _check_modules(draws, "draws")
    arrays = []
    for mid in ids:
        a = draws[mid]
        try:
            a = np.asarray(a, dtype=float)
        except (TypeError, ValueError):
            raise ModelError(f"module '{mid}': draws are not a numeric array") from None
        if a.ndim != 2 or a.shape[1] != N_PARAMS:
            raise ModelError(f"module '{mid}': draws must have shape (n_draws, {N_PARAMS}) in the order "
                             f"{MODULE_PARAMETERS}, got shape {a.shape}")
        if len(a) < MIN_DRAWS:
            raise ModelError(f"module '{mid}': needs at least {MIN_DRAWS} posterior draws, got {len(a)}")
        bad = ~np.isfinite(a)
        if bad.any():
            cols = [MODULE_PARAMETERS[j] for j in np.flatnonzero(bad.any(axis=0))]
            raise ModelError(f"module '{mid}': {int(bad.sum())} non-finite draw values (NaN/inf) in {cols}")
        nonpos = (a[:, LEVEL] <= 0).any(axis=0)
        if nonpos.any():
            cols = [p for p, lev in zip(MODULE_PARAMETERS, LEVEL) if lev]
            cols = [c for c, b in zip(cols, nonpos) if b]
            raise ModelError(f"module '{mid}': {cols} must be positive in every draw")
        flat = np.ptp(a, axis=0) == 0
        if flat.any():
            raise ModelError(f"module '{mid}': draws of {[MODULE_PARAMETERS[j] for j in np.flatnonzero(flat)]} "
                             "do not vary (a posterior needs spread)")
        arrays.append(a)
    return ids, arrays


# --------------------------------------------------------------------------- sampling


def _emcee_seed(rng):
    if not isinstance(rng, np.random.Generator):
        raise ModelError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    return int(rng.integers(0, 2 ** 32 - 1))


def _versions():
    return {"numpy": np.__version__, "emcee": emcee.__version__, "arviz": _arviz().__version__,
            "numba": numba.__version__}


def _arviz():
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)
        import arviz
    return arviz


def _rhat_ess(keep):
    """Split R-hat and bulk ESS (arviz, walkers as chains) of ``keep`` (n, W, D)."""
    az = _arviz()
    ds = az.convert_to_dataset({"h": np.swapaxes(keep, 0, 1)})  # (chain = walker, draw, dim)
    rhat = np.asarray(az.rhat(ds)["h"].values, dtype=float)
    ess = np.asarray(az.ess(ds, method="bulk")["h"].values, dtype=float)
    return rhat, ess


def _targets(convergence):
    t = {"tau_factor": TAU_FACTOR, "rhat_max": RHAT_MAX, "ess_min": ESS_MIN}
    for k, v in (convergence or {}).items():
        if k not in t:
            raise ModelError(f"convergence: unknown target '{k}'; expected {sorted(t)}")
        t[k] = float(v)
    return t


def _run_emcee(log_prob, p0, seed, *, max_steps, max_seconds, progress, label, convergence=None, stacklevel=3):
    """Run emcee until converged or out of budget.

    Convergence, checked between chunks on the last three quarters of the run
    (the first quarter is burn-in): length >= 50 emcee autocorrelation times,
    split R-hat <= 1.01 and bulk ESS >= 1000 in every dimension (defaults;
    ``convergence`` may override ``tau_factor``, ``rhat_max``, ``ess_min``).

    Returns
    -------
    kept : ndarray (n_keep, W, D)
    diag : dict
    """
    target = _targets(convergence)
    W, D = p0.shape
    # DE moves: better than the stretch move here (autocorrelation ~40 vs ~110
    # steps on a 3-module batch) and they jump between the modes of small batches
    sampler = emcee.EnsembleSampler(W, D, log_prob, vectorize=True, moves=emcee.moves.DEMove())
    state = emcee.State(p0, random_state=np.random.RandomState(seed).get_state())
    t0 = time.perf_counter()
    n_next = min(max_steps, 2000)
    while True:
        state = sampler.run_mcmc(state, n_next - sampler.iteration, progress=progress,
                                 skip_initial_state_check=True)
        n = sampler.iteration
        burn = n // 4
        keep = sampler.get_chain()[burn:]
        tau = emcee.autocorr.integrated_time(keep, tol=0)
        tau_max = float(np.max(tau)) if np.all(np.isfinite(tau)) else float("inf")
        need = target["tau_factor"] * tau_max / len(keep)  # > 1: too short
        rhat_max = ess_min = float("nan")
        if need <= 1.0:  # arviz only when it can pass: it is the slow part of a check
            rhat, ess = _rhat_ess(keep)
            rhat_max, ess_min = float(np.max(rhat)), float(np.min(ess))
            need = max(need, (rhat_max - 1.0) / (target["rhat_max"] - 1.0), target["ess_min"] / ess_min)
        converged = need <= 1.0
        out_of_budget = n >= max_steps or (max_seconds is not None and time.perf_counter() - t0 > max_seconds)
        if converged or out_of_budget:
            break
        # R-hat - 1 and 1/ESS shrink about like 1/length: aim 20 % past the estimate
        n_next = int(min(max_steps, max(1.25 * n, 1.2 * need * n if np.isfinite(need) else 2 * n)))
    if np.isnan(rhat_max):
        rhat, ess = _rhat_ess(keep)
        rhat_max, ess_min = float(np.max(rhat)), float(np.min(ess))
    acc = sampler.acceptance_fraction
    diag = {"converged": bool(converged), "n_steps": int(n), "n_burn": int(burn), "tau_max": tau_max,
            "rhat_max": rhat_max, "ess_bulk_min": ess_min, "nwalkers": int(W),
            "acceptance_min": float(acc.min()), "acceptance_mean": float(acc.mean()), "emcee_seed": int(seed),
            "sampling_s": float(time.perf_counter() - t0), "targets": target}
    if not converged:
        warnings.warn(f"{label}: not converged within the budget ({n} steps, tau_max {tau_max:.0f}, "
                      f"R-hat {rhat_max:.3f}, bulk ESS {ess_min:.0f}); raise max_steps/max_seconds",
                      PopulationConvergenceWarning, stacklevel=stacklevel)
    return keep, diag


def _start_hyper(post, m, C, rng, nwalkers):
    """Walkers (sampler coordinates) around the hyper-MAP, found from robust moment estimates."""
    pop = post.pop
    mu0 = np.median(m, axis=0)
    mad = 1.4826 * np.median(np.abs(m - mu0), axis=0)
    meas = np.median(np.sqrt(np.einsum("ijj->ij", C)), axis=0)
    typical = np.exp(pop.logtau_mean)
    tau0 = np.sqrt(np.maximum(mad ** 2 - meas ** 2, (0.3 * typical) ** 2))
    a, b = pop.beta
    h0 = np.concatenate([mu0, np.log(tau0), [np.log(a / b)]])
    u0 = post.from_natural(h0)

    def nlp(u):
        v = post(u[None, :])[0]
        return -v if np.isfinite(v) else 1e300

    best = optimize.minimize(nlp, u0, method="Powell", options={"xtol": 1e-4, "ftol": 1e-9, "maxfev": 20000})
    u = best.x if np.isfinite(best.fun) and best.fun < nlp(u0) else u0
    # nu ~ N(0, 1) and log tau, logit f within a few tenths: a ball emcee expands quickly
    scale = np.concatenate([np.full(N_PARAMS, 0.5), np.full(N_PARAMS, 0.2), [0.3]])
    p0 = u + scale * rng.standard_normal((nwalkers, len(u)))
    lp = post(p0)
    for _ in range(100):
        bad = ~np.isfinite(lp)
        if not bad.any():
            break
        p0[bad] = u + 0.1 * scale * rng.standard_normal((bad.sum(), len(u)))
        lp = post(p0)
    return p0


def _thin_rows(n, k):
    """Indices of at most ``k`` evenly spaced rows out of ``n``."""
    return np.unique(np.linspace(0, n - 1, min(n, k)).round().astype(int))


def _member_prob(pop, terms, hflat):
    """P(member) of each module at each hyper draw: (n, N)."""
    out = []
    for sl in np.array_split(np.arange(len(hflat)), max(1, len(hflat) // 256)):
        mu, tau, _, logeps, log1m = pop.unpack(hflat[sl])
        _, lmem = terms(pop, mu, tau, logeps, log1m)
        out.append(np.exp(lmem))
    return np.concatenate(out)


def _rao_blackwell(pm):
    """Outlier probabilities and Monte Carlo se from P(member) at draws ``pm`` (n, W, N)."""
    p_out = 1.0 - pm.mean(axis=(0, 1))
    az = _arviz()
    ess = np.asarray(az.ess(az.convert_to_dataset({"p": np.swapaxes(pm, 0, 1)}))["p"].values, dtype=float)
    sd = pm.reshape(-1, pm.shape[2]).std(axis=0)
    ess = np.maximum(np.nan_to_num(ess, nan=1.0), 1.0)  # nan: constant draws
    return p_out, np.where(sd > 0, sd / np.sqrt(ess), 0.0)


def _outlier_probabilities(pop, terms, kept, n_rb):
    """Rao-Blackwellised outlier probabilities (averaged over hyper draws) and their se."""
    n_keep, W, _ = kept.shape
    idx = _thin_rows(n_keep, max(100, n_rb // W))
    sub = kept[idx]  # (n, W, D)
    pm = _member_prob(pop, terms, sub.reshape(-1, sub.shape[2])).reshape(len(idx), W, -1)
    return _rao_blackwell(pm)


def _predictive(pop, kept, rng, n):
    """Draws of a new module: member and with-outlier versions, SI (n, 5) each."""
    flat = kept.reshape(-1, kept.shape[2])
    h = flat[rng.integers(0, len(flat), n)]
    mu, tau, _, logeps, _ = pop.unpack(h)
    z = rng.standard_normal((n, N_PARAMS))
    member = pop.coords.to_theta(mu + tau * z)
    u = rng.random((n, N_PARAMS))
    eps = np.exp(logeps)[:, None]
    moderate = u < (1.0 - GROSS_SHARE) * eps
    gross = (u >= (1.0 - GROSS_SHARE) * eps) & (u < eps)
    x = np.where(moderate, mu + pop.lam * tau * z, mu + tau * z)
    x = np.where(gross, pop.gross_mean + pop.gross_sd * z, x)
    return member, pop.coords.to_theta(x)


def _assemble(pop, ids, kept, p_out, mcse, rng, n_predictive, diag):
    member, mixed = _predictive(pop, kept, rng, n_predictive)
    hyper_si = pop.to_si(kept)  # each (n_keep, W)
    hyper = {k: np.ascontiguousarray(v.T) for k, v in hyper_si.items()}
    diag = dict(diag)
    diag["outlier_prob_mcse"] = {mid: float(s) for mid, s in zip(ids, mcse)}
    diag["n_modules"] = len(ids)
    return PopulationResult(module_ids=ids, outlier_prob={mid: float(p) for mid, p in zip(ids, p_out)},
                            predictive=member, hyper=hyper, diagnostics=diag, predictive_with_outliers=mixed)


# --------------------------------------------------------------------------- two-stage fit


def _module_summaries(ids, arrays, pop, log_interim_prior):
    """x draws, self-normalised likelihood weights, Gaussian moments per module."""
    xs, lws, ms, Cs, ess = [], [], [], [], []
    for mid, a in zip(ids, arrays):
        x = pop.coords.to_x(a)
        lp = np.asarray(log_interim_prior(a), dtype=float).reshape(-1)
        if lp.shape != (len(a),):
            raise ModelError(f"log_interim_prior returned shape {lp.shape} for module '{mid}', expected ({len(a)},)")
        if not np.all(np.isfinite(lp)):
            raise ModelError(f"module '{mid}': the interim prior is not finite at {int((~np.isfinite(lp)).sum())} "
                             "draws (were these draws made under this prior?)")
        lw = -(lp + pop.coords.log_jacobian(a))  # 1 / interim density in x
        lw -= special.logsumexp(lw)
        w = np.exp(lw)
        m = w @ x
        d = x - m
        C = (d * w[:, None]).T @ d
        ev = np.linalg.eigvalsh(C)
        if not ev.min() > 1e-14 * ev.max():
            raise ModelError(f"module '{mid}': the draws are degenerate (their covariance is singular); "
                             "parameters must not be exact functions of each other")
        xs.append(x)
        lws.append(lw)
        ms.append(m)
        Cs.append(C)
        ess.append(1.0 / (w * w).sum())
    return xs, lws, np.array(ms), np.array(Cs), np.array(ess)


def _importance_terms_from(xs, lws, per_module):
    tx, tl = [], []
    for x, lw in zip(xs, lws):
        k = _thin_rows(len(x), per_module)
        lwk = lw[k] - special.logsumexp(lw[k])
        tx.append(x[k])
        tl.append(lwk)
    return _ImportanceTerms(tx, tl)


def _compare(pop, gauss, xs, lws, kept, n_check=64, draws_per_module=1000):
    """Gaussian vs importance likelihood at hyper draws (the 'auto' check).

    Importance sums over up to ``draws_per_module`` draws per module, with
    their Monte Carlo variance (``1/ESS - 1/M`` for the log of a
    self-normalised sum; the delta-method se for the membership ratio), so
    that noise of the sums is not mistaken for an approximation error.  A
    module enters at a hyper draw only if its sum has an importance-weight
    ESS >= :data:`CHECK_MIN_ESS` there: a population much narrower than the
    module's posterior leaves few draws where it matters, and then the sum,
    not the Gaussian, is the unreliable one.

    * ``reweight_ess_fraction``: ``exp(-v)``, v the variance over hyper draws
      of the summed log-likelihood difference minus the sums' own variance --
      the effective sample size left if the Gaussian-based hyper draws were
      reweighted to the importance sums.
    * ``outlier_prob_diff_max``: largest difference of a module's membership
      probability (averaged over the hyper draws); the check allows 0.03 plus
      three standard errors.
    """
    flat = kept.reshape(-1, kept.shape[2])
    h = flat[_thin_rows(len(flat), n_check)]
    mu, tau, _, logeps, log1m = pop.unpack(h)
    llg, lmg = gauss(pop, mu, tau, logeps, log1m)
    N = len(xs)
    dll = np.zeros_like(llg)
    noise = np.zeros_like(llg)
    pmg = np.exp(lmg)
    pmi = pmg.copy()
    se = np.zeros_like(llg)
    usable = np.zeros(llg.shape, dtype=bool)
    for i in range(N):
        k = _thin_rows(len(xs[i]), draws_per_module)
        x, lw = xs[i][k], lws[i][k] - special.logsumexp(lws[i][k])
        lmix, lmem = pop.log_density(np.broadcast_to(x, (len(h),) + x.shape), mu, tau, logeps, log1m)
        a = lw + lmix  # (S, M)
        lli = special.logsumexp(a, axis=1)
        wn = np.exp(a - lli[:, None])  # normalised weights of the mixture sum
        ess = 1.0 / (wn ** 2).sum(axis=1)
        # where the population is much narrower than a module's posterior the
        # draws do not cover it: the sums, not the Gaussian, are unreliable there
        ok = ess >= CHECK_MIN_ESS
        usable[:, i] = ok
        dll[ok, i] = lli[ok] - llg[ok, i]
        noise[ok, i] = 1.0 / ess[ok] - 1.0 / len(k)
        r = np.exp(lmem)  # P(member | x_m, alpha) per draw
        p = (wn * r).sum(axis=1)
        pmi[ok, i] = p[ok]
        # self-normalised IS: var(ratio) ~ sum wn^2 (r - ratio)^2
        se[ok, i] = np.sqrt((wn ** 2 * (r - p[:, None]) ** 2).sum(axis=1))[ok]
    d = dll.sum(axis=1)
    excess = max(float(d.var() - noise.sum(axis=1).mean()), 0.0)
    ess_frac = math.exp(-excess)
    diff = np.abs(pmg.mean(axis=0) - pmi.mean(axis=0))
    over = diff - 3.0 * se.mean(axis=0)
    ok = ess_frac >= CHECK_ESS_FRACTION and np.all(over <= CHECK_OUTLIER_DIFF)
    return {"reweight_ess_fraction": ess_frac, "loglike_diff_var": float(d.var()),
            "importance_noise_var": float(noise.sum(axis=1).mean()), "usable_fraction": float(usable.mean()),
            "outlier_prob_diff_max": float(diff.max()), "outlier_prob_diff_minus_3se_max": float(over.max()),
            "passed": bool(ok)}


def fit_population(draws, datasheet, *, rng, log_interim_prior=None, max_steps=40000, max_seconds=None,
                   progress=False, method="auto", spread_prior=None,
                   outlier_fraction_prior=OUTLIER_FRACTION_PRIOR, outlier_scale=OUTLIER_SCALE, nwalkers=32,
                   max_draws_per_module=256, n_predictive=4000, n_rao_blackwell=2048, convergence=None):
    """Population (batch-level) posterior from per-module posterior draws.

    Parameters
    ----------
    draws : dict
        Module id -> ndarray (M_i, 5) of posterior draws in SI, order
        :data:`~tembayes.constants.MODULE_PARAMETERS` (R0 [ohm], R1 [ohm/K],
        S0 [V/K], S1 [V/K^2], K [W/K]); at least 2 modules, >= 20 draws each.
    datasheet : tembayes.data.Datasheet
        Sets the coordinates and the hyperprior scales.
    rng : numpy.random.Generator
        The only source of randomness (emcee's RandomState is seeded from it);
        the same generator state gives the same result.
    log_interim_prior : callable, optional
        ``f(theta (n, 5) SI) -> (n,)`` log density the draws were made under;
        default :func:`~tembayes.calibrate.priors.law_log_prior` (datasheet).
    max_steps : int
        Budget of emcee steps.
    max_seconds : float, optional
        Wall-clock budget of the sampling [s] (checked between chunks).
    progress : bool
        emcee's progress bar.
    method : {"auto", "gaussian", "importance"}
        How a module's likelihood enters (module docstring).
    spread_prior : dict, optional
        Spread name (``tau_R0_rel``, ``tau_R1_ohm_per_K``, ``tau_S0_rel``,
        ``tau_S1_V_per_K2``, ``tau_K_rel``) -> ``(median, log_sd)`` of a
        log-normal prior, e.g. :meth:`PopulationResult.spread_prior` of an
        earlier batch; unnamed spreads keep the default.
    outlier_fraction_prior : (float, float)
        Beta(a, b) prior of the module-level outlier fraction.
    outlier_scale : float
        Width of the outlier component in unit-to-unit spreads.
    nwalkers : int
    max_draws_per_module : int
        Draws per module (evenly thinned) in the importance sums.
    n_predictive : int
        Draws of :attr:`PopulationResult.predictive`.
    n_rao_blackwell : int
        Hyper draws averaged for ``outlier_prob``.
    convergence : dict, optional
        Override the convergence targets ``tau_factor`` (50), ``rhat_max``
        (1.01), ``ess_min`` (1000), e.g. looser for quick looks.

    Returns
    -------
    PopulationResult

    Raises
    ------
    ModelError
        Fewer than 2 modules, malformed or non-finite draws (naming the
        module), draws outside the interim prior's support, bad options.
    """
    if method not in ("auto", "gaussian", "importance"):
        raise ModelError(f"method must be 'auto', 'gaussian' or 'importance', got {method!r}")
    if nwalkers < 2 * _Population.ndim + 2 or nwalkers % 2:
        raise ModelError(f"nwalkers must be even and >= {2 * _Population.ndim + 2}, got {nwalkers}")
    ids, arrays = _validate_draws(draws)
    seed = _emcee_seed(rng)
    t0 = time.perf_counter()
    pop = _Population(datasheet, spread_prior=spread_prior, outlier_fraction_prior=outlier_fraction_prior,
                      outlier_scale=outlier_scale)
    interim = law_log_prior(datasheet) if log_interim_prior is None else log_interim_prior
    xs, lws, m, C, interim_ess = _module_summaries(ids, arrays, pop, interim)
    gauss = _GaussianTerms(m, C)
    imp = _importance_terms_from(xs, lws, max_draws_per_module)

    def run(terms, label):
        post = _HyperPosterior(pop, terms, m, C)
        p0 = _start_hyper(post, m, C, rng, nwalkers)
        kept, diag = _run_emcee(post, p0, seed, max_steps=max_steps, max_seconds=max_seconds,
                                progress=progress, label=label, convergence=convergence, stacklevel=4)
        return post.natural(kept), diag

    check = None
    if method == "importance":
        terms = _importance_terms_from(xs, lws, max(32, min(max_draws_per_module, IMPORTANCE_BUDGET // len(ids))))
        kept, diag = run(terms, "population (importance)")
    else:
        terms = gauss
        kept, diag = run(gauss, "population (gaussian)")
        if method == "auto":
            check = _compare(pop, gauss, xs, lws, kept)
            if not check["passed"]:
                warnings.warn(f"the Gaussian approximation of the module posteriors changes the result "
                              f"(reweighting ESS {check['reweight_ess_fraction']:.2f}, outlier_prob difference "
                              f"{check['outlier_prob_diff_max']:.3f}); re-running with importance sums",
                              UserWarning, stacklevel=2)
                terms = _importance_terms_from(
                    xs, lws, max(32, min(max_draws_per_module, IMPORTANCE_BUDGET // len(ids))))
                kept, diag = run(terms, "population (importance)")
    p_out, mcse = _outlier_probabilities(pop, terms, kept, n_rao_blackwell)
    h_med = np.median(kept.reshape(-1, kept.shape[2]), axis=0)
    wess = imp.weight_ess(pop, h_med)
    diag.update({"method": terms.name, "check": check,
                 "weight_ess": {mid: float(v) for mid, v in zip(ids, wess)},
                 "weight_ess_min": float(wess.min()),
                 "interim_weight_ess_min": float(interim_ess.min()),
                 "draws_per_module_importance": int(max(imp.draws_per_module)),
                 "versions": _versions(), "elapsed_s": float(time.perf_counter() - t0)})
    return _assemble(pop, ids, kept, p_out, mcse, rng, n_predictive, diag)


# --------------------------------------------------------------------------- joint fit


def _laplace(loglike, mid, coords, x0, prior_sd):
    """Mode and covariance (in x) of one module's likelihood, for initialisation.

    A weak Gaussian term (the interim prior's scale) keeps the search finite
    where the likelihood is flat; the covariance is the inverse of a
    finite-difference Hessian of the log likelihood alone.
    """
    def f(x):
        v = np.asarray(loglike(coords.to_theta(x[None, :])), dtype=float).reshape(-1)
        if v.shape != (1,):
            raise ModelError(f"loglike of module '{mid}' must return shape (n,) for theta (n, 5), got {v.shape}")
        return v[0]

    def nlp(x):
        v = f(x)
        return -v + 0.5 * (((x - x0) / prior_sd) ** 2).sum() if np.isfinite(v) else 1e300

    if not np.isfinite(f(x0)):
        raise ModelError(f"module '{mid}': loglike is not finite at the start values; pass start=")
    x = optimize.minimize(nlp, x0, method="Powell", options={"xtol": 1e-10, "ftol": 1e-12, "maxfev": 40000}).x
    x = optimize.minimize(nlp, x, method="BFGS").x
    # Hessian by central differences, step adapted to the curvature
    h = np.full(N_PARAMS, 1e-4)
    for _ in range(3):
        d2 = np.array([(f(x + h * e) - 2 * f(x) + f(x - h * e)) / h[k] ** 2 for k, e in enumerate(np.eye(N_PARAMS))])
        h = np.where(d2 < 0, 0.1 / np.sqrt(np.maximum(-d2, 1e-30)), h * 10)
    H = np.empty((N_PARAMS, N_PARAMS))
    E = np.eye(N_PARAMS) * h
    for a in range(N_PARAMS):
        for b in range(a, N_PARAMS):
            H[a, b] = H[b, a] = (f(x + E[a] + E[b]) - f(x + E[a] - E[b]) - f(x - E[a] + E[b])
                                 + f(x - E[a] - E[b])) / (4 * h[a] * h[b])
    ev, V = np.linalg.eigh(-H)
    if not np.all(ev > 0):
        raise ModelError(f"module '{mid}': the likelihood has no well-defined maximum (Hessian not negative definite)")
    return x, (V / ev) @ V.T


class _JointPosterior:
    """Log posterior of (hyperparameters, module coordinates) for :func:`joint_fit`.

    Sampler vector: the hyper part ``u`` of :class:`_HyperPosterior`, then
    per module and parameter either ``xi`` (centred: ``x = m + s xi``, ``m, s``
    the module likelihood's mode and sd) or ``eta`` (non-centred:
    ``x = mu + tau eta``).  Non-centred is used for parameters whose
    likelihood is wider than the population spread (typically the slopes),
    centred otherwise: each avoids the funnel the other would have.
    """

    def __init__(self, hyper, loglikes, ids, m, s, noncentred):
        self.hyper = hyper
        self.pop = hyper.pop
        self.loglikes = [loglikes[i] for i in ids]
        self.m, self.s = m, s
        self.nc = noncentred  # (5,) bool
        self.N = len(ids)

    def split(self, v):
        """Sampler vectors (W, 11 + 5N) -> natural hyper (W, 11), x (W, N, 5)."""
        W = len(v)
        h = self.hyper.natural(v[:, :_Population.ndim])
        z = v[:, _Population.ndim:].reshape(W, self.N, N_PARAMS)
        with np.errstate(over="ignore", invalid="ignore"):  # far proposals are refused by the prior box
            mu, tau = h[:, None, :N_PARAMS], np.exp(h[:, None, N_PARAMS:2 * N_PARAMS])
            x = np.where(self.nc, mu + tau * z, self.m + self.s * z)
        return h, x

    def join(self, h, x):
        mu, tau = h[:, None, :N_PARAMS], np.exp(h[:, None, N_PARAMS:2 * N_PARAMS])
        z = np.where(self.nc, (x - mu) / tau, (x - self.m) / self.s)
        return np.concatenate([self.hyper.from_natural(h), z.reshape(len(h), -1)], axis=1)

    def __call__(self, v):
        W = len(v)
        u = v[:, :_Population.ndim]
        h, x = self.split(v)
        lp = self.pop.log_prior(h) + np.log(self.hyper._scale(u[:, N_PARAMS:2 * N_PARAMS])).sum(axis=1)
        out = np.full(W, -np.inf)
        ok = np.isfinite(lp)
        if not ok.any():
            return out
        h, x, lp = h[ok], x[ok], lp[ok]
        mu, tau, _, logeps, log1m = self.pop.unpack(h)
        if not np.all(np.isfinite(x)):
            bad = ~np.isfinite(x).all(axis=(1, 2))
            lp[bad] = -np.inf
            x[bad] = self.m
        lmix, _ = self.pop.log_density(x, mu, tau, logeps, log1m)
        # non-centred coordinates: the Jacobian dx/deta = tau cancels the density's 1/tau
        lmix = lmix + (np.log(tau)[:, None, :] * self.nc).sum(axis=2)
        total = lp + lmix.sum(axis=1)
        theta = self.pop.coords.to_theta(x)
        for i, f in enumerate(self.loglikes):
            ll = np.asarray(f(theta[:, i, :]), dtype=float).reshape(-1)
            total = total + ll
        out[ok] = np.where(np.isfinite(total), total, -np.inf)
        return out


def joint_fit(loglikes, datasheet, *, rng, max_steps=200000, max_seconds=None, progress=False,
              spread_prior=None, outlier_fraction_prior=OUTLIER_FRACTION_PRIOR, outlier_scale=OUTLIER_SCALE,
              nwalkers=None, n_predictive=4000, n_rao_blackwell=2048, convergence=None, start=None):
    """Module parameters and hyperparameters sampled together (the check of the two-stage fit).

    Same population model and hyperpriors as :func:`fit_population`, but each
    module enters through its likelihood instead of posterior draws, so no
    interim prior and no approximation are involved.  The cost grows with
    ``11 + 5 N`` sampled dimensions: meant for small batches.

    Parameters
    ----------
    loglikes : dict
        Module id -> callable ``loglike(theta) -> (n,)`` log likelihood for
        ``theta`` (n, 5) SI in MODULE_PARAMETERS order (vectorised).
    datasheet : tembayes.data.Datasheet
    rng : numpy.random.Generator
    max_steps, max_seconds, progress, spread_prior, outlier_fraction_prior, outlier_scale, n_predictive,
    n_rao_blackwell, convergence
        As in :func:`fit_population`.
    nwalkers : int, optional
        Default ``max(64, 2 * ndim + 2)``, ``ndim = 11 + 5 N``.
    start : dict, optional
        Module id -> (5,) SI parameters to start each module's likelihood-mode
        search from (default: the datasheet values, slopes +0.3 %/K).

    Returns
    -------
    PopulationResult
        ``diagnostics`` cover every sampled dimension (hyper and module).
        ``outlier_prob`` averages ``P(member | x_i, alpha)`` over the joint draws.
    """
    ids = _check_modules(loglikes, "loglikes")
    for mid in ids:
        if not callable(loglikes[mid]):
            raise ModelError(f"module '{mid}': loglike must be callable, got {type(loglikes[mid]).__name__}")
    seed = _emcee_seed(rng)
    t0 = time.perf_counter()
    pop = _Population(datasheet, spread_prior=spread_prior, outlier_fraction_prior=outlier_fraction_prior,
                      outlier_scale=outlier_scale)
    x0 = pop.mu_mean.copy()
    x0[~LEVEL] = pop.mu_sd[~LEVEL] * 0.3  # slopes: a positive start (most modules rise with T)
    starts = {}
    for mid in ids:
        if start is not None and mid in start:
            th = np.asarray(start[mid], dtype=float).reshape(-1)
            if th.shape != (N_PARAMS,) or not np.all(np.isfinite(th)) or np.any(th[LEVEL] <= 0):
                raise ModelError(f"start['{mid}'] must be 5 finite SI values with R0, S0, K > 0, got {start[mid]!r}")
            starts[mid] = pop.coords.to_x(th)
        else:
            starts[mid] = x0
    modes, covs = zip(*(_laplace(loglikes[mid], mid, pop.coords, starts[mid], pop.mu_sd) for mid in ids))
    m, C = np.array(modes), np.array(covs)
    hyper = _HyperPosterior(pop, _GaussianTerms(m, C), m, C)
    u0 = _start_hyper(hyper, m, C, rng, 2 * _Population.ndim + 2)
    tau_hat = np.exp(np.median(hyper.natural(u0)[:, N_PARAMS:2 * N_PARAMS], axis=0))
    s = np.sqrt(np.einsum("ijj->ij", C))
    noncentred = np.median(s, axis=0) > tau_hat
    post = _JointPosterior(hyper, loglikes, ids, m, s, noncentred)
    ndim = _Population.ndim + N_PARAMS * len(ids)
    W = nwalkers or max(64, 2 * ndim + 2 + (ndim % 2))
    if W < 2 * ndim or W % 2:
        raise ModelError(f"nwalkers must be even and >= {2 * ndim}, got {W}")
    # walkers: hyper ball around the hyper-MAP, modules around their likelihood modes
    uh = u0[rng.integers(0, len(u0), W)] + 0.05 * rng.standard_normal((W, _Population.ndim))
    h = hyper.natural(uh)
    x = m + 0.5 * np.einsum("ijk,wik->wij", np.linalg.cholesky(C), rng.standard_normal((W, len(ids), N_PARAMS)))
    p0 = post.join(h, x)
    kept, diag = _run_emcee(post, p0, seed, max_steps=max_steps, max_seconds=max_seconds, progress=progress,
                            label="joint population fit", convergence=convergence)
    n_keep = len(kept)
    h_nat = post.hyper.natural(kept[:, :, :_Population.ndim])
    # Rao-Blackwellised membership: P(member | x_i, alpha) averaged over the joint draws
    idx = _thin_rows(n_keep, max(100, n_rao_blackwell // W))
    hs, xs = post.split(kept[idx].reshape(-1, ndim))
    mu, tau, _, logeps, log1m = pop.unpack(hs)
    _, lmem = pop.log_density(xs, mu, tau, logeps, log1m)
    p_out, mcse = _rao_blackwell(np.exp(lmem).reshape(len(idx), W, -1))
    diag.update({"method": "joint", "noncentred": {p: bool(b) for p, b in zip(MODULE_PARAMETERS, noncentred)},
                 "versions": _versions(), "elapsed_s": float(time.perf_counter() - t0)})
    return _assemble(pop, ids, h_nat, p_out, mcse, rng, n_predictive, diag)
