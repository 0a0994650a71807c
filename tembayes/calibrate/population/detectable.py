"""The smallest deviation a batch of this size can flag.

A batch of a few modules learns little of the unit-to-unit spread, so a unit
must sit far from the others before the population calls it an outlier.
How far is a property of the design -- the number of modules, the spread
hyperprior (or an earlier batch's spreads), how precisely each module is
measured -- not of the data.  It is found on a synthetic batch of that
design: the other modules at the normal quantiles of the hyperprior's
median spread about its centre (a typical scatter of members, without the
luck of a draw), one unit ``d`` prior-median spreads off in one parameter,
every module measured with the batch's mean covariance; ``d`` is bisected (on
a log scale) to where its ``outlier_prob`` crosses :data:`FLAG`.  Each probe
is a short population fit (:data:`PROBE_TARGETS`): the bracket ends a factor
1.14 wide, and the probes' Monte Carlo error near 0.5 adds a few percent.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtri

from tembayes.calibrate.population.hyper import sample_hyper
from tembayes.calibrate.population.membership import batch_membership
from tembayes.calibrate.population.model import LEVEL
from tembayes.calibrate.population.sampling import Budget, PopulationConvergenceWarning
from tembayes.calibrate.population.terms import GaussianTerms
from tembayes.calibrate.sampler import Targets
from tembayes.constants import MODULE_PARAMETERS

#: The outlier probability a unit must exceed to be flagged.
FLAG = 0.5
#: Deviations searched [prior-median spreads].
SEARCH = (1.0, 64.0)
#: Bisection steps on the log scale (a factor 64 in 5 halvings of its log: a bracket 1.14 wide, +-7 %).
STEPS = 5
#: Convergence targets of a probe (a probability near 0.5 needs no more).
PROBE_TARGETS = Targets(tau_multiple=20.0, rhat_max=1.05, ess_min=200.0)
#: Step budget of a probe.
PROBE_STEPS = 4000


@dataclass(frozen=True)
class FlaggedDeviation:
    """The smallest deviation of one parameter that a batch of this design flags.

    Attributes
    ----------
    parameter : str
        The module parameter (``S0_V_per_K`` ...).
    n_modules : int
        Modules in the batch.
    spreads : float or None
        The deviation in prior-median spreads (about :data:`SEARCH`'s lower
        end when even that is flagged); None when even its upper end is not.
    rel : float or None
        The same as a relative offset (levels; None for slopes).
    si : float or None
        The same in SI (slopes; None for levels).
    """

    parameter: str
    n_modules: int
    spreads: float | None
    rel: float | None = None
    si: float | None = None

    def to_json(self) -> dict:
        """``summary.json``'s ``smallest_flagged_deviation``: ``rel`` or ``si`` only when it has one."""
        out = {"parameter": self.parameter, "n_modules": self.n_modules, "spreads": self.spreads}
        out.update({k: v for k, v in (("rel", self.rel), ("si", self.si)) if v is not None})
        return out


def _outlier_prob(pop, mean, cov, rng, nwalkers):
    """The first module's ``outlier_prob`` in a short population fit of Gaussian module likelihoods ``mean, cov``."""
    terms = GaussianTerms(mean, cov)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PopulationConvergenceWarning)
        kept, _ = sample_hyper(
            pop, terms, mean, cov, rng, nwalkers, Budget(PROBE_STEPS, targets=PROBE_TARGETS), label="probe"
        )
    return float(batch_membership(pop, terms, kept, 1024).outlier_prob[0])


def smallest_flagged(pop, n_modules: int, parameter: int, cov, rng, nwalkers: int = 32) -> FlaggedDeviation:
    """The deviation at which one unit of ``n_modules`` is flagged, in ``parameter`` (index).

    Parameters
    ----------
    pop : .model.Population
        The batch's hyperprior.
    n_modules : int
        Modules in the batch (>= 2).
    parameter : int
        Index into the module parameters.
    cov : ndarray, shape (5, 5)
        A module's likelihood covariance in population coordinates [x units^2].
    rng : numpy.random.Generator

    Returns
    -------
    FlaggedDeviation
    """
    j = int(parameter)
    tau0 = np.exp(pop.logtau_mean)
    centre = pop.mu_mean
    q = ndtri((np.arange(1, n_modules) - 0.5) / (n_modules - 1))  # the members' typical positions
    mean = np.vstack([centre, centre + q[:, None] * tau0[None]])
    C = np.repeat(np.asarray(cov, float)[None], n_modules, axis=0)

    def flagged(d):
        m = mean.copy()
        m[0, j] += d * tau0[j]
        return _outlier_prob(pop, m, C, rng, nwalkers) > FLAG

    name = MODULE_PARAMETERS[j]
    lo, hi = SEARCH
    if not flagged(hi):
        return FlaggedDeviation(name, n_modules, None)
    for _ in range(STEPS):
        mid = float(np.sqrt(lo * hi))
        lo, hi = (lo, mid) if flagged(mid) else (mid, hi)
    d = float(np.sqrt(lo * hi))
    if LEVEL[j]:
        return FlaggedDeviation(name, n_modules, d, rel=float(np.expm1(d * tau0[j])))
    return FlaggedDeviation(name, n_modules, d, si=float(d * tau0[j] * pop.coords.ref[j]))
