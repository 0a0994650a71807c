"""What a batch-calibration report holds (``tembayes report``), gathered from a run.

:func:`build_report` reads a calibration run (``summary.json``,
``posterior.nc``) and its batch, optionally ``tembayes predict`` and
``tembayes gap`` result folders, and returns a :class:`BatchReport`: plain
numbers, tables and PNG figures.  :mod:`tembayes.report.html` turns it into
one self-contained HTML file.  Nothing here recalibrates; the validation
bands are computed with :func:`tembayes.predict.predict` when no predict
folder is given.
"""

from __future__ import annotations

import datetime as _dt
import json
import platform
import time as _time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from tembayes.common.provenance import versions
from tembayes.constants import KELVIN, MODULE_PARAMETERS
from tembayes.data.quality import summarize_experiment
from tembayes.errors import DataError
from tembayes.report.outliers import OutlierAnswer
from tembayes.report.tolerances import DEFAULT_CONFIDENCE, DEFAULT_TOLERANCES, check_module, parse_tolerance

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from tembayes.calibrate.run import CalibrationRun
    from tembayes.data import Batch

#: Most modules given their own figures (laws, corner, validation); all are in the tables.
MAX_FIGURE_MODULES = 12
#: Keys a ``gap.json`` must have (docs/outputs.md, 'gap.json (gap)').
GAP_KEYS = ("verdict", "where", "ranking", "best")


@dataclass(frozen=True)
class BatchReport:
    """Everything the report shows (plain data; :mod:`tembayes.report.html` renders it).

    Attributes
    ----------
    overview : dict
        Module type, datasheet (CSV units), derived R/S/K, modules, paths, dates.
    quality : list of dict
        Per module and experiment: :func:`summarize_experiment` numbers.
    modules : list of dict
        Per module: ``id``, ``params`` (summary stats, SI), ``outlier_prob``,
        ``odd_one_prob``, ``deviation``,
        ``diagnostics``, ``hysteresis``, ``acceptance`` (the tolerance checks).
    population : dict or None
        ``params`` and ``diagnostics`` of the population fit; ``p_any_outlier``,
        ``outlier_vs_spread``, ``answer`` (the outlier question in words,
        :class:`~tembayes.report.outliers.OutlierAnswer`) and ``odd_one``.
    tolerances : list of str
    confidence : float
    validation : list of dict
        Per module and run: ``module``, ``experiment``, ``channels`` (metrics),
        ``source`` (computed, or the predict folder), ``figure`` key.
    gap : list of dict
        Per gap folder: the ``gap.json`` document, its folder, figure keys.
    provenance : dict
        The calibration's command, seed and versions; the report's.
    figures : dict
        Key -> ``(caption, PNG bytes)``, in display order.
    notes : list of str
        What was left out and why (e.g. modules without their own figures).
    """

    overview: dict
    quality: list
    modules: list
    population: dict | None
    tolerances: list
    confidence: float
    validation: list
    gap: list
    provenance: dict
    figures: dict = field(default_factory=dict)
    notes: list = field(default_factory=list)

    def to_json(self) -> dict:
        """The numbers of the report (no figures): ``report.json``."""
        return {
            "overview": self.overview,
            "quality": self.quality,
            "modules": self.modules,
            "population": self.population,
            "tolerances": self.tolerances,
            "confidence": self.confidence,
            "validation": self.validation,
            "gap": [{k: v for k, v in g.items() if k != "figures"} for g in self.gap],
            "provenance": self.provenance,
            "notes": self.notes,
            "passed": {m["id"]: m["acceptance"]["passed"] for m in self.modules},
        }


def step_estimates(run: CalibrationRun, batch: Batch, module_id: str) -> dict:
    """The module's per-step R and S with the rig at its posterior mean.

    See :func:`tembayes.identify.pipeline.step_estimates`.
    """
    from tembayes.identify.pipeline import step_estimates as _steps
    from tembayes.physics.rigread import rig_from_config

    rig = rig_from_config(batch.rig_config, leg_cells=0)
    nu = run.module_summary(module_id).nuisance
    vals = {k: v.mean for k, v in nu.items() if k in rig.parameter_names}
    sds = {k: v.sd for k, v in nu.items() if k in rig.parameter_names}
    return _steps(batch.modules[module_id].identification, rig, vals, sds)


