"""Does the model fit its own identification run?  The adequacy verdict.

A posterior is only as good as the model under it, and convergence says
nothing about that.  Four numbers from the identification run's own step
windows say whether the model explains the data, and a run that did not
converge has them as well:

- **window agreement**: the variance of the step windows' scores (the
  gradient of each window's log-likelihood) against the posterior's, per law
  parameter (:func:`tembayes.calibrate.discrepancy.window_sandwich`).  About
  1 when the model is right; large when the laws depend on which steps are
  used.
- **noise scale**: the inferred scale of each channel's noise against the
  noise the run itself shows between neighbouring samples.  About 1 when the
  model is right; a model that misses part of the signal has to call it noise.
- **window offsets**: each window's level error, in noise sds.  A model that
  misses the steady levels puts them there.
- **residual whiteness**: the lag-1 autocorrelation of each channel's
  residuals within the windows.  Near 0 for white sensor noise; a missed
  dynamic leaves a slow residual.

Each is checked against a limit set from the benches: about twice the largest
value a model that is right gave (the in-model and out-of-model law-coverage
studies, ``analyses/law_coverage.py``), so a module whose model is right
passes; a 6 s sensor lag left out of the model fails every check.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from tembayes.calibrate.likelihood import NOISE_SCALE, OFFSET_SD
from tembayes.calibrate.stepdata import CHANNELS

if TYPE_CHECKING:
    from collections.abc import Mapping, Sequence

    from tembayes.calibrate.discrepancy import WindowSandwich
    from tembayes.calibrate.stepdata import StepData

__all__ = ["AdequacyCheck", "Adequacy", "adequacy_numbers", "assess", "LIMITS"]

#: Limit of each check; a value beyond it fails.  See the module docstring.
LIMITS = {
    "window_agreement": 4.0,
    "noise_scale": 1.5,
    "window_offsets": 2.0,
    "residual_lag1": 0.5,
}

_SAYS = {
    "window_agreement": "the step windows disagree about {what}: the laws depend on which steps are used",
    "noise_scale": "{what} scatters {value:.2f}x as much as its sensor noise: the model misses part of the signal",
    "window_offsets": "{what}'s steady levels miss by {value:.1f} noise sds: the model misses the levels",
    "residual_lag1": "{what}'s residuals are correlated (lag-1 {value:.2f}): the model misses a dynamic",
}


@dataclass(frozen=True)
class AdequacyCheck:
    """One adequacy check: its worst value over the parameters or channels it covers."""

    name: str
    value: float
    limit: float
    where: str

    @property
    def passed(self) -> bool:
        """Whether the value is finite and within the limit in magnitude."""
        return bool(np.isfinite(self.value) and abs(self.value) <= self.limit)

    def says(self) -> str:
        """Plain-language reason the check failed (names where, and the value)."""
        return _SAYS[self.name].format(what=self.where, value=self.value)


@dataclass(frozen=True)
class Adequacy:
    """The adequacy verdict of one module's calibration.

    Attributes
    ----------
    numbers : dict
        The raw numbers (:func:`adequacy_numbers`).
    checks : tuple of AdequacyCheck
    """

    numbers: dict
    checks: tuple

    @property
    def verdict(self) -> str:
        """``"fits"`` when every check passes, else ``"does_not_fit"``."""
        return "fits" if all(c.passed for c in self.checks) else "does_not_fit"

    @property
    def reasons(self) -> list:
        """Plain-language reasons of the failed checks (empty when the model fits)."""
        return [c.says() for c in self.checks if not c.passed]

    def to_json(self) -> dict:
        """JSON-ready dict: the raw numbers, the verdict, its reasons and every check."""
        return {
            **self.numbers,
            "verdict": self.verdict,
            "reasons": self.reasons,
            "checks": {
                c.name: {"value": c.value, "limit": c.limit, "where": c.where, "passed": c.passed} for c in self.checks
            },
        }


def adequacy_numbers(
    scatter: WindowSandwich,
    values: Mapping[str, np.ndarray],
    data: StepData,
    resid: np.ndarray,
    law_names: Sequence[str],
) -> dict:
    """The numbers the verdict reads, from a module's kept draws.

    Parameters
    ----------
    scatter : WindowSandwich
        The windows' score scatter (:func:`~tembayes.calibrate.discrepancy.window_sandwich`).
    values : mapping of str to ndarray
        The kept draws by parameter name (noise parameters included).
    data : StepData
    resid : ndarray, shape (3, n)
        Observed minus fitted at the posterior mean, per channel.
    law_names : sequence of str
        The law parameters, in the order of ``scatter.ratios``.
    """
    starts = np.append(data.window_starts, resid.shape[1])
    rho = {}
    for c, name in enumerate(CHANNELS):
        num = den = 0.0
        for a, b in zip(starts[:-1], starts[1:]):
            r = resid[c, a:b] - resid[c, a:b].mean()
            num += float(r[1:] @ r[:-1])
            den += float(r @ r)
        rho[name] = num / den if den > 0 else float("nan")
    return {
        "window_score_variance_ratio_max": float(np.max(scatter.ratios)),
        "window_score_variance_ratios": dict(zip(law_names, map(float, scatter.ratios))),
        "noise_scale_median": {c: float(np.median(values[n])) for c, n in zip(CHANNELS, NOISE_SCALE)},
        "offset_sd_over_noise_median": {
            c: float(np.median(values[n]) / sd) for c, n, sd in zip(CHANNELS, OFFSET_SD, data.noise)
        },
        "residual_lag1_autocorrelation": rho,
    }


def _worst(name, values, limit, key=abs):
    where, value = max(values.items(), key=lambda kv: key(kv[1]) if np.isfinite(kv[1]) else np.inf)
    return AdequacyCheck(name, float(value), float(limit), str(where))


def assess(numbers: dict, limits: Mapping[str, float] | None = None) -> Adequacy:
    """The verdict on :func:`adequacy_numbers`' output.

    Parameters
    ----------
    numbers : dict
    limits : dict, optional
        Limits by check name (default :data:`LIMITS`).

    Returns
    -------
    Adequacy
    """
    lim = {**LIMITS, **(limits or {})}
    checks = (
        _worst("window_agreement", numbers["window_score_variance_ratios"], lim["window_agreement"]),
        _worst("noise_scale", numbers["noise_scale_median"], lim["noise_scale"]),
        _worst("window_offsets", numbers["offset_sd_over_noise_median"], lim["window_offsets"]),
        _worst("residual_lag1", numbers["residual_lag1_autocorrelation"], lim["residual_lag1"]),
    )
    return Adequacy(numbers=numbers, checks=checks)
