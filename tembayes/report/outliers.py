"""The outlier question in words: which unit is odd, how far, and what the batch can tell.

Read from a run's ``summary.json`` (:class:`~tembayes.calibrate.runsummary.RunSummary`),
so the console after ``tembayes calibrate`` and the report say the same.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

from tembayes.calibrate.population.detectable import FLAG as FLAG_PROB
from tembayes.calibrate.population.detectable import SEARCH
from tembayes.calibrate.population.deviation import K_HAT_MAX
from tembayes.calibrate.population.fit import SMALL_BATCH
from tembayes.calibrate.population.model import spread_key
from tembayes.constants import MODULE_PARAMETERS

if TYPE_CHECKING:
    from tembayes.calibrate.runsummary import RunSummary

_UNITS = {"R1_ohm_per_K": "ohm/K", "S1_V_per_K2": "V/K^2"}


def short(parameter: str) -> str:
    """``S0_V_per_K`` -> ``S0``."""
    return parameter.split("_")[0]


def spread_text(parameter: str, value: float) -> str:
    """A spread in ``[population]`` units as text: levels in %, slopes in SI."""
    return f"{100 * value:.2g} %" if parameter not in _UNITS else f"{value:.2g} {_UNITS[parameter]}"


@dataclass(frozen=True)
class OutlierAnswer:
    """What the population stage says about outliers.

    Attributes
    ----------
    n_modules : int
        Modules in the population.
    odd_one : str
        The module with the highest ``odd_one_prob``.
    odd_one_prob : dict
        Module id -> its probability of being the outlier, given exactly one (highest first).
    parameter : str
        The odd one's parameter least like the other modules' (smallest ``p_loo``).
    deviation : dict
        That parameter's ``{"rel", "spreads", "p_loo"}``.
    p_any_outlier : float
    flagged : tuple of str
        Modules whose ``outlier_prob`` exceeds :data:`FLAG_PROB`.
    what_it_takes : list of dict
        ``outlier_vs_spread`` rows with a value (empty when none).
    reach : dict or None
        ``smallest_flagged_deviation`` (batches under 8 modules).
    k_hat : float or None
        Pareto k of the odd one's leave-one-out weights (above
        :data:`~tembayes.calibrate.population.deviation.K_HAT_MAX` its
        deviation is an approximation, unless ``refit``).
    refit : bool
        Its deviation comes from a fit of the other modules without it.
    refit_converged : bool
        That fit met its convergence targets (otherwise its deviation is
        an approximation still).
    spread_stated : bool
        The run started from a stated spread of the odd one's parameter
        (``[population]`` or ``--population-prior``).
    """

    n_modules: int
    odd_one: str
    odd_one_prob: dict
    parameter: str
    deviation: dict
    p_any_outlier: float
    flagged: tuple
    what_it_takes: list
    reach: dict | None = None
    k_hat: float | None = None
    refit: bool = False
    refit_converged: bool = True
    spread_stated: bool = False

    @classmethod
    def of(cls, summary: RunSummary) -> OutlierAnswer | None:
        """The answer of a run, or None without a population fit (or from a run that predates it)."""
        mods = {m: e for m, e in summary.modules.items() if e.odd_one_prob is not None and e.deviation}
        if len(mods) < 2 or summary.p_any_outlier is None:
            return None
        odd = dict(sorted(((m, e.odd_one_prob) for m, e in mods.items()), key=lambda kv: -kv[1]))
        top = next(iter(odd))
        dev = mods[top].deviation
        par = min(MODULE_PARAMETERS, key=lambda p: dev[p]["p_loo"])
        curve = summary.outlier_vs_spread or {}
        diag = summary.population_diagnostics
        rows = []
        if curve.get("module") == top:  # the fit picked its parameter by the same rule
            par = curve["parameter"]
            rows = [r for r in curve["rows"] if r.get("outlier_prob") is not None]
        return cls(
            n_modules=len(mods),
            odd_one=top,
            odd_one_prob=odd,
            parameter=par,
            deviation=dict(dev[par]),
            p_any_outlier=float(summary.p_any_outlier),
            flagged=tuple(m for m, e in mods.items() if (e.outlier_prob or 0.0) > FLAG_PROB),
            what_it_takes=rows,
            reach=summary.smallest_flagged_deviation,
            k_hat=(diag.get("deviation_k_hat") or {}).get(top),
            refit=top in (diag.get("deviation_refit") or ()),
            refit_converged=top not in (diag.get("deviation_refit_unconverged") or ()),
            spread_stated=spread_key(par) in (summary.population_prior or {}),
        )

    def _caveat(self) -> str:
        """Why the deviation is approximate, if it is."""
        if self.refit:
            return (
                ""
                if self.refit_converged
                else " (approximate: the fit of the other modules without it did not converge)"
            )
        if self.k_hat is not None and self.k_hat > K_HAT_MAX:
            return f" (approximate: leave-one-out Pareto k {self.k_hat:.2f} > {K_HAT_MAX})"
        return ""

    def lines(self) -> list[str]:
        """The answer as sentences, the odd one first."""
        d, p = self.deviation, short(self.parameter)
        nxt = [f"{m} {q:.2f}" for m, q in list(self.odd_one_prob.items())[1:3]]
        out = []
        if self.flagged:
            out.append(f"Off the batch's population (outlier_prob > {FLAG_PROB}): {', '.join(self.flagged)}.")
        out.append(
            f"Likeliest odd one: {self.odd_one} (odd_one_prob {self.odd_one_prob[self.odd_one]:.2f}; "
            f"{', '.join(nxt)}). Its {p} sits {100 * d['rel']:+.1f} % from the other modules "
            f"({d['spreads']:+.1f} of their spreads); a unit of their population lies that far out "
            f"with probability {d['p_loo']:.2g}{self._caveat()}."
        )
        out.append(f"Probability that the batch holds an outlier at all: {self.p_any_outlier:.2f}.")
        if self.n_modules < SMALL_BATCH and self.odd_one not in self.flagged and not self.spread_stated:
            out.append(self._small_batch())
        if self.reach:
            out.append(self._reach())
        return out

    def _reach(self) -> str:
        r, p = self.reach, short(self.reach["parameter"])
        if r.get("spreads") is None:
            return (
                f"With {r['n_modules']} modules no deviation of {p} within {SEARCH[1]:.0f} typical spreads is flagged."
            )
        size = f"{100 * r['rel']:.0f} %" if "rel" in r else f"{r['si']:.2g} {_UNITS[r['parameter']]}"
        return (
            f"With {r['n_modules']} modules and these spread priors, a unit is called an outlier (P > {FLAG_PROB}) "
            f"only when its {p} sits about {size} ({r['spreads']:.0f} typical spreads) or more from the others."
        )

    def _small_batch(self) -> str:
        p = short(self.parameter)
        text = (
            f"{self.n_modules} modules learn little of the unit-to-unit spread themselves, so whether "
            f"{self.odd_one} is an outlier depends on this type's {p} spread"
        )
        rows = self.what_it_takes
        # the smallest spread the draws reach, and about the batch's own median spread
        mid = min(rows, key=lambda r: abs(r["posterior_mass"] - 0.5)) if rows else None
        picks = rows[:1] + ([mid] if mid is not None and mid is not rows[0] else [])
        if picks:
            text += ": " + "; ".join(
                f"if it is at most {spread_text(self.parameter, r['spread_max'])}, P = {r['outlier_prob']:.2f}"
                for r in picks
            )
        text += (
            ". A larger batch, the spreads in batch.toml's [population] table, or "
            "--population-prior EARLIER_RUN would decide it."
        )
        return text
