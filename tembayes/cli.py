"""The ``tembayes`` command: a thin layer over the library.

Each sub-command parses its arguments, calls one library function and prints
progress to stderr.  A refused input or impossible request ends with a
one-line ``tembayes: error: ...`` and exit status 2; nothing is written.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
from pathlib import Path

import tembayes
from tembayes.common.heap import keep_short_lived_blocks_on_the_heap
from tembayes.constants import KELVIN, RATE_HZ
from tembayes.errors import DataError, ModelError, TembayesError

_EPILOG_SIMULATE = """\
examples:
  tembayes simulate runs/demo --modules 3 --outlier TEM1 --seed 0
  tembayes simulate runs/kt --effect k_temperature --effect sensor_lag=8 --seed 3
  tembayes simulate runs/other --datasheet other_type.toml --validation-rate 1
  tembayes simulate runs/real --fidelity high --validation-start rest --modules 8   # out-of-model bench
  tembayes simulate runs/sink --rig heatsink-al --modules 4    # another shipped rig
  tembayes simulate runs/mine --rig my_rig.toml                # your rig file (copied into the batch)
  tembayes simulate runs/short --protocol runs/design/protocol.csv --rate 2 --fidelity high   # try a design

effects (NAME or NAME=VALUE; VALUE sets the first parameter, others scale along):
{effects}
"""

_EPILOG_IDENTIFY = """\
examples:
  tembayes identify data/example --out runs/example-identify
  tembayes identify data/example --out runs/legs2 --leg-cells 2 --no-figures

writes DIR/identify.json (per module: the step table with R, S and their
uncertainties, the corrected fit and the paper's recipe, the hysteresis check,
the fitted rig parameters, validation errors; the batch average) and figures
(the paper's Figures 5-9: the run, R(T) and S(T) laws, validation with
constant and temperature-dependent laws, error against T_avg).  Every key:
docs/outputs.md, 'identify.json (identify)'.
"""

_EPILOG_CALIBRATE = """\
examples:
  tembayes calibrate data/example --out runs/example --seed 0
  tembayes calibrate data/example --out runs/example --seed 0 --resume   # after an interruption
  tembayes calibrate runs/demo --out runs/demo-cal --max-steps 20000 --no-figures
  tembayes calibrate data/example --out runs/one-by-one --workers 1   # in this process, with stage messages
  tembayes calibrate runs/lag --out runs/lag-cal --effect sensor_lag   # a catalogue effect in the model
  tembayes calibrate factory/lot42 --out runs/lot42 --workers 8 --quiet   # a local Dask cluster of 8 processes
  tembayes calibrate factory/lot42 --out runs/lot42 --scheduler tcp://10.0.0.5:8786   # a running Dask cluster
  tembayes calibrate factory/lot42 --out runs/lot42 --scheduler tcp://10.0.0.5:8786 --resume   # only missing modules
  tembayes calibrate factory/lot43 --out runs/lot43 --population-prior runs/lot42   # the spreads lot 42 learned
  tembayes calibrate spares/unit7 --out runs/unit7 --unit-prior runs/lot42   # a new unit, lot 42's population as its prior

writes RUN/summary.json (per module R0, R1, S0, S1 and K with mean, sd and
90 % interval, outlier_prob, odd_one_prob, deviation, convergence
diagnostics; p_any_outlier; the population's predictive distribution for a
new module), RUN/posterior.nc
(arviz InferenceData: posterior, log_likelihood per step window,
sample_stats, observed_data, constant_data, prior, population),
RUN/modules/<id>.nc as each module finishes, and corner plots in
RUN/figures.  Interrupted runs continue with --resume (finished modules are
reused, a running one continues from its sampler checkpoint).  Known
unit-to-unit spreads of the type go in batch.toml's optional [population]
table (docs/data-format.md, '[population]'); summary.json's
population_spreads gives them for the next batch (--population-prior RUN
reads them from there); --unit-prior RUN instead makes an earlier run's
population each module's prior on the laws (a new unit of a known type
after a short test, docs/design.md).  The console and the report end with the outlier
answer in words: the likeliest odd one, how far it sits from the others,
and, for a small batch, what the type's spread would have to be to call it
an outlier.  Every output key:
docs/outputs.md, 'summary.json (calibrate)' and 'posterior.nc (calibrate)'.
"""

_EPILOG_EXPORT = """\
examples:
  tembayes export runs/example --format mat --out runs/example-observer.mat
  tembayes export runs/example --out runs/ex.json --point 30,-0.8 --point 15,0.6 --module TEM1
  tembayes export runs/example --out runs/hot.json --point 60,-2 --allow-extrapolation   # beyond the data
  tembayes export runs/two --out runs/two.npz --heldout validation.csv   # validation2.csv stays unseen

reads the run and its batch (recorded in RUN/summary.json, or --batch) and
writes one file, SI units (temperatures in K).  The operating points must lie
in the calibrated range: the junction temperatures (T_AVG_C) and currents the
identification runs covered, recorded in the file's meta.calibrated_range;
outside it the export is refused unless --allow-extrapolation, which records a
warning in meta.warnings.  Every field with its shape and unit is in the
file's "fields" table.  In Python:
  scipy.io.loadmat("x.mat", simplify_cells=True)["modules"]["TEM1"]["linear"]["op0"]["A"]
  numpy.load("x.npz")["modules__TEM1__linear__op0__A"]
in MATLAB: x = load('x.mat'); x.modules.TEM1.linear.op0.A
"""

_EPILOG_REPORT = """\
examples:
  tembayes report runs/example --out runs/example-report
  tembayes report runs/example --out runs/rep --gap runs/example-gap --tolerance R0=3% --tolerance K=8%
  tembayes report runs/big --out runs/big-report --no-validation --tolerance R1=0.008:0.012

writes DIR/report.html, one self-contained file (figures inline, no script,
no network): acceptance per module, batch overview, data quality, laws with
bands over the step estimates, population and outlier probabilities,
hysteresis, convergence, corner plots, validation bands and metrics, the gap
diagnosis given with --gap, provenance; and DIR/report.json (its numbers).

tolerances (repeatable; default R0=5% S0=5% K=10% outlier_prob=0.5 converged=yes):
  R0=5%              within 5 % of the datasheet-derived value (R0, S0, K)
  R1=0.008:0.012     inside an absolute range, SI (ohm/K here)
  outlier_prob=0.3   outlier probability at most 0.3
  converged=no       do not require convergence
a parameter check passes when P(inside) >= --confidence (default 0.95).
"""

_EPILOG_GAP = """\
examples:
  tembayes gap runs/example data/example --out runs/example-gap
  tembayes simulate runs/lag --modules 3 --effect sensor_lag --validation-rate 1
  tembayes calibrate runs/lag --out runs/lag-cal
  tembayes gap runs/lag-cal runs/lag --out runs/lag-gap
  tembayes gap runs/lag-cal runs/lag --out runs/lag-blind --exclude sensor_lag   # withheld

