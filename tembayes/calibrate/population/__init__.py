"""The batch (population) stage: what the modules of one type have in common.

Each module of a batch has been calibrated on its own under a broad *interim
prior*; this stage reuses its posterior draws, dividing the interim prior out
(:mod:`.terms`), and samples the hyperparameters of a population model
(:mod:`.model`):

* **members**: ``x_j ~ N(mu_j, tau_j^2)`` independently for each of the five
  parameters, in coordinates ``x`` that make the levels' spreads relative
  sds; a diagonal population, because a batch of 3-10 modules cannot
  identify correlations;
* **outliers, per parameter**: with probability ``eps`` a parameter of a
  module comes from an outlier component instead -- "off by several
  spreads", ``N(mu_j, (6 tau_j)^2)``, or "a broken unit", the interim
  prior's marginal; a module is an outlier if any of its parameters is;
* **hyperpriors**: ``mu`` from the interim prior, ``tau`` log-normal around a
  typical manufacturing spread (or a ``spread_prior`` learned from an earlier
  batch), the module-level outlier fraction ``f ~ Beta(1, 9)``,
  ``eps = 1 - (1 - f)^(1/5)``.

:func:`fit_population` is the two-stage fit (default; Gaussian module
likelihoods, checked against importance sums); :func:`joint_fit` samples the
module parameters too, from their likelihoods (the check of the two-stage
fit, for small batches).  Both return a :class:`PopulationResult`:
Rao-Blackwellised ``outlier_prob`` per module (:mod:`.membership`) and the
predictive of a new member of the type.  Methods, measurements and what a
batch can say: ``docs/methods.md``, 'The population'.
"""

from tembayes.calibrate.population.fit import fit_population
from tembayes.calibrate.population.joint import joint_fit
from tembayes.calibrate.population.model import HYPER_NAMES
from tembayes.calibrate.population.result import PopulationResult
from tembayes.calibrate.population.sampling import PopulationConvergenceWarning

__all__ = ["HYPER_NAMES", "PopulationConvergenceWarning", "PopulationResult", "fit_population", "joint_fit"]
