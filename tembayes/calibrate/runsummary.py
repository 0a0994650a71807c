"""A calibration run's ``summary.json`` as a typed record.

:func:`tembayes.calibrate.results.summary` builds the document (its keys are
in docs/outputs.md, 'summary.json (calibrate)'); :class:`RunSummary` is what
:func:`~tembayes.calibrate.batch.calibrate_batch` returns and what
:class:`~tembayes.calibrate.run.CalibrationRun` holds, so callers read
``summary.modules["TEM1"].laws["R0_ohm"].mean`` instead of nested keys.
Runs written before a key existed read with its empty value.
"""

from __future__ import annotations

import copy
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

from tembayes.constants import KELVIN, MODULE_PARAMETERS, T_REF


@dataclass(frozen=True)
class LawSummary:
    """Posterior moments of one parameter, in its SI unit.

    Attributes
    ----------
    mean, sd : float
    q05, q95 : float
        The 5 % and 95 % quantiles (the 90 % interval).
    """

    mean: float
    sd: float
    q05: float
    q95: float

    @classmethod
    def from_json(cls, d: Mapping) -> LawSummary:
        """From ``{"mean", "sd", "q05", "q95"}``."""
        return cls(float(d["mean"]), float(d["sd"]), float(d["q05"]), float(d["q95"]))


@dataclass(frozen=True)
class ModuleSummary:
    """One module's entry of ``summary.json``.

    Attributes
    ----------
    laws : mapping of str to LawSummary
        The five module parameters (``R0_ohm`` ... ``K_W_per_K``).
    outlier_prob : float or None
        None without a population fit, or for a module left out of it.
    odd_one_prob : float or None
        The probability that this module is the batch's outlier given that
        there is exactly one (None as ``outlier_prob``).
    deviation : mapping or None
        Parameter -> ``{"rel", "spreads", "p_loo"}`` against the other
        modules' population (None as ``outlier_prob``).
    converged : bool
    diagnostics : mapping
        The stored diagnostics record (``rhat_max``, ``ess_bulk_min``,
        ``psis_k``, ``adequacy``, ...).
    hysteresis : mapping
        ``{"R_ohm": {"estimate", "sd", "z"}, "S_V_per_K": {...}}`` (up - down), or empty.
    nuisance : mapping of str to LawSummary
        Rig parameters, step shift and noise scales.
    """

    laws: Mapping[str, LawSummary]
    outlier_prob: float | None
    converged: bool
    diagnostics: Mapping
    hysteresis: Mapping
    nuisance: Mapping[str, LawSummary]
    odd_one_prob: float | None = None
    deviation: Mapping | None = None

    @property
    def adequacy_failed(self) -> bool:
        """The model-adequacy check found that the model does not fit the identification run."""
        return (self.diagnostics.get("adequacy") or {}).get("verdict") == "does_not_fit"

    @property
    def adequacy_reasons(self) -> tuple[str, ...]:
        """Why the adequacy check failed (empty when it passed or was not run)."""
        return tuple((self.diagnostics.get("adequacy") or {}).get("reasons") or ())

    @classmethod
    def from_json(cls, d: Mapping) -> ModuleSummary:
        """From a ``summary.json`` module entry."""
        diag = MappingProxyType(dict(d.get("diagnostics") or {}))
        op, odd, dev = d.get("outlier_prob"), d.get("odd_one_prob"), d.get("deviation")
        return cls(
            laws=MappingProxyType({p: LawSummary.from_json(d[p]) for p in MODULE_PARAMETERS}),
            outlier_prob=None if op is None else float(op),
            converged=bool(diag.get("converged", False)),
            diagnostics=diag,
            hysteresis=MappingProxyType(dict(d.get("hysteresis") or {})),
            nuisance=MappingProxyType({k: LawSummary.from_json(v) for k, v in (d.get("nuisance") or {}).items()}),
            odd_one_prob=None if odd is None else float(odd),
            deviation=None if dev is None else MappingProxyType(dict(dev)),
        )


@dataclass(frozen=True)
class RunSummary:
    """``summary.json`` of a calibration run.

    Attributes
    ----------
    modules : mapping of str to ModuleSummary
        Every calibrated module, in batch order.
    converged : bool
        Every module and the population fit converged, and none failed.
    tref_C : float
        Reference temperature of the laws [degC].
    population : mapping or None
        The population's hyperparameter summaries; None without a fit.
    p_any_outlier : float or None
        The probability that the batch holds at least one outlier (None without a fit).
    outlier_vs_spread : mapping or None
        The odd one's outlier probability against an assumed largest spread
        (docs/outputs.md; None without a fit).
    smallest_flagged_deviation : mapping or None
        Batches under 8 modules: the deviation a unit needs to be flagged (docs/outputs.md).
    population_diagnostics : mapping
        The population sampler's convergence record (empty without a fit).
    population_spreads : mapping or None
        The learned spreads, in batch.toml's ``[population]`` format.
    population_prior : mapping
        The spreads the population started from (``[population]``, ``--population-prior``).
    population_excluded, failed_modules : mapping of str to str
        Module id -> why it was left out of the population / why it failed.
    calibration, batch : mapping
        The run's provenance records (seed, options, rig, versions; the
        batch's path and file digests).
    """

    modules: Mapping[str, ModuleSummary]
    converged: bool
    tref_C: float
    population: Mapping | None
    p_any_outlier: float | None
    outlier_vs_spread: Mapping | None
    smallest_flagged_deviation: Mapping | None
    population_diagnostics: Mapping
    population_spreads: Mapping | None
    population_prior: Mapping
    population_excluded: Mapping[str, str]
    failed_modules: Mapping[str, str]
    calibration: Mapping
    batch: Mapping
    _document: Mapping

    @classmethod
    def from_json(cls, doc: Mapping) -> RunSummary:
        """The record of a ``summary.json`` document (which is copied, not kept)."""
        doc = copy.deepcopy(dict(doc))
        return cls(
            modules=MappingProxyType({m: ModuleSummary.from_json(e) for m, e in doc["modules"].items()}),
            converged=bool(doc.get("converged", False)),
            tref_C=float(doc.get("tref_C", T_REF - KELVIN)),
            population=doc.get("population"),
            p_any_outlier=None if doc.get("p_any_outlier") is None else float(doc["p_any_outlier"]),
            outlier_vs_spread=doc.get("outlier_vs_spread"),
            smallest_flagged_deviation=doc.get("smallest_flagged_deviation"),
            population_diagnostics=MappingProxyType(dict(doc.get("population_diagnostics") or {})),
            population_spreads=doc.get("population_spreads"),
            population_prior=MappingProxyType(dict(doc.get("population_prior") or {})),
            population_excluded=MappingProxyType(dict(doc.get("population_excluded") or {})),
            failed_modules=MappingProxyType(dict(doc.get("failed_modules") or {})),
            calibration=MappingProxyType(dict(doc.get("calibration") or {})),
            batch=MappingProxyType(dict(doc.get("batch") or {})),
            _document=doc,
        )

    def to_json(self) -> dict:
        """The ``summary.json`` document (a copy: every key, including those not typed here)."""
        return copy.deepcopy(dict(self._document))
