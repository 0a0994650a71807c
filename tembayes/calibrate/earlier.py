"""What an earlier calibration run of a module type gives the next: its learned spreads, its population.

Two uses, two options of ``tembayes calibrate``:

- ``--population-prior RUN``: the unit-to-unit *spreads* the earlier run
  learned become the population stage's spread prior for a new batch (the
  batch's own centre stays free) -- :func:`population_prior_of_run`.
- ``--unit-prior RUN``: the earlier run's *population* (its predictive for a
  new unit, ``summary.json``'s ``population``) becomes each module's prior on
  the laws in place of the datasheet's -- :func:`unit_prior_of_run`.  This is
  for a new unit of a known type, tested briefly (``tembayes design
  --population RUN``).  The population's members are independent given the
  hyperparameters, so the prior is a product of the marginals: on the
  reference type the predictive's correlations are below 0.03.

Both refuse a run of another module type or whose population did not converge.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from tembayes.calibrate.priors import LAW_KINDS, LawPrior, ParameterPrior
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data.batch import POPULATION_SPREAD_KEYS
from tembayes.errors import DataError


def _earlier_summary(run, module_type):
    """``(path, summary.json)`` of an earlier run of ``module_type`` whose population converged."""
    f = Path(run) / "summary.json"
    if not f.is_file():
        raise DataError(f, "is not there", "Give the --out folder of an earlier `tembayes calibrate` run.")
    doc = json.loads(f.read_text())
    if doc.get("population") is None:
        raise DataError(
            f,
            "has no population: that run fitted none (fewer than 2 modules converged)",
            "Give a run of at least 2 converged modules of the type.",
            column="population",
        )
    earlier = (doc.get("batch") or {}).get("module_type")
    if earlier is not None and earlier != module_type:
        raise DataError(
            f,
            f"is a run of module type {earlier!r}, not {module_type!r}",
            "Give a run of the same module type ([module_type] name in batch.toml).",
            column="batch.module_type",
        )
    if not (doc.get("population_diagnostics") or {}).get("converged", False):
        raise DataError(
            f,
            "its population fit did not converge, so what it learned is not reliable",
            "Give a run whose population converged (summary.json: population_diagnostics.converged).",
            column="population_diagnostics.converged",
        )
    return f, doc


def population_prior_of_run(run: Path | str, module_type: str) -> dict[str, tuple[float, float]]:
    """The unit-to-unit spreads an earlier run learned, as ``[population]`` entries ``spread_... -> (median, log_sd)``.

    Raises
    ------
    DataError
        No ``summary.json``, no population fit in it, or another module type.
    """
    f, doc = _earlier_summary(run, module_type)
    spreads = doc.get("population_spreads")
    if not spreads:
        raise DataError(
            f,
            "has no population_spreads: that run fitted no population (fewer than 2 modules converged)",
            "Give a run of at least 2 converged modules of the type.",
            column="population_spreads",
        )
    out = {}
    for k, v in spreads.items():
        try:
            median, log_sd = float(v["median"]), float(v["log_sd"])
        except (KeyError, TypeError, ValueError):
            median = log_sd = float("nan")
        if k not in POPULATION_SPREAD_KEYS or not (median > 0 and log_sd > 0 and math.isfinite(median * log_sd)):
            raise DataError(
                f,
                f"population_spreads.{k} is {v!r}: not one of {', '.join(POPULATION_SPREAD_KEYS)} with a "
                "positive median and log_sd",
                "Give the summary.json a calibration run wrote, unedited.",
                column=f"population_spreads.{k}",
            )
        out[k] = (median, log_sd)
    return out


def unit_prior_of_run(run: Path | str, module_type: str) -> LawPrior:
    """The population of an earlier run of ``module_type`` as a new unit's prior on the laws.

    Per law, the population-predictive draws of ``posterior.nc`` give the
    prior the datasheet's would be of the same kind: a log-normal for R0,
    S0 and K (the mean and sd of the draws' logs), a normal for R1 and S1.

    Raises
    ------
    DataError
        No ``summary.json`` or population draws, another module type, or a
        population that did not converge.
    """
    from tembayes.calibrate.run import load_run

    _earlier_summary(run, module_type)
    draws = load_run(run).population_draws()
    if draws is None:
        raise DataError(
            Path(run) / "posterior.nc",
            "has no population-predictive draws (group 'population'): that run fitted no population",
            "Give a run of at least 2 converged modules of the type.",
            column="population",
        )
    priors = []
    for j, (name, kind) in enumerate(zip(MODULE_PARAMETERS, LAW_KINDS)):
        v = np.log(draws[:, j]) if kind == "lognormal" else draws[:, j]
        centre = float(np.exp(v.mean())) if kind == "lognormal" else float(v.mean())
        priors.append(ParameterPrior(name, kind, centre, float(v.std(ddof=1))))
    return LawPrior(tuple(priors), f"population of {Path(run).resolve()}")
