"""The population posteriors on the calibration's emcee driver (:func:`tembayes.calibrate.sampler.sample`).

The driver's differential-evolution moves suit the population: the posterior
of a small batch can be bimodal ("tight spread plus one outlier" vs "wider
spread"), and DE jumps between the modes (autocorrelation ~40 steps vs ~110
for the stretch move on a 3-module batch).  Every sampled dimension is
monitored, against the modules' convergence targets.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from tembayes.calibrate.sampler import Targets, sample
from tembayes.errors import ModelError

#: The population's targets: the modules' rule, on a chain three times longer.
#: The outlier probabilities' Monte Carlo se is estimated from the chain; at 50
#: autocorrelation times it read 1.3x below their seed-to-seed spread (16 seeds
#: of the example), at 150 it matches it (1.05-1.24). A fit takes ~12 s.
POPULATION_TARGETS = Targets(tau_multiple=150.0)


class PopulationConvergenceWarning(UserWarning):
    """The population sampler ran out of budget before converging."""


@dataclass(frozen=True)
class Budget:
    """How long the population sampler may run, and its convergence targets.

    Attributes
    ----------
    max_steps : int
        Budget of emcee steps.
    max_seconds : float, optional
        Wall-clock budget of the sampling [s], checked at the driver's convergence checks.
    progress : bool
        emcee's progress bar.
    targets : tembayes.calibrate.sampler.Targets
        Convergence targets; :data:`POPULATION_TARGETS` by default.
    """

    max_steps: int
    max_seconds: float = None
    progress: bool = False
    targets: Targets = POPULATION_TARGETS

    def __post_init__(self):
        if not isinstance(self.targets, Targets):
            raise ModelError(f"convergence must be a tembayes.calibrate.sampler.Targets, got {self.targets!r}")


def run_emcee(log_prob, p0, seed, budget, *, label):
    """Sample ``log_prob`` from walkers ``p0`` until converged or out of budget.

    Parameters
    ----------
    log_prob : callable
        ``f(X (W, D)) -> (W,)`` log posterior density (vectorised).
    p0 : ndarray (W, D)
        Initial walkers.
    seed : int
        Seed of emcee's random state.
    budget : Budget
    label : str
        Names the run in the progress bar and the warning.

    Returns
    -------
    kept : ndarray (n_keep, W, D)
        Stored iterations after burn-in.
    diag : dict
        Convergence diagnostics (``n_steps``, ``n_burn``, ``tau_max`` in steps).

    Warns
    -----
    PopulationConvergenceWarning
        The budget ran out before the targets were met.
    """
    t0 = time.perf_counter()

    def out_of_time(chain, steps):
        return time.perf_counter() - t0 > budget.max_seconds

    run = sample(
        log_prob,
        p0,
        seed=seed,
        monitor=range(p0.shape[1]),
        max_steps=budget.max_steps,
        progress=budget.progress,
        label=label,
        stop=None if budget.max_seconds is None else out_of_time,
        targets=budget.targets,
        warning=PopulationConvergenceWarning,
    )
    diag = {
        "converged": run.converged,
        "n_steps": run.steps,
        "n_burn": run.burn * run.thin_by,
        "thin_by": run.thin_by,
        "tau_max": float(np.max(run.tau)),
        "rhat_max": float(np.max(run.rhat)),
        "rhat_walkers_max": float(np.max(run.rhat_walkers)),
        "ess_bulk_min": float(np.min(run.ess_bulk)),
        "nwalkers": int(p0.shape[0]),
        "acceptance_min": float(run.acceptance.min()),
        "acceptance_mean": float(run.acceptance.mean()),
        "emcee_seed": int(seed),
        "sampling_s": float(time.perf_counter() - t0),
        "targets": asdict(budget.targets),
    }
    return run.chain, diag