def read_gap(folder: Path | str) -> tuple[dict, list[Path]]:
    """``folder/gap.json`` checked for the keys of docs/outputs.md, 'gap.json (gap)', and the folder's PNG figures."""
    f = Path(folder) / "gap.json"
    if not f.is_file():
        raise DataError(f, "is not there", "Give the --out folder of a `tembayes gap` run with --gap.")
    try:
        doc = json.loads(f.read_text())
    except json.JSONDecodeError as err:
        raise DataError(f, f"is not JSON ({err})", "Rerun `tembayes gap`.") from None
    missing = [k for k in GAP_KEYS if k not in doc]
    if missing:
        raise DataError(
            f,
            f"lacks the key(s) {missing} (docs/outputs.md, 'gap.json (gap)')",
            "Give a gap.json written by `tembayes gap`.",
        )
    return doc, sorted(Path(folder).glob("*.png"))


def read_predict(folder: Path | str) -> tuple[dict, Path | None]:
    """``folder/metrics.json`` of a ``tembayes predict`` run and its prediction figure."""
    f = Path(folder) / "metrics.json"
    if not f.is_file():
        raise DataError(f, "is not there", "Give the --out folder of a `tembayes predict` run with --predict.")
    doc = json.loads(f.read_text())
    if "channels" not in doc:
        raise DataError(
            f,
            "lacks the key 'channels' (docs/outputs.md, 'metrics.json (predict)')",
            "Give a metrics.json written by `tembayes predict`.",
        )
    fig = Path(folder) / "prediction.png"
    return doc, (fig if fig.is_file() else None)


