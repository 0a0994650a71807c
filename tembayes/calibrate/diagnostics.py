"""A module calibration's convergence and fit diagnostics, as one typed record.

A module counts as converged when the sampler met its targets
(:mod:`tembayes.calibrate.sampler`: nested R-hat, bulk ESS, chain length in
autocorrelation times) *and* the linearised likelihood it sampled agrees with
the exact one at its draws: the Pareto-smoothed importance-sampling shape
``k_hat`` of the exact-over-linearised weights is below :data:`PSIS_K_MAX`
(Vehtari et al. 2024, *JMLR* 25(72): above 0.7 the importance weights have
too heavy a tail for the correction to be trusted), and where that took a
second look on more draws, its weights have at least
:data:`RECHECK_MIN_ESS` effective draws (:attr:`PsisCheck.passes`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

from tembayes.calibrate import sampler as smp

#: Largest PSIS ``k_hat`` for which the expansion counts as exact enough.
PSIS_K_MAX = 0.7
#: Fewest effective draws of a second look's weights for it to pass: with 100 the
#: weighted laws' means it reports (``law_shift_sd``) are known to ~0.1 posterior sd.
RECHECK_MIN_ESS = 100


@dataclass(frozen=True)
class PsisCheck:
    """One importance-sampling check of a stage's expansion.

    Attributes
    ----------
    stage : int
        The expansion stage checked.
    k_hat : float
        Pareto shape of the exact-over-linearised weights.
    weight_ess_fraction : float
        Effective sample size of the weights over the number of draws.
    max_logw_dev : float
        Largest log-weight deviation from its mean.
    early_steps : int or None
        Set when the check ran during sampling (the stage was stopped there).
    draws : int or None
        Posterior draws the check weighed (None: a record from before it was kept).
    law_shift_sd : float or None
        How far the Pareto-smoothed weights move the laws' posterior means,
        in posterior sds (the largest over the five laws): what the expansion
        costs the laws where ``k_hat`` says the weights can be trusted.
    recheck : bool
        A second look, after the first failed; it passes only on weights with
        at least :data:`RECHECK_MIN_ESS` effective draws.
    """

    stage: int
    k_hat: float
    weight_ess_fraction: float
    max_logw_dev: float
    early_steps: int | None = None
    draws: int | None = None
    law_shift_sd: float | None = None
    recheck: bool = False

    @property
    def effective_draws(self) -> float | None:
        """Effective sample size of the weights [draws] (None for a record without ``draws``)."""
        return None if self.draws is None else self.weight_ess_fraction * self.draws

    @property
    def passes(self) -> bool:
        """``k_hat`` below :data:`PSIS_K_MAX`, and for a second look enough effective draws."""
        if self.k_hat >= PSIS_K_MAX:
            return False
        return not self.recheck or self.effective_draws >= RECHECK_MIN_ESS

    def to_json(self) -> dict:
        """The check as stored (the optional fields only when set)."""
        d = asdict(self)
        for k in ("early_steps", "draws", "law_shift_sd"):
            if d[k] is None:
                del d[k]
        if not self.recheck:
            del d["recheck"]
        return d


@dataclass(frozen=True)
class ModuleDiagnostics:
    """How a module's sampling went.

    Attributes
    ----------
    rhat, ess_bulk, ess_tail, tau_steps : dict
        ``name -> value`` for every sampled coordinate (``tau`` in emcee steps).
    rhat_max, rhat_walkers_max, ess_bulk_min : float
        Over the five law parameters: nested R-hat (the target), per-walker
        R-hat (reported), bulk ESS.
    tau_max_steps, tau_max_all_steps : float
        Largest autocorrelation time [steps] over the laws / every coordinate.
    chain_over_tau : float
        Kept chain length in autocorrelation times of the laws.
    steps, burn_in_steps, nwalkers : int
    acceptance_mean, acceptance_min : float
    sampler_converged : bool
        The sampler met its targets.
    psis : list of PsisCheck
        The expansion checks, the last one deciding.
    resumed : bool
        Part of the run came from a checkpoint.
    map_nfev : int or None
        Model evaluations of the mode search.
    level_band_neglected : float
        Largest neglected response to a hold level [noise sd per level sd].
    discrepancy, adequacy : dict
        The discrepancy model's record and the adequacy checks (their own JSON).
    timings : dict
        ``stage -> seconds``.
    """

    rhat: dict
    ess_bulk: dict
    ess_tail: dict
    tau_steps: dict
    rhat_max: float
    rhat_walkers_max: float
    ess_bulk_min: float
    tau_max_steps: float
    tau_max_all_steps: float
    chain_over_tau: float
    steps: int
    burn_in_steps: int
    nwalkers: int
    acceptance_mean: float
    acceptance_min: float
    sampler_converged: bool
    psis: tuple
    resumed: bool
    map_nfev: int | None
    level_band_neglected: float
    discrepancy: dict
    adequacy: dict
    timings: dict = field(default_factory=dict)

    @property
    def psis_k(self) -> float:
        """The deciding (last) PSIS ``k_hat``."""
        return self.psis[-1].k_hat

    @property
    def converged(self) -> bool:
        """The sampler met its targets and the last PSIS check passes (:attr:`PsisCheck.passes`)."""
        return bool(self.sampler_converged and self.psis[-1].passes)

    def reasons(self) -> list:
        """Why the module did not converge, one phrase per failed target (empty when it did)."""
        if self.converged:
            return []
        bits = []
        if self.rhat_max > smp.RHAT_MAX:
            bits.append(f"R-hat {self.rhat_max:.3f} > {smp.RHAT_MAX}")
        if self.ess_bulk_min < smp.ESS_MIN:
            bits.append(f"bulk ESS {self.ess_bulk_min:.0f} < {smp.ESS_MIN:.0f}")
        if self.chain_over_tau < smp.MIN_TAU_MULTIPLE:
            bits.append(f"chain {self.chain_over_tau:.0f} autocorrelation times < {smp.MIN_TAU_MULTIPLE:.0f}")
        if not self.sampler_converged and not bits:
            bits.append("the sampler stopped before its targets were met")
        last = self.psis[-1]
        on = "" if last.draws is None else f" on {last.draws} draws"
        if last.k_hat >= PSIS_K_MAX:
            bits.append(f"expansion PSIS k_hat {last.k_hat:.2f} >= {PSIS_K_MAX}{on}")
        elif not last.passes:
            bits.append(
                f"expansion PSIS weights degenerate: {last.effective_draws:.0f} effective of {last.draws} draws "
                f"< {RECHECK_MIN_ESS}"
            )
        return bits

    def to_json(self) -> dict:
        """The record as stored with the module (``modules/<id>.nc``) and read by :meth:`from_json`."""
        d = {k: getattr(self, k) for k in self.__dataclass_fields__}
        d["psis"] = [p.to_json() for p in self.psis]
        d["converged"] = self.converged
        return d

    @classmethod
    def from_json(cls, d: dict) -> "ModuleDiagnostics":
        """The record from :meth:`to_json`'s dict."""
        kw = {k: d.get(k) for k in cls.__dataclass_fields__}
        kw["psis"] = tuple(PsisCheck(**p) for p in d["psis"])
        kw["timings"] = d.get("timings") or {}
        return cls(**kw)
