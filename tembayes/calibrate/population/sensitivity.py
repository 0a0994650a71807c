"""What it would take: the odd one's outlier probability if the type's spread were known to be small.

A small batch cannot learn the unit-to-unit spread of the parameter that
makes a unit odd, so "is it an outlier" hangs on that spread.  The hyper
draws already hold the answer for every spread they visit: the posterior
*given* ``tau_j <= s`` is the posterior restricted to the draws below ``s``,
so ``P(outlier | data, tau_j <= s) = 1 - mean pm_i`` over those draws (the
other hyperparameters integrated over as the data say).  Each row also
gives how probable ``tau_j <= s`` is under the batch's own posterior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tembayes.calibrate.population.membership import odd_one
from tembayes.calibrate.population.model import LEVEL, spread_key
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data.write import to_jsonable

#: Assumed spreads, as multiples of the spread hyperprior's median.
SPREAD_FACTORS = (0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 3.0)
#: A row needs at least this many hyper draws below its spread (thinned
#: draws, nearly independent: a probability's Monte Carlo se then <= 0.05).
MIN_DRAWS = 100


@dataclass(frozen=True)
class SpreadSensitivity:
    """The odd one's outlier probability against an assumed largest spread of one parameter.

    Attributes
    ----------
    module_id : str
    parameter : str
        The module parameter (``S0_V_per_K`` ...).
    spread : ndarray, shape (k,)
        Assumed largest spreads, in ``[population]`` units (levels relative, slopes SI).
    outlier_prob, odd_one_prob, posterior_mass : ndarray, shape (k,)
        Given ``spread <= s``: the module's outlier probability, its odd-one
        probability; and the batch's posterior probability of ``spread <= s``.
        NaN where fewer than :data:`MIN_DRAWS` draws lie below ``s``.
    outlier_prob_mcse : ndarray, shape (k,)
        Monte Carlo se of ``outlier_prob``: the sd of the per-draw values
        below ``s`` over the root of their effective number, taken as the
        same fraction of them as of all draws (the module's ``mcse``).
    """

    module_id: str
    parameter: str
    spread: np.ndarray
    outlier_prob: np.ndarray
    odd_one_prob: np.ndarray
    posterior_mass: np.ndarray
    outlier_prob_mcse: np.ndarray

    @property
    def spread_name(self) -> str:
        """The spread's ``[population]`` key (``spread_S0_rel`` ...)."""
        return spread_key(self.parameter)

    def to_json(self) -> dict:
        """``summary.json``'s ``outlier_vs_spread`` (a NaN row's probabilities null)."""
        return to_jsonable(
            {
                "module": self.module_id,
                "parameter": self.parameter,
                "spread_name": self.spread_name,
                "rows": [
                    {"spread_max": s, "outlier_prob": p, "outlier_prob_mcse": e, "odd_one_prob": q, "posterior_mass": m}
                    for s, p, e, q, m in zip(
                        self.spread, self.outlier_prob, self.outlier_prob_mcse, self.odd_one_prob, self.posterior_mass
                    )
                ],
            }
        )


def spread_sensitivity(pop, membership, module: int, parameter: int, module_id: str) -> SpreadSensitivity:
    """The :class:`SpreadSensitivity` of one module against the spread of one parameter.

    Parameters
    ----------
    pop : .model.Population
    membership : .membership.Membership
        With its hyper draws and ``log_member``.
    module, parameter : int
        Indices of the module (input order) and the parameter.
    module_id : str

    Returns
    -------
    SpreadSensitivity
    """
    j = int(parameter)
    _, tau, *_ = pop.unpack(membership.hyper)
    median = float(np.exp(pop.logtau_mean[j]))
    grid = median * np.asarray(SPREAD_FACTORS)
    lmem = membership.log_member
    off = -np.expm1(lmem[:, module])  # per-draw outlier probability
    ess_fraction = _ess_fraction(off, membership.mcse[module])
    k = len(grid)
    p_out, p_odd, mass, mcse = np.full(k, np.nan), np.full(k, np.nan), np.empty(k), np.full(k, np.nan)
    for r, s in enumerate(grid):
        sel = tau[:, j] <= s
        mass[r] = sel.mean()
        if sel.sum() >= MIN_DRAWS:
            p_out[r] = off[sel].mean()
            mcse[r] = off[sel].std() / np.sqrt(ess_fraction * sel.sum())
            p_odd[r] = odd_one(lmem[sel])[0][module]
    si = grid if LEVEL[j] else grid * pop.coords.ref[j]
    return SpreadSensitivity(module_id, MODULE_PARAMETERS[j], si, p_out, p_odd, mass, mcse)


def _ess_fraction(values, mcse):
    """Effective share of the draws ``values`` (S,) given their mean's Monte Carlo se (1 when it is 0)."""
    sd = values.std()
    return 1.0 if mcse <= 0 or sd <= 0 else min(1.0, (sd / mcse) ** 2 / len(values))


def driver(odd_one_prob, p_loo) -> tuple[int, int]:
    """The odd one (highest ``odd_one_prob``) and its parameter least like the others' (smallest ``p_loo``)."""
    i = int(np.argmax(odd_one_prob))
    return i, int(np.argmin(np.asarray(p_loo)[i]))