def _dates(paths):
    ts = [p.stat().st_mtime for p in paths if p.is_file()]
    if not ts:
        return None
    iso = [_dt.datetime.fromtimestamp(t, _dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC") for t in (min(ts), max(ts))]
    return iso[0] if iso[0] == iso[1] else f"{iso[0]} to {iso[1]}"


def build_report(
    run: CalibrationRun,
    batch: Batch,
    *,
    tolerances: Sequence[str] = DEFAULT_TOLERANCES,
    confidence: float = DEFAULT_CONFIDENCE,
    validate: bool = True,
    predict_dirs: Sequence[Path | str] = (),
    gap_dirs: Sequence[Path | str] = (),
    n_draws: int = 200,
    seed: int = 0,
    max_figure_modules: int = MAX_FIGURE_MODULES,
    command: str | None = None,
    progress: Callable[[str], None] | None = None,
) -> BatchReport:
    """Gather a batch-calibration report.

    Parameters
    ----------
    run : tembayes.calibrate.run.CalibrationRun
    batch : tembayes.data.Batch
        The calibrated batch (data quality, step estimates, validation runs).
    tolerances : sequence of str
        Acceptance checks (:mod:`tembayes.report.tolerances`).
    confidence : float
        Posterior probability of a range that passes a parameter check.
    validate : bool
        Compute posterior-predictive bands on the batch's validation runs
        (ignored for the modules covered by ``predict_dirs``).
    predict_dirs, gap_dirs : sequence of path
        ``tembayes predict`` / ``tembayes gap`` output folders to include.
    n_draws : int
        Posterior draws per validation prediction.
    seed : int
        Seeds the validation predictions.
    max_figure_modules : int
        Modules given their own figures (highest outlier probability first).
    command : str, optional
        The command line that made the report (recorded).
    progress : callable, optional

    Returns
    -------
    BatchReport
    """
    t0 = _time.perf_counter()
    say = progress or (lambda msg: None)
    tols = [parse_tolerance(t) for t in tolerances]
    if not 0.5 <= confidence < 1.0:
        raise ValueError(f"confidence {confidence}: between 0.5 and 1")
    run.rig_for(batch)  # the batch holds every module of the run
    gaps = [(Path(d), *read_gap(d)) for d in gap_dirs]  # refused inputs before any work
    preds = [(Path(d), *read_predict(d)) for d in predict_dirs]
    ids = list(run.module_ids)
    figs, notes = {}, []
    modules = [
        {**_module_row(run, mid), "acceptance": check_module(tols, run, mid, batch.datasheet, confidence=confidence)}
        for mid in ids
    ]
    summ = run.summary
    population = None
    if summ.population:
        answer = OutlierAnswer.of(summ)
        population = {
            "params": summ.population,
            "diagnostics": dict(summ.population_diagnostics),
            "p_any_outlier": summ.p_any_outlier,
            "outlier_vs_spread": summ.outlier_vs_spread,
            "answer": None if answer is None else answer.lines(),
            "odd_one": None if answer is None else {"module": answer.odd_one, "parameter": answer.parameter},
        }
    # modules with their own figures: the likeliest outliers first, then in batch order
    order = sorted(ids, key=lambda m: -(run.outlier_prob(m) or 0.0))
    shown = [m for m in ids if m in order[:max_figure_modules]]
    if len(shown) < len(ids):
        notes.append(
            f"{len(ids) - len(shown)} of {len(ids)} modules have no figures of their own (the "
            f"{max_figure_modules} likeliest outliers do); every module is in the tables."
        )
    figs.update(_calibration_figures(run, batch, shown, notes, say))
    validation = _given_predictions(preds, figs)
    if validate:
        covered = {row["module"] for row in validation}
        validation += _computed_predictions(
            run, batch, [m for m in ids if m not in covered], shown, figs, n_draws=n_draws, seed=seed, say=say
        )
    if not validation:
        notes.append(
            "No validation bands: the batch has no validation runs"
            if validate and not preds
            else "No validation bands: --no-validation and no --predict folder"
        )
    gap = _gap_sections(gaps, figs)
    provenance = _provenance(dict(summ.calibration), command, seed, t0)
    return BatchReport(
        _overview(run, batch),
        _quality(batch, ids),
        modules,
        population,
        list(tolerances),
        confidence,
        validation,
        gap,
        provenance,
        figs,
        notes,
    )


def _overview(run, batch):
    """The report's first section: module type, datasheet, what was calibrated with which model, dates."""
    ds, cal = batch.datasheet, run.summary.calibration
    ids = list(run.module_ids)
    return {
        "module_type": ds.name,
        "datasheet": ds.to_table(),
        "datasheet_derived": {
            "R_ohm": ds.resistance(),
            "S_V_per_K": ds.seebeck(),
            "K_W_per_K": ds.conductance(),
            "at_C": ds.th - KELVIN,
        },
        "modules": ids,
        "n_modules": len(ids),
        "run": str(run.path),
        "batch": str(batch.path),
        "tref_C": run.tref_C,
        "rig": cal.get("rig"),
        "sensors": {c: batch.layout.describe(c) for c in batch.layout.sensors},
        "boundaries": list(batch.layout.boundaries),
        "face_sensors": list(batch.layout.face),
        "model": cal.get("model", "paper"),
        "effects": cal.get("effects", []),
        "discrepancy": cal.get("discrepancy", "none"),
        # runs before --unit-prior were all calibrated under the datasheet's prior
        "law_prior": cal.get("law_prior", "datasheet"),
        "data_files_dated": _dates(
            [e.path for m in batch.modules.values() for e in (m.identification, *m.validations)]
        ),
        "run_files_dated": _dates([run.path / "summary.json", run.path / "posterior.nc"]),
    }


def _quality(batch, ids):
    """One row per experiment file: its data-quality numbers."""
    return [
        {"module": mid, "experiment": Path(str(exp.path)).name, **summarize_experiment(exp)}
        for mid in ids
        for exp in (batch.modules[mid].identification, *batch.modules[mid].validations)
    ]


def _module_row(run, mid):
    """A module's laws, outlier probability, diagnostics and hysteresis, as summary.json records them."""
    ms = run.module_summary(mid)
    return {
        "id": mid,
        "params": {p: asdict(ms.laws[p]) for p in MODULE_PARAMETERS},
        "outlier_prob": ms.outlier_prob,
        "odd_one_prob": ms.odd_one_prob,
        "deviation": None if ms.deviation is None else dict(ms.deviation),
        "diagnostics": dict(ms.diagnostics),
        "hysteresis": dict(ms.hysteresis),
    }


def _calibration_figures(run, batch, shown, notes, say):
    """``key -> (caption, PNG bytes)``: the laws, population corner, hysteresis and per-module corners."""
    from tembayes.plots.calibrate import (
        plot_corner_module,
        plot_corner_population,
        plot_hysteresis,
        plot_laws,
        plot_outliers,
    )
    from tembayes.plots.report import plot_module_laws, png_bytes

    figs = {}
    say("report: laws and step estimates")
    for mid in shown:
        try:
            steps = step_estimates(run, batch, mid)
        except Exception as err:  # a run without a staircase still gets its bands
            notes.append(f"{mid}: no step estimates ({err})")
            steps = {k: [] for k in ("Tavg_R_C", "R_ohm", "R_sd", "Tavg_S_C", "S_V_per_K", "S_sd", "direction")}
        figs[f"laws_{mid}"] = (
            f"{mid}: R(T) and S(T), posterior 90 % band over the per-step estimates",
            png_bytes(plot_module_laws(run, mid, steps)),
        )
    figs["laws_all"] = (
        "Every module's laws over the population's predictive band; bottom: deviations from the population median",
        png_bytes(plot_laws(run)),
    )
    if run.has_population:
        say("report: population corner plot")
        figs["corner_population"] = (
            "Modules' posteriors over the population predictive (a new module)",
            png_bytes(plot_corner_population(run)),
        )
    if run.summary.p_any_outlier is not None:
        figs["outliers"] = (
            "Left: which module is the odd one (odd_one_prob, bars) and whether it is an outlier (dots). Right: "
            "the odd one's outlier probability if its most deviating parameter's unit-to-unit spread were known "
            "to be at most s, and how probable that is under this batch's own posterior",
            png_bytes(plot_outliers(run)),
        )
    figs["hysteresis"] = ("Up-step minus down-step R and S (±2 sd)", png_bytes(plot_hysteresis(run)))
    for mid in shown:
        say(f"report: corner plot {mid}")
        figs[f"corner_{mid}"] = (f"{mid}: posterior of R0, R1, S0, S1, K", png_bytes(plot_corner_module(run, mid)))
    return figs


def _given_predictions(preds, figs):
    """Validation rows from ``tembayes predict`` folders (their figures added to ``figs``)."""
    rows = []
    for d, doc, fig in preds:
        key = f"predict_{len(rows)}"
        if fig is not None:
            figs[key] = (f"{doc.get('module')}: {Path(str(doc.get('experiment'))).name} (from {d})", fig.read_bytes())
        rows.append(
            {
                "module": doc.get("module"),
                "experiment": Path(str(doc.get("experiment"))).name,
                "channels": doc["channels"],
                "source": str(d),
                "n_draws": doc.get("n_draws"),
                "figure": key if fig is not None else None,
            }
        )
    return rows


def _computed_predictions(run, batch, ids, shown, figs, *, n_draws, seed, say):
    """Validation rows computed here: posterior-predictive bands on every validation run of ``ids``."""
    from tembayes.plots.predict import plot_prediction
    from tembayes.plots.report import png_bytes
    from tembayes.predict.predictive import predict

    rows = []
    for mid in ids:
        for exp in batch.modules[mid].validations:
            name = Path(str(exp.path)).name
            say(f"report: posterior-predictive bands, {mid} {name}")
            res = predict(run, exp, mid, batch, n_draws=n_draws, seed=seed, compare_constant=False)
            key = f"validation_{mid}_{Path(name).stem}"
            if mid in shown:
                figs[key] = (
                    f"{mid}: {name}, measured against the 50/90/95 % posterior-predictive bands",
                    png_bytes(plot_prediction(res.linear)),
                )
            rows.append(
                {
                    "module": mid,
                    "experiment": name,
                    "channels": res.linear.metrics(),
                    "source": f"computed here ({n_draws} draws, seed {seed})",
                    "n_draws": n_draws,
                    "figure": key if mid in shown else None,
                }
            )
    return rows


def _gap_sections(gaps, figs):
    """One section per ``tembayes gap`` folder (its figures added to ``figs``)."""
    out = []
    for i, (d, doc, pngs) in enumerate(gaps):
        keys = []
        for p in pngs:
            key = f"gap{i}_{p.stem}"
            figs[key] = (f"gap diagnosis ({d.name}): {p.stem}", p.read_bytes())
            keys.append(key)
        out.append({"folder": str(d), "doc": doc, "figures": keys})
    return out


def _provenance(cal, command, seed, t0):
    """How the run and the report were made: commands, seeds, versions, times."""
    import tembayes

    return {
        "calibration": {
            "command": cal.get("command"),
            "seed": cal.get("seed"),
            "versions": cal.get("versions", {}),
            "options": cal.get("options", {}),
            "seconds": cal.get("seconds"),
        },
        "report": {
            "command": command,
            "seed": seed,
            "tembayes": tembayes.__version__,
            "python": platform.python_version(),
            "versions": versions(),
            "generated": _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M:%S UTC"),
            "seconds": _time.perf_counter() - t0,
        },
    }