writes DIR/gap.json (docs/outputs.md, 'gap.json (gap)'): verdict, where,
ranking with the held-out evidence and the gap before/after and its shrink,
best; plus the screen, the range conflicts, the best group of effects the
data cannot tell apart and the settings; and the figures ranking.png,
gap_map_*.png and residuals_*.png.  Held out are the validation runs and,
one at a time, the identification run's step windows.  The gap is the
excess RMSE over the rig's sensors [K] of the validation runs beyond the predictive's
own uncertainty (or, when only the identification windows show one, their
excess RMS in noise sds: gap.json's "metric"); the evidence the held-out
ELPD difference [nats].
"""

_EPILOG_PREDICT = """\
examples:
  tembayes predict runs/example data/example/TEM2/validation.csv --module TEM2 --out runs/example-pred
  tembayes predict runs/example data/example/TEM2/validation.csv --module population --out runs/pop-pred
  tembayes predict RUN new.csv --module SN0042 --batch path/to/batch --draws 1000 --seed 1 --no-constant
  tembayes predict runs/example data/example/TEM1/validation.csv --module TEM1 --out runs/ppc --draws 200 --netcdf

writes DIR/metrics.json (docs/outputs.md, 'metrics.json (predict)'): per
channel (the rig's sensor columns and voltage_V) the RMSE and max |error| of the predictive
mean, in K or V, and the fraction of samples inside the central 50/90/95 %
predictive bands, noise included; plus the errors per 5 K bin of T-bar, the
anchoring of the rig and, unless --no-constant, the same for R and S
constant at 35 degC under "constant_laws"; and the figures prediction.png,
residuals.png (and *_constant.png, error_vs_tavg.png).  The run's batch
folder (recorded in summary.json, or --batch) is needed: its identification
runs anchor the rig.
--module population predicts a new unit known only through its batch.
--netcdf also writes DIR/predictive.nc, an ArviZ InferenceData (groups
posterior_predictive, observed_data, constant_data; a units attribute on
every variable): az.plot_ppc(az.from_netcdf("runs/ppc/predictive.nc")).
"""

_EPILOG_INSPECT = """\
example:
  tembayes inspect data/example
  tembayes inspect data/example --json > quality.json
"""


def _effects_table():
    from tembayes.physics.effects import CATALOGUE

    lines = []
    for e in CATALOGUE.values():
        ps = ", ".join(f"{p.name}={p.default:g} {p.unit}" for p in e.parameters)
        lines.append(f"  {e.name:<19s}{ps}")
    return "\n".join(lines)


def _cmd_simulate(args):
    from tembayes.bench import TEC1_12706, BenchConfig, simulate_batch
    from tembayes.data import load_batch_toml
    from tembayes.data.outputs import check_output
    from tembayes.design.protocol import read_protocol
    from tembayes.physics.effects import parse_effects
    from tembayes.physics.rigread import rig_source

    datasheet = TEC1_12706
    rig = rig_source(args.rig) if args.rig else None
    if args.datasheet:
        datasheet, _ = load_batch_toml(args.datasheet)
    protocol = read_protocol(args.protocol, imax=datasheet.imax) if args.protocol else None
    check_output(
        args.out,
        kind="simulate",
        overwrite=args.overwrite,
        inputs=([(args.datasheet, "datasheet file")] if args.datasheet else [])
        + ([(Path(rig["file"]), "rig file")] if rig and "file" in rig else [])
        + ([(args.protocol, "protocol file")] if args.protocol else []),
    )
    config = BenchConfig(
        n_modules=args.modules,
        effects=parse_effects(args.effect),
        seed=args.seed,
        outlier=args.outlier,
        outlier_shift=args.outlier_shift,
        datasheet=datasheet,
        rate=args.rate,
        validation_rate=args.validation_rate,
        hold=args.hold,
        n_validations=args.validations,
        validation_duration=args.validation_hours * 3600.0,
        fidelity=args.fidelity,
        validation_start=args.validation_start,
        physics=args.physics,
        rig=rig,
        protocol=protocol,
    )
    truth = simulate_batch(args.out, config, overwrite=args.overwrite)
    print(
        f"wrote {args.out}: {len(truth['modules'])} modules ({datasheet.name}), "
        f"effects: {', '.join(config.effects) or 'none'}, outlier: {config.outlier or 'none'}, seed {args.seed}, "
        f"rig: {truth['generator']['bench_rig']}"
    )
    return 0


def _cmd_inspect(args):
    from tembayes.data import load_batch, summarize_experiment
    from tembayes.data.preflight import ERROR

    batch = load_batch(args.batch, strict=False)
    ds = batch.datasheet
    errors = [f for f in batch.findings if f.severity == ERROR]
    report = {
        "batch": str(batch.path),
        "module_type": ds.to_table(),
        "derived_SI": {"S_V_per_K": ds.seebeck(), "R_ohm": ds.resistance(), "K_W_per_K": ds.conductance()},
        "rig": batch.rig_config,
        "modules": {
            mid: {e.path.name: summarize_experiment(e) for e in (m.identification, *m.validations)}
            for mid, m in batch.modules.items()
        },
        "findings": [f.to_json() for f in batch.findings],
    }
    if args.json:
        json.dump(report, sys.stdout, indent=2)
        print()
        return 2 if errors else 0
    rig = batch.rig_config.get("file") or batch.rig_config.get("preset", "reference")
    print(f"batch {batch.path}  type {ds.name or '?'}  rig {rig}")
    print(f"  datasheet -> S {ds.seebeck():.4g} V/K, R {ds.resistance():.4g} ohm, K {ds.conductance():.4g} W/K")
    cold = batch.layout.face[1]
    c = cold.removesuffix("_C")
    for mid, files in report["modules"].items():
        for name, q in files.items():
            print(
                f"  {mid:<8s} {name:<18s} {q['n_samples']:>7d} samples {q['duration_s'] / 3600:5.2f} h "
                f"dt {q['dt_median_s']:.3g} s  I {q['current_min_A']:+.2f}..{q['current_max_A']:+.2f} A  "
                f"{c} {q[cold + '_min']:.1f}..{q[cold + '_max']:.1f} C  noise {c} {1e3 * q[cold + '_noise']:.1f} mK"
            )
    for f in batch.findings:
        print(f"  {f.severity.upper()}: {f}")
    if errors:
        more = f" (and {len(errors) - 1} more problem(s), listed above)" if len(errors) > 1 else ""
        print(f"tembayes: error: {errors[0]}{more}", file=sys.stderr)
        return 2
    print("  no problems found" if not batch.findings else f"  {len(batch.findings)} warning(s), no errors")
    return 0


def _cmd_identify(args):
    from tembayes.data import load_batch
    from tembayes.data.outputs import check_output
    from tembayes.identify.pipeline import identify_batch, to_json
    from tembayes.physics.rigread import rig_from_config

    rig_from_config(None, args.leg_cells)  # refuse a bad option before any work
    check_output(args.out, kind="identify", inputs=[(args.batch, "batch folder")], overwrite=args.overwrite)
    batch = load_batch(args.batch)  # refused input: nothing is written
    _say_findings(batch.findings)

    results = identify_batch(batch, leg_cells=args.leg_cells, progress=_progress)

    def figures(tmp):
        from tembayes.plots.identify import save_identify_figures

        save_identify_figures(results, batch, tmp)

    _write_result(args, "identify.json", to_json(results, batch), None if args.no_figures else figures)
    for mid, r in results.items():
        f = r.fit
        print(
            f"{mid}: R0 {f['R0_ohm']:.4f} ohm  R1 {1e3 * f['R1_ohm_per_K']:.2f} mohm/K  "
            f"S0 {1e3 * f['S0_V_per_K']:.3f} mV/K  S1 {1e6 * f['S1_V_per_K2']:.1f} uV/K2  "
            f"K {r.rig_fit.values['K_W_per_K']:.3f} W/K"
        )
    print(f"wrote {args.out / 'identify.json'}" + ("" if args.no_figures else " and the figures"))
    return 0


def _cmd_calibrate(args):
    from tembayes.calibrate.batch import calibrate_batch
    from tembayes.calibrate.module import CalibrationOptions
    from tembayes.calibrate.runfolder import bytes_needed
    from tembayes.data import load_batch
    from tembayes.data.outputs import check_output
    from tembayes.data.preflight import raise_first_error

    workers = args.workers
    if workers < 1:  # before anything is touched
        print(f"tembayes calibrate: --workers must be at least 1, got {workers}", file=sys.stderr)
        return 2
    if args.scheduler:
        try:  # a wrong address is refused before anything is written
            from distributed import Client

            Client(
                args.scheduler if not os.path.isfile(args.scheduler) else None,
                scheduler_file=args.scheduler if os.path.isfile(args.scheduler) else None,
                timeout="10s",
            ).close()
        except (OSError, TimeoutError, ValueError) as exc:
            print(
                f"tembayes calibrate: cannot reach the Dask scheduler {args.scheduler!r} ({exc}); start one "
                "with `dask scheduler` and workers with `dask worker ADDRESS --nworkers N --nthreads 1`",
                file=sys.stderr,
            )
            return 2
    from tembayes.physics.effects import parse_effects

    sampled = tuple(spec.strip() for spec in args.effect or () if "=" not in spec)
    fixed = parse_effects([spec for spec in args.effect or () if "=" in spec])
    parse_effects(sampled)  # names checked, none twice
    opt = CalibrationOptions(
        max_steps=args.max_steps,
        nwalkers=args.walkers,
        model=args.model,
        effects=sampled,
        effect_values={k: v for values in fixed.values() for k, v in values.items()},
        discrepancy=args.discrepancy,
    )
    check_output(
        args.out,
        kind="calibrate",
        inputs=[(args.batch, "batch folder")],
        overwrite=args.overwrite or args.resume,
        need_bytes=bytes_needed(1, workers),
    )
    # every file validated, then only paths kept: memory independent of the batch size
    batch = load_batch(args.batch, lazy=True)  # refused input: nothing is written
    raise_first_error(batch.findings, command="calibrate")
    _say_findings(batch.findings)
    earlier = None
    if args.population_prior is not None:
        from tembayes.calibrate.earlier import population_prior_of_run

        earlier = population_prior_of_run(args.population_prior, batch.datasheet.name)
    if args.unit_prior is not None:
        from tembayes.calibrate.earlier import unit_prior_of_run

        opt = dataclasses.replace(opt, law_prior=unit_prior_of_run(args.unit_prior, batch.datasheet.name))
    summ = calibrate_batch(
        batch,
        args.out,
        seed=args.seed,
        options=opt,
        resume=args.resume,
        overwrite=args.overwrite,
        progress=_progress,
        progress_bar=not args.quiet,
        argv=args.argv,
        workers=workers,
        scheduler=args.scheduler,
        keep_unconverged=args.keep_unconverged,
        population_prior=earlier,
    )
    if not args.no_figures:
        from tembayes.plots.calibrate import save_calibration_figures

        _progress("figures")
        save_calibration_figures(args.out)
    mods = summ.modules
    shown = list(mods)
    if len(mods) > 20:  # a factory batch: the likeliest outliers and the failures, then the counts
        shown = sorted(mods, key=lambda k: -(mods[k].outlier_prob or 0.0))[:10]
    for mid in shown:
        m = mods[mid]
        law = m.laws
        print(
            f"{mid}: R0 {law['R0_ohm'].mean:.4f}+-{law['R0_ohm'].sd:.4f} ohm  "
            f"S0 {1e3 * law['S0_V_per_K'].mean:.3f}+-{1e3 * law['S0_V_per_K'].sd:.3f} mV/K  "
            f"K {law['K_W_per_K'].mean:.4f}+-{law['K_W_per_K'].sd:.4f} W/K  "
            f"outlier_prob {'-' if m.outlier_prob is None else f'{m.outlier_prob:.2f}'}  "
            f"{'converged' if m.converged else 'NOT CONVERGED'}"
        )
        if m.adequacy_failed:
            print(
                f"  {mid}: the model does not fit its identification run: "
                + "; ".join(m.adequacy_reasons)
                + f". The laws rest on it: run `tembayes gap {args.out} {args.batch}` to find what is missing"
            )
    if len(shown) < len(mods):
        n_conv = sum(m.converged for m in mods.values())
        print(f"... the {len(shown)} likeliest outliers of {len(mods)} calibrated modules shown; {n_conv} converged")
    for mid, why in summ.population_excluded.items():
        print(f"{mid}: left out of the population: {why}")
    from tembayes.report.outliers import OutlierAnswer

    answer = OutlierAnswer.of(summ)
    if answer is not None:
        print("\n".join(answer.lines()))
    print(f"wrote {args.out / 'summary.json'} and {args.out / 'posterior.nc'}")
    return 0 if summ.converged else 1


def _write_result(args, name, doc, figures):
    """``args.out/name`` (the command line and version added) and the figures (None: none), as one atomic folder."""
    from tembayes.data import write_json
    from tembayes.data.write import atomic_directory

    with atomic_directory(args.out, overwrite=args.overwrite, kind=args.command) as tmp:
        doc["command"] = "tembayes " + " ".join(args.argv)
        doc["tembayes_version"] = tembayes.__version__
        write_json(tmp / name, doc)
        if figures is not None:
            figures(tmp)


def _run_batch(args, run):
    """The batch of ``--batch``, or the one recorded in ``RUN/summary.json``, checked against the run's digests."""
    from tembayes.calibrate.run import load_run_batch

    batch, notes = load_run_batch(run, args.batch)
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    _say_findings(batch.findings)
    return batch


def _progress(msg):
    print(msg, file=sys.stderr, flush=True)


def _say_findings(findings):
    """The preflight's warnings on the batch, one line each on stderr."""
    for f in findings:
        print(f"warning: {f}", file=sys.stderr)


def _check_out(args, kind, *inputs):
    """``check_output`` for a command reading a run (and more): the run and the other inputs are never touched."""
    from tembayes.data.outputs import check_output

    check_output(
        args.out,
        kind=kind,
        overwrite=args.overwrite,
        inputs=[(args.run, "run folder"), *((p, r) for p, r in inputs if p is not None)],
    )


def _cmd_export(args):
    from tembayes.calibrate.run import load_run
    from tembayes.export.formats import write_export
    from tembayes.export.observer import observer_inputs

    fmt = args.format or (args.out.suffix.lstrip(".").lower() or None)
    if fmt not in ("json", "npz", "mat"):
        print(f"tembayes export: give --format json, npz or mat (FILE {args.out} has no such suffix)", file=sys.stderr)
        return 2
    points = []
    for text in args.point or ():
        try:
            tavg, current = (float(x) for x in text.split(","))
        except ValueError:
            print(
                f"tembayes export: --point {text!r}: expected T_AVG_C,CURRENT_A, e.g. --point 30,0.5", file=sys.stderr
            )
            return 2
        points.append((tavg, current))
    _check_out(args, "export", (args.batch, "batch folder"))
    run = load_run(args.run)  # refused inputs: nothing is written
    batch = _run_batch(args, run)
    _check_out(args, "export", (batch.path, "batch folder"))
    exp = observer_inputs(
        run,
        batch,
        points=points or None,
        room_C=args.ambient,
        allow_extrapolation=args.allow_extrapolation,
        n_draws=args.draws,
        seed=args.seed,
        modules=args.module,
        heldout=args.heldout or True,
        progress=_progress,
    )
    write_export(exp, args.out, fmt)
    for mid, m in exp.modules.items():
        pn = m.process_noise
        print(
            f"{mid}: {len(exp.parameters)} parameters, {len(m.linear)} operating points; process noise "
            + ", ".join(f"{c} {1e3 * s:.2g} m/{t:.0f} s" for c, s, t in zip(pn["channels"], pn["sd"], pn["tau_s"]))
        )
    for w in exp.warnings:
        print(f"warning: {w} (recorded in the file's meta.warnings)", file=sys.stderr)
    print(
        f"wrote {args.out} ({fmt}; operating points "
        + ", ".join(f"{t:.4g} C/{i:.4g} A" for t, i in exp.meta["points"])
        + ")"
    )
    return 0


def _cmd_rig(args):
    from tembayes.data.outputs import check_output
    from tembayes.physics.rigread import rig_file_of, rig_source
    from tembayes.physics.rigsummary import summarise_rig

    rig = rig_file_of(rig_source(args.rig))  # refused input: nothing is written
    check_output(args.out, kind="rig", inputs=[(rig.path, "rig file")], overwrite=args.overwrite)
    summary = summarise_rig(rig) if args.module_k is None else summarise_rig(rig, args.module_k)

    def figures(tmp):
        from tembayes.plots.rig import save_rig_figure

        save_rig_figure(summary, tmp / "rig.png")

    _write_result(args, "rig.json", summary.to_json(), figures)
    print(f"rig '{rig.name}': {rig.description}")
    width = max(len(p.name) for p in rig.parameters)
    for p in rig.parameters:
        held = "  (held)" if p.held else ""
        print(f"  {p.name:<{width}}  {p.nominal:<10.4g} [{p.low:.4g}, {p.high:.4g}] {p.unit:<4} {p.doc}{held}")
    print("CSV columns: time_s, current_A, voltage_V, " + ", ".join([*rig.sensors, *rig.boundaries.values()]))
    taus = ", ".join(f"{t:.0f} s" for t in summary.time_constants[:3])
    print(f"slowest time constants (module K {summary.module_k:g} W/K): {taus}")
    for share, t in summary.hold_times.items():
        print(f"a staircase hold of {t / 60:.1f} min brings every sensor within {100 * share:g} % of its step's move")
    print(f"wrote {args.out / 'rig.json'} and rig.png")
    return 0


def _check_temperature_limits(low_C, high_C):
    """Refuse ``--min-temperature`` / ``--max-temperature`` that are not numbers or not in order [degC]."""
    for name, v in (("--min-temperature", low_C), ("--max-temperature", high_C)):
        if v is not None and not -KELVIN < v < 500.0:
            raise ModelError(f"{name} {v:g}: give a sensor temperature in degC, e.g. {name} 12")
    if low_C is not None and high_C is not None and not low_C < high_C:
        raise ModelError(f"--min-temperature {low_C:g} is not below --max-temperature {high_C:g}")


def _cmd_design(args):
    from tembayes.data import load_batch_toml
    from tembayes.data.outputs import check_output
    from tembayes.design.search import (
        REFERENCE_RATIO_ERROR,
        REFERENCE_SLACK,
        Designer,
        design,
        design_json,
        parse_target,
    )
    from tembayes.physics.rigread import rig_source

    targets = [parse_target(t) for t in args.target]  # refused input: nothing is written
    _check_temperature_limits(args.min_temperature, args.max_temperature)
    datasheet, rig_config = load_batch_toml(args.batch_or_toml)
    if args.rig:
        rig_config = rig_source(args.rig)
    check_output(args.out, kind="design", inputs=[(args.batch_or_toml, "batch or datasheet")], overwrite=args.overwrite)
    law_prior = None
    if args.population is not None:
        from tembayes.calibrate.earlier import unit_prior_of_run

        law_prior = unit_prior_of_run(args.population, datasheet.name)
    designer = Designer(
        datasheet,
        rig_config,
        seed=args.seed,
        n_draws=args.draws,
        jobs=args.jobs,
        say=_progress,
        law_prior=law_prior,
        rate_hz=args.rate,
    )
    d = design(
        designer,
        targets or None,
        max_hours=args.max_hours,
        min_hold_s=args.min_hold,
        min_temperature_K=None if args.min_temperature is None else args.min_temperature + KELVIN,
        max_temperature_K=None if args.max_temperature is None else args.max_temperature + KELVIN,
    )

    def files(tmp):
        from tembayes.design.protocol import write_protocol
        from tembayes.plots.design import save_design_figure

        write_protocol(tmp / "protocol.csv", d.best.protocol)
        save_design_figure(d, tmp / "design.png")

    _write_result(args, "design.json", design_json(d, designer), files)
    best, ref = d.best, d.reference
    turns = "/".join(f"{v:+.3g}" for v in best.turns_for(datasheet.imax))
    lo, hi = (t - KELVIN for t in best.sensor_range_K)
    print(
        f"design: {len(best.protocol.levels)} levels, step {best.step_for(datasheet.imax):.3g} A, turning at "
        f"{turns} A, hold {best.hold_s:g} s, sampled at {best.rate_Hz:g} Hz: {best.duration_s / 3600:.2f} h against "
        f"the reference's {ref.duration_s / 3600:.2f} h at {ref.rate_Hz:g} Hz; sensors {lo:.1f}-{hi:.1f} degC "
        f"(limits {d.limits_K[0] - KELVIN:.1f}-{d.limits_K[1] - KELVIN:.1f})"
    )
    for k, v in best.sd_rel().items():
        print(f"  {k:<14s} expected sd {100 * v:.3f} %  (reference {100 * ref.sd_rel()[k]:.3f} %)")
    if d.targets_are_the_reference:
        longer = min(
            (e.hold_s for e in d.evaluated if best.hold_s < e.hold_s < ref.hold_s and e.within(d.limits_K)),
            default=None,
        )
        hold_longer = f" or hold longer (--min-hold {longer:g})" if longer else ""
        print(
            f"  caution: 'as narrow as the reference (within {100 * REFERENCE_SLACK:g} %)' is a prediction; out-of-model, "
            f"short holds came out up to {100 * REFERENCE_RATIO_ERROR:g} % wider against the reference than predicted. "
            f"Try the design (below){hold_longer}; docs/design.md"
        )
    cfg = rig_config or {}
    rig = cfg.get("file") or cfg.get("preset")
    rig = None if rig == "reference" else rig  # simulate's default: the reference rig's own bench
    trial = f"--protocol {args.out / 'protocol.csv'} --rate {best.rate_Hz:g} --datasheet {args.batch_or_toml}"
    print(f"wrote {args.out / 'protocol.csv'}, design.json and design.png; try it: tembayes simulate OUT {trial}"
          + (f" --rig {rig}" if rig else ""))  # fmt: skip
    if law_prior is not None:
        print(
            f"the widths assume {law_prior.source} as the unit's prior: calibrate with --unit-prior {args.population}"
        )
    return 0


def _cmd_report(args):
    from tembayes.calibrate.run import load_run
    from tembayes.report import build_report, write_report
    from tembayes.report.tolerances import DEFAULT_TOLERANCES, parse_tolerance

    tolerances = args.tolerance or list(DEFAULT_TOLERANCES)
    try:
        for t in tolerances:
            parse_tolerance(t)
    except ValueError as err:
        print(f"tembayes report: {err}", file=sys.stderr)
        return 2
    if not 0.5 <= args.confidence < 1.0:
        print(f"tembayes report: --confidence must be in [0.5, 1), got {args.confidence}", file=sys.stderr)
        return 2
    _check_out(
        args,
        "report",
        (args.batch, "batch folder"),
        *((d, "gap folder") for d in args.gap or ()),
        *((d, "predict folder") for d in args.predict or ()),
    )
    run = load_run(args.run)  # refused inputs: nothing is written
    batch = _run_batch(args, run)
    _check_out(args, "report", (batch.path, "batch folder"))
    rep = build_report(
        run,
        batch,
        tolerances=tolerances,
        confidence=args.confidence,
        validate=not args.no_validation,
        predict_dirs=args.predict or (),
        gap_dirs=args.gap or (),
        n_draws=args.draws,
        seed=args.seed,
        max_figure_modules=args.max_figure_modules,
        command="tembayes " + " ".join(args.argv),
        progress=_progress,
    )
    path = write_report(rep, args.out, overwrite=args.overwrite)
    for m in rep.modules:
        failed = [c["check"] for c in m["acceptance"]["checks"] if not c["passed"]]
        print(f"{m['id']}: {'PASS' if not failed else 'FAIL (' + ', '.join(failed) + ')'}")
    print(f"wrote {path}")
    return 0


def _cmd_predict(args):
    from tembayes.calibrate.run import load_run
    from tembayes.data import load_experiment
    from tembayes.data.preflight import check_experiment, raise_first_error
    from tembayes.predict.predictive import predict

    if args.draws < 10:
        print(f"tembayes predict: --draws must be at least 10, got {args.draws}", file=sys.stderr)
        return 2
    _check_out(args, "predict", (args.batch, "batch folder"), (args.experiment, "experiment file"))
    run = load_run(args.run)  # refused inputs: nothing is written
    if args.module != "population" and args.module not in run.module_ids:
        raise DataError(
            args.run / "posterior.nc",
            f"has no module '{args.module}'",
            f"Choose one of {list(run.module_ids)} or 'population'.",
        )
    batch = _run_batch(args, run)
    _check_out(args, "predict", (batch.path, "batch folder"), (args.experiment, "experiment file"))
    exp = load_experiment(args.experiment, datasheet=batch.datasheet, layout=batch.layout)
    findings = check_experiment(exp, datasheet=batch.datasheet, layout=batch.layout)
    raise_first_error(findings)
    _say_findings(findings)
    result = predict(
        run,
        exp,
        args.module,
        batch,
        n_draws=args.draws,
        seed=args.seed,
        compare_constant=not args.no_constant,
        keep_predictive=args.netcdf,
        progress=_progress,
    )
    _write_predict(args, result)
    for ch, m in result.linear.metrics().items():
        unit = "V" if ch == "voltage_V" else "K"
        print(
            f"{ch}: RMSE {m['rmse']:.4g} {unit}  max {m['max_abs']:.4g} {unit}  "
            f"coverage 50/90/95 % {100 * m['coverage50']:.0f}/{100 * m['coverage90']:.0f}/"
            f"{100 * m['coverage95']:.0f} %"
        )
    print(f"wrote {args.out / 'metrics.json'}" + (" and predictive.nc" if args.netcdf else ""))
    return 0


def _write_predict(args, result):
    """``metrics.json``, the figures and, with ``--netcdf``, ``predictive.nc``, as one atomic folder."""
    from tembayes.data import write_json
    from tembayes.data.write import atomic_directory
    from tembayes.plots.predict import save_predict_figures
    from tembayes.predict.inference import PREDICTIVE_FILE, write_predictive

    doc = result.to_json()
    if args.netcdf:
        doc["predictive_netcdf"] = PREDICTIVE_FILE
    with atomic_directory(args.out, overwrite=args.overwrite, kind=args.command) as tmp:
        doc["command"] = "tembayes " + " ".join(args.argv)
        doc["tembayes_version"] = tembayes.__version__
        write_json(tmp / "metrics.json", doc)
        if args.netcdf:
            write_predictive(result, tmp / PREDICTIVE_FILE)
        if not args.no_figures:
            save_predict_figures(result, tmp)


def _cmd_gap(args):
    from tembayes.calibrate.run import load_run
    from tembayes.gap.diagnose import diagnose

    _check_out(args, "gap", (args.batch, "batch folder"))
    run = load_run(args.run)  # refused inputs: nothing is written
    batch = _run_batch(args, run)
    diag = diagnose(
        run,
        batch,
        exclude=args.exclude or (),
        candidates=args.candidates,
        n_draws=args.draws,
        seed=args.seed,
        jobs=args.jobs,
        progress=_progress,
    )
    from tembayes.data import write_json
    from tembayes.data.write import atomic_directory
    from tembayes.gap.conflicts import is_immaterial
    from tembayes.gap.ranking import RECALIBRATED
    from tembayes.gap.recalibrated import write_recalibrated_run
    from tembayes.plots.gap import save_gap_figures

    with atomic_directory(args.out, overwrite=args.overwrite, kind="gap") as tmp:
        doc = diag.to_json()
        recal = write_recalibrated_run(diag, run, batch, tmp / "run", seed=args.seed, progress=_progress)
        if recal is not None:
            doc["recalibrated"] = recal
        doc["command"] = "tembayes " + " ".join(args.argv)
        doc["tembayes_version"] = tembayes.__version__
        write_json(tmp / "gap.json", doc)
        if not args.no_figures:
            save_gap_figures(diag, tmp)
    print(f"verdict: {diag.verdict}" + (f" -- best: {diag.best}" if diag.best else ""))
    if len(diag.best_group) > 1:
        print(f"  the data cannot tell apart: {', '.join(diag.best_group)}")
    for w in diag.where[:5]:
        print(f"  where: {w['channel']}, {w['regime']} (score {w['score']:.2f})")
    for mid, rows in diag.conflicts.items():
        for c in rows:
            if is_immaterial(c):
                print(
                    f"  does not matter: {mid} {c['parameter']} {c['median']:.4g} {c['unit']} (documented "
                    f"{c['low']:.4g}-{c['high']:.4g}; held at its edge, the held-out windows and the laws stay)"
                )
    if diag.gap_in:
        print(f"  gap in: {', '.join(diag.gap_in)}")
    for r in diag.screen[:3]:
        if r.log_bayes_factor is not None:
            base_chi2 = diag.base.refits[r.refit.module_id].chi2_total
            print(
                f"  screen: {r.effect:20s} log Bayes factor {r.log_bayes_factor:+.4g} on the identification "
                f"run (chi2 per sample {r.refit.chi2_total:.3f}; the base model's {base_chi2:.3f})"
            )
    scale, unit = (1e3, "mK") if diag.primary == "validation" else (1.0, "noise sd (identification windows)")
    for r in diag.ranking:
        if r.evidence is None:
            print(f"  {r.effect:20s} failed: {r.failed}")
        elif r.kind == RECALIBRATED:
            before, after = r.gaps.on()
            print(
                f"  {r.effect:20s} evidence {r.evidence.value:+.4g} +- {r.evidence.se:.3g} nats  "
                f"gap {scale * before:.3g} -> {scale * after:.3g} {unit} (shrink {r.gaps.shrink():.0%})"
            )
        elif r.dropped:
            print(f"  {r.effect:20s} dropped: {r.dropped}")
    if diag.best and diag.recalibration:
        print(f"  recalibrated with {diag.best}: {args.out / 'run'} (predict, report and export take it)")
    print(f"wrote {args.out / 'gap.json'}")
    return 0


def _add_batch_option(p):
    """``--batch``: the run's batch, when not the one recorded in ``RUN/summary.json`` (see :func:`_run_batch`)."""
    p.add_argument(
        "--batch",
        type=Path,
        metavar="BATCH",
        help="the calibrated batch folder (default: the one recorded in RUN/summary.json)",
    )


def build_parser():
    """The argument parser of the ``tembayes`` command."""
    parser = argparse.ArgumentParser(
        prog="tembayes",
        description="Bayesian uncertainty quantification of thermoelectric-module parameters.",
        epilog="Run 'tembayes COMMAND --help' for a command's options and an example.",
    )
    parser.add_argument("--version", action="version", version=f"tembayes {tembayes.__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    _add_simulate(sub)
    _add_identify(sub)
    _add_calibrate(sub)
    _add_predict(sub)
    _add_gap(sub)
    _add_report(sub)
    _add_export(sub)
    _add_inspect(sub)
    _add_rig(sub)
    _add_design(sub)
    return parser


def _add_simulate(sub):
    """The ``tembayes simulate`` subcommand."""
    p = sub.add_parser(
        "simulate",
        help="make a synthetic batch on the virtual bench",
        description="Make a synthetic batch folder (docs/data-format.md, 'The batch folder') plus truth.json on the "
        "virtual bench: a higher-fidelity rig and module than the calibration model, with "
        "unit-to-unit spread, sensor noise and drifts of the boundary temperatures.",
        epilog=_EPILOG_SIMULATE.format(effects=_effects_table()),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("out", type=Path, help="batch folder to create (refused if it exists, see --overwrite)")
    p.add_argument("--modules", type=int, default=3, metavar="N", help="modules in the batch (default 3)")
    p.add_argument(
        "--effect",
        action="append",
        default=[],
        metavar="NAME[=VALUE]",
        help="switch on a catalogue effect (repeatable)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--outlier", metavar="ID", help="module id whose S0 sits apart, e.g. TEM1")
    p.add_argument(
        "--outlier-shift", type=float, default=0.04, metavar="F", help="relative S0 shift of the outlier (default 0.04)"
    )
    p.add_argument(
        "--datasheet",
        type=Path,
        metavar="TOML",
        help="a batch.toml-style file whose [module_type] sets the module type (default TEC1-12706)",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=5.0,
        metavar="HZ",
        help="sampling rate of the identification runs (default 5 Hz, the reference rig's)",
    )
    p.add_argument(
        "--validation-rate", type=float, metavar="HZ", help="sampling rate of the validation runs (default: --rate)"
    )
    p.add_argument("--hold", type=float, default=600.0, metavar="S", help="identification hold (default 600 s)")
    p.add_argument(
        "--protocol",
        type=Path,
        metavar="CSV",
        help="the identification run's current program (time_s,current_A, e.g. tembayes design's protocol.csv; "
        "plus plate_C, the plates' setpoint, on plates that hold both faces) instead of the staircase with --hold",
    )
    p.add_argument("--validations", type=int, default=1, metavar="K", help="validation runs per module (default 1)")
    p.add_argument(
        "--validation-hours", type=float, default=4.0, metavar="H", help="length of a validation run (default 4 h)"
    )
    p.add_argument(
        "--fidelity",
        choices=("standard", "high"),
        default="standard",
        help="standard: the calibration model's structure, finer steps (proves the code); high: a rig "
        "and module the model does not contain -- finer steel, the module's layers, sensor bodies "
        "at uncertain depths, Thomson heat, K(T), re-mounting spread, slow sensor noise (measures "
        "the method); with --rig: the rig file's network plus sensor bodies and leads, module edge "
        "leaks, re-mounting spread and slow sensor noise",
    )
    p.add_argument(
        "--physics",
        choices=("paper", "full"),
        default="full",
        help="the standard bench's physics: that of a calibration model form (default full, the "
        "default model's; paper: Evers et al.'s form)",
    )
    p.add_argument(
        "--validation-start",
        choices=("steady", "rest"),
        default="steady",
        help="steady: a validation run starts with 300 s at 0 A; rest: the rig at rest and the current "
        "switched straight to the first level",
    )
    p.add_argument(
        "--rig",
        metavar="RIG",
        help="a shipped rig (reference, reference-faces, heatsink-al, liquid-plates) or a rig file: the batch has "
        "that rig's columns and [rig] entry, simulated at a finer resolution than the calibration's (default: the "
        "reference rig's benches)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace OUT if it exists")
    p.set_defaults(func=_cmd_simulate)


def _add_identify(sub):
    """The ``tembayes identify`` subcommand."""
    p = sub.add_parser(
        "identify",
        help="the paper's deterministic step method (per-step R and S, linear fits, rig fit)",
        description="The classical step identification (Evers et al. 2020, Algorithm 1, after Mitrani "
        "et al. 2004), done carefully: R from the voltage jump extrapolated to the step instant, S "
        "from each hold's steady state with the junction temperatures reconstructed through the rig, "
        "linear laws with standard errors, a hysteresis check, the deterministic rig fit and the "
        "validation of constant vs temperature-dependent laws.  The paper's literal recipe is "
        "reported alongside (fit_paper).",
        epilog=_EPILOG_IDENTIFY,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("batch", type=Path, help="batch folder")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder to create")
    p.add_argument(
        "--leg-cells",
        type=int,
        default=0,
        metavar="N",
        help="resolve the module's legs into N cells in the rig fit and validation (default 0: "
        "the paper's lumped module)",
    )
    p.add_argument("--no-figures", action="store_true", help="write identify.json only")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it is an earlier identify output")
    p.set_defaults(func=_cmd_identify)


def _add_calibrate(sub):
    """The ``tembayes calibrate`` subcommand."""
    p = sub.add_parser(
        "calibrate",
        help="Bayesian calibration: per-module posteriors and the batch population",
        description="Sample each module's posterior of R0, R1, S0, S1 and K (plus the rig's thermal "
        "nuisance parameters, the step instant and the noise) with emcee from the step responses of "
        "its identification run, until converged (50 autocorrelation times, R-hat <= 1.01, bulk "
        "ESS >= 1000), then the batch's population with each module's outlier probability.  Exit "
        "status 1 when a module or the population did not converge (results are written and marked).",
        epilog=_EPILOG_CALIBRATE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("batch", type=Path, help="batch folder")
    p.add_argument("--out", type=Path, required=True, metavar="RUN", help="run folder to create")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run in RUN")
    p.add_argument("--overwrite", action="store_true", help="replace RUN if it exists")
    p.add_argument(
        "--max-steps", type=int, default=60000, metavar="N", help="sampler budget per module (default 60000 steps)"
    )
    p.add_argument("--walkers", type=int, metavar="N", help="emcee walkers (default 2 x parameters + 2)")
    p.add_argument(
        "--model",
        choices=("paper", "full"),
        default="full",
        help="the model's physics: full (default: Thomson heat, the plates' two layers, the sensors' "
        "response time and depth, a temperature slope of K) or paper (Evers et al.'s form)",
    )
    p.add_argument(
        "--discrepancy",
        choices=("none", "window-sandwich", "robust"),
        default="robust",
        help="for a model that is not the rig: window-sandwich widens the laws' posterior to the scatter "
        "of the step windows' scores; robust (default) also carries over the uncertainty of the rig "
        "parameters held fixed; none trusts the model",
    )
    p.add_argument(
        "--effect",
        action="append",
        metavar="NAME[=VALUE]",
        help="add a catalogue effect to the model (repeatable): its size sampled under its prior, or "
        "fixed at VALUE (the first parameter's, SI; see tembayes simulate --help)",
    )
    p.add_argument("--no-figures", action="store_true", help="skip the corner plots")
    p.add_argument("--quiet", action="store_true", help="no progress bars (stage messages only)")
    p.add_argument(
        "--workers",
        type=int,
        default=min(2, os.cpu_count() or 1),
        metavar="N",
        help="modules calibrated at once, on a local Dask cluster of N single-threaded processes "
        "(default: %(default)s; 1: in this process, with stage messages); the results do not "
        "depend on it",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="calibrate the modules on a running dask.distributed cluster (tcp://host:8786, or a "
        "scheduler file) instead; its workers need tembayes installed",
    )
    p.add_argument(
        "--keep-unconverged",
        action="store_true",
        help="let modules that did not converge into the population (default: left out, with the "
        "reason in summary.json)",
    )
    p.add_argument(
        "--population-prior",
        type=Path,
        metavar="EARLIER_RUN",
        help="start from the unit-to-unit spreads an earlier run of the same module type learned "
        "(its summary.json's population_spreads), combined with batch.toml's [population]; chained "
        "over batches, the spreads sharpen",
    )
    p.add_argument(
        "--unit-prior",
        type=Path,
        metavar="EARLIER_RUN",
        help="each module's prior on the laws is the population of an earlier run of the same module "
        "type (its predictive for a new unit) instead of the datasheet's: for a new unit of a known "
        "type after a short test (tembayes design --population)",
    )
    p.set_defaults(func=_cmd_calibrate)


def _add_predict(sub):
    """The ``tembayes predict`` subcommand."""
    p = sub.add_parser(
        "predict",
        help="posterior-predictive bands of an experiment for a calibrated module or a new unit",
        description="Simulate an experiment (e.g. a validation run) for posterior draws of a module "
        "-- laws, K, the rig's thermal parameters (those the step likelihood leaves open anchored on "
        "the identification run), the step instants and the noise -- from its measured current and "
        "boundary temperatures, and compare the measurements with the central 50/90/95 % bands.",
        epilog=_EPILOG_PREDICT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run", type=Path, help="calibration run folder (tembayes calibrate --out)")
    p.add_argument("experiment", type=Path, help="experiment CSV (docs/data-format.md, 'CSV columns')")
    p.add_argument("--module", required=True, metavar="ID", help="module id of the run, or 'population'")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder to create")
    _add_batch_option(p)
    p.add_argument("--draws", type=int, default=500, metavar="N", help="predictive draws (default 500)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--no-constant", action="store_true", help="skip the constant-law comparison")
    p.add_argument(
        "--netcdf",
        action="store_true",
        help="also write DIR/predictive.nc: ArviZ InferenceData with every predictive draw "
        "(posterior_predictive) and the measurements (observed_data); draws x samples x 20 bytes",
    )
    p.add_argument("--no-figures", action="store_true", help="write metrics.json (and predictive.nc) only")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    p.set_defaults(func=_cmd_predict)


def _add_gap(sub):
    """The ``tembayes gap`` subcommand."""
    p = sub.add_parser(
        "gap",
        help="diagnose the sim-to-real gap of a calibrated batch on its held-out runs",
        description="Where the calibrated model and the held-out measurements (validation*.csv) part "
        "(a gap map per channel and operating regime), which catalogue effect causes it (every effect "
        "refitted on the identification run with the base model as control, the rig parameters calibrated "
        "outside their documented range, then the strongest candidates recalibrated with the effect added and ranked by held-out evidence), and how "
        "far the gap shrinks with it; a verdict no_gap / explained / partially_explained / unexplained.",
        epilog=_EPILOG_GAP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run", type=Path, help="calibration run folder (tembayes calibrate --out)")
    p.add_argument("batch", type=Path, help="the calibrated batch folder (its validation*.csv are held out)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder to create")
    p.add_argument(
        "--exclude",
        action="append",
        metavar="EFFECT",
        help="withhold a catalogue effect from the diagnosis (repeatable)",
    )
    p.add_argument(
        "--candidates",
        type=int,
        default=2,
        metavar="K",
        help="candidates recalibrated (default 2, plus one a range conflict points at)",
    )
    p.add_argument(
        "--draws", type=int, default=200, metavar="N", help="predictive draws per held-out run (default 200)"
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        metavar="N",
        help="refits and recalibrations at once, in worker processes (default: the cores + 1)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--no-figures", action="store_true", help="write gap.json only")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    p.set_defaults(func=_cmd_gap)


def _add_report(sub):
    """The ``tembayes report`` subcommand."""
    p = sub.add_parser(
        "report",
        help="batch-calibration report: one self-contained HTML file with pass/fail per module",
        description="A report a quality engineer reads for a calibrated batch: acceptance against tolerances, "
        "batch overview and data quality, laws with bands over the step estimates, modules against the "
        "population with outlier probabilities, hysteresis, convergence, corner plots, validation bands and "
        "metrics, the gap diagnosis, and the versions, seed and commands that produced it.",
        epilog=_EPILOG_REPORT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run", type=Path, help="calibration run folder (tembayes calibrate --out)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder to create (report.html)")
    _add_batch_option(p)
    p.add_argument(
        "--tolerance",
        action="append",
        metavar="SPEC",
        help="acceptance check (repeatable; replaces the defaults, see below)",
    )
    p.add_argument(
        "--confidence",
        type=float,
        default=0.95,
        help="posterior probability of the tolerance range that passes (default 0.95)",
    )
    p.add_argument(
        "--gap",
        action="append",
        metavar="DIR",
        type=Path,
        help="a `tembayes gap` output folder to summarise (repeatable)",
    )
    p.add_argument(
        "--predict",
        action="append",
        metavar="DIR",
        type=Path,
        help="a `tembayes predict` output folder to include instead of computing that module's bands",
    )
    p.add_argument(
        "--no-validation", action="store_true", help="do not compute posterior-predictive bands on the validation runs"
    )
    p.add_argument(
        "--draws", type=int, default=200, metavar="N", help="posterior draws per validation prediction (default 200)"
    )
    p.add_argument(
        "--max-figure-modules",
        type=int,
        default=12,
        metavar="N",
        help="modules given their own figures, likeliest outliers first (default 12)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed of the validation draws (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it exists")
    p.set_defaults(func=_cmd_report)


def _add_export(sub):
    """The ``tembayes export`` subcommand."""
    p = sub.add_parser(
        "export",
        help="uncertainty inputs for observer design: posterior moments, noise, linearised rig model",
        description="Per module and for a new unit of the batch: the posterior mean and covariance of the "
        "laws, K and the rig parameters (and thinned draws), the sensors' measurement-noise covariance, a "
        "process-noise suggestion (an OU disturbance per output, fitted to the held-out residuals), and the "
        "rig linearised at operating points (A, B, C, D, state/input/output names) with its sensitivities "
        "to the parameters.  Schema: docs/outputs.md, 'The export file (export)'.",
        epilog=_EPILOG_EXPORT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("run", type=Path, help="calibration run folder (tembayes calibrate --out)")
    p.add_argument("--out", type=Path, required=True, metavar="FILE", help="file to write")
    p.add_argument("--format", choices=("json", "npz", "mat"), help="default: FILE's suffix")
    _add_batch_option(p)
    p.add_argument(
        "--point",
        action="append",
        metavar="T_AVG_C,CURRENT_A",
        help="operating point to linearise at (repeatable; default: the identification runs' steady "
        "states at their lowest, nearest-zero and highest current); refused outside the calibrated range",
    )
    p.add_argument(
        "--allow-extrapolation",
        action="store_true",
        help="export --point values outside the calibrated range too, with a warning recorded in the file",
    )
    p.add_argument(
        "--ambient",
        type=float,
        default=None,
        metavar="C",
        help="temperature of the room the rig leaks to at the operating points [C] (default: the identification "
        "runs' median)",
    )
    p.add_argument("--module", action="append", metavar="ID", help="only these modules (repeatable)")
    p.add_argument("--draws", type=int, default=200, metavar="N", help="posterior draws kept per module")
    p.add_argument(
        "--heldout",
        action="append",
        metavar="NAME",
        help="fit the process noise on this validation run only (file name, repeatable; default: "
        "every validation run) -- keeps another run unseen for checking an observer",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace FILE if it exists")
    p.set_defaults(func=_cmd_export)


def _add_inspect(sub):
    """The ``tembayes inspect`` subcommand."""
    p = sub.add_parser(
        "inspect",
        help="load and validate a batch folder, print a data-quality summary",
        description="Load a batch folder with every check of docs/data-format.md and print, per experiment, "
        "samples, duration, sampling interval, current and temperature ranges and noise.",
        epilog=_EPILOG_INSPECT,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("batch", type=Path, help="batch folder")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=_cmd_inspect)


_EPILOG_RIG = """\
example:
  tembayes rig reference --out rig_check              # a shipped rig
  tembayes rig my_rig.toml --out rig_check --module-k 0.3
"""


_EPILOG_DESIGN = """\
examples:
  tembayes design data/example --out runs/design                       # the reference's R0, S0, K widths
  tembayes design data/example --out runs/design --target R0_ohm=0.3% --target K_W_per_K=0.5% --max-hours 2
  tembayes simulate runs/short --protocol runs/design/protocol.csv --rate 2 --fidelity high   # then try it (its rate)
  tembayes design data/example --out runs/slow-logger --rate 1       # a rig logged at 1 Hz
  tembayes design data/example --out runs/cool --max-temperature 65   # no sensor above 65 degC during the test
  tembayes design data/example --out runs/unit-design --population runs/lot42 --target R0_ohm=0.5% --target S0_V_per_K=0.5% --max-hours 0.75
  tembayes calibrate spares/unit7 --out runs/unit7 --unit-prior runs/lot42   # that unit, under lot 42's population

Targets are posterior sds, relative (PARAM=SD%) or absolute in SI (PARAM=SD).  The expected widths
come from modules the bench draws from the type, each run simulated and linearised as the calibration
would (Laplace, plus the rig parameters the calibration holds fixed).  The shortest staircase found
is sampled as slowly as the targets allow (design.json: staircase.sampling_rate_Hz).  No candidate's
sensors leave the temperature limits (default: the reference staircase's own range, within 1 K);
docs/design.md.
"""


def _add_design(sub):
    """The ``tembayes design`` subcommand."""
    p = sub.add_parser(
        "design",
        help="the shortest identification staircase that reaches target posterior widths",
        description="Search current staircases (the hold and the turning levels at the reference's step; every "
        "level inside the span stepped to from both sides, as the hysteresis check needs; no sensor colder or "
        "hotter than the limits) for the shortest that reaches the target posterior sds of the laws, and write "
        "protocol.csv (the current program), design.json (its duration and expected widths, and the reference "
        "staircase's) and design.png.",
        epilog=_EPILOG_DESIGN,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("batch_or_toml", type=Path, metavar="BATCH_OR_TOML", help="a batch folder or its batch.toml")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder to create")
    p.add_argument(
        "--target",
        action="append",
        default=[],
        metavar="PARAM=SD",
        help="a posterior sd to reach, e.g. R0_ohm=0.3%% (repeatable; default: the reference staircase's R0, S0 "
        "and K widths, within 5 %%)",
    )
    p.add_argument("--rig", metavar="RIG", help="a shipped rig or a rig file (default: the batch's [rig])")
    p.add_argument(
        "--population",
        type=Path,
        metavar="RUN",
        help="an earlier calibration run of the type: its population is the new unit's prior on the laws "
        "(calibrate the unit with --unit-prior RUN)",
    )
    p.add_argument("--max-hours", type=float, default=8.0, metavar="H", help="longest test allowed (default 8 h)")
    p.add_argument(
        "--min-hold",
        type=float,
        default=0.0,
        metavar="S",
        help="hold every level at least S seconds (e.g. 600 where short holds bias the slopes; docs/design.md)",
    )
    for side, word, example in (("min", "colder", "12, above the dew point"), ("max", "hotter", "65")):
        p.add_argument(
            f"--{side}-temperature",
            type=float,
            metavar="C",
            help=f"no sensor {word} than C degC during the test (default: as the reference staircase goes, "
            f"within 1 K; e.g. {example})",
        )
    p.add_argument(
        "--rate",
        type=float,
        default=RATE_HZ,
        metavar="HZ",
        help=f"the rig's sampling rate (default {RATE_HZ:g} Hz, the reference rig's); the design samples as slowly "
        "as the targets allow",
    )
    p.add_argument("--draws", type=int, default=2, metavar="N", help="bench modules each width averages (default 2)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the drawn modules (default 0)")
    p.add_argument("--jobs", type=int, default=2, metavar="N", help="worker processes (default 2)")
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it is an earlier design output")
    p.set_defaults(func=_cmd_design)


def _add_rig(sub):
    """The ``tembayes rig`` subcommand."""
    p = sub.add_parser(
        "rig",
        help="check a rig file (or a shipped rig) and describe it before a test",
        description="Read and check a rig file (docs/rigs.md) or a shipped rig by name, print its parameters and "
        "the CSV columns a batch on it needs, and write rig.json and rig.png: the network drawn, its slowest time "
        "constants and the hold a current staircase needs for the sensors to reach steady state.",
        epilog=_EPILOG_RIG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("rig", help="a rig file (.toml) or a shipped rig's name (reference)")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="output folder to create")
    p.add_argument(
        "--module-k",
        type=float,
        default=None,
        metavar="W_PER_K",
        help="the module's thermal conductance for the time constants (default 0.5 W/K, a 40 mm 6 A module)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace DIR if it is an earlier rig output")
    p.set_defaults(func=_cmd_rig)


def main(argv=None):
    """Entry point of the ``tembayes`` command; returns the exit status."""
    keep_short_lived_blocks_on_the_heap()
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parser.parse_args(argv)
    args.argv = argv
    try:
        return args.func(args)
    except TembayesError as err:
        print(f"tembayes: error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # the file system refused mid-way (no space, permissions): say so, no traceback
        print(f"tembayes: error: {_os_error(err)}", file=sys.stderr)
        return 2


def _os_error(err):
    import errno

    what = f"{err.filename}: {err.strerror or err}" if err.filename else str(err)
    hint = {
        errno.ENOSPC: "Free some space and run again (calibrate: --resume continues where it stopped)",
        errno.EACCES: "Choose an --out you can write to",
        errno.EROFS: "Choose an --out you can write to",
        errno.EDQUOT: "Free some space (disk quota) and run again",
    }.get(err.errno, "Check the path and run again")
    return f"{what}. {hint}"


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
