"""The identification windows' gap cells, judged at white noise and by the calibration's noise model.

For every case of some ``analyses/gap_benchmark.py`` work folders (``CASE/batch``,
``CASE/run``) the base model is refitted on each module's identification run as
``tembayes gap`` does (from the posterior's medians) and its step windows are
predicted from the others (leave-one-window-out).  The held-out residuals are
whitened twice: at white noise at the measured level (``gap`` before
2026-11-29) and by the base calibration's noise model
(:class:`tembayes.gap.which.WindowNoise`, what ``gap`` uses now).  Per case:
the cells of the identification map that are significant and material (the
family-wise level of a one-module batch with one validation run), the worst
cell, and the windows' mean z^2 (1 when they scatter as the noise model says).

A null case on the out-of-model bench should have no cell; a catalogue
effect that shows in the windows should keep some.

    python analyses/window_noise_check.py /work/gapnull_rf_high --label reference-faces_high_null
    python analyses/window_noise_check.py --label reference-faces_high_null --summarise

Writes ``analyses/results/window_noise_check_LABEL.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def check_module(run, batch, module_id, alpha):
    """``{"white": ..., "noise_model": ..., "noise": ...}`` of one module (see the module docstring).

    ``alpha`` is the level of each cell test, the family-wise level split as ``gap`` splits it.
    """
    from types import SimpleNamespace

    from tembayes.calibrate.module import laplace_fit
    from tembayes.constants import MODULE_PARAMETERS
    from tembayes.gap.evidence import material
    from tembayes.gap.where import identification_map
    from tembayes.gap.which import WindowNoise, step_windows, window_cv
    from tembayes.predict.predictive import module_raw_draws

    raws = module_raw_draws(run, module_id)
    module = batch.modules[module_id]
    fit = laplace_fit(
        module.identification,
        batch.datasheet,
        rig_config=batch.rig_config,
        options=run.calibration_options(),
        start={k: float(np.median(raws[k])) for k in MODULE_PARAMETERS},
    )
    data, r = fit.data, fit.residuals
    windows = step_windows(data)
    wn = WindowNoise.of_draws(raws)
    out = {"noise": {"scale": wn.scale.tolist(), "offset_over_noise": (wn.offset_sd / data.noise).tolist()}}
    for tag, noise in (("white", None), ("noise_model", wn.whitened(data.noise))):
        _, z = window_cv(fit.jac[: r.size], r, fit.cov, data.step, noise)
        gm = identification_map(SimpleNamespace(windows=windows, cv_z=z))
        cells = material(gm.significant(alpha))
        worst = max(gm.cells, key=lambda c: c["score"])
        out[tag] = {
            "cells": [{k: c[k] for k in ("channel", "regime", "score", "p")} for c in cells],
            "worst": {k: worst[k] for k in ("channel", "regime", "score", "p")},
            "mean_z2": float(np.mean(np.asarray(z, float) ** 2)),
        }
    return out


def check_case(case):
    """The modules ``gap`` diagnoses in one gap-benchmark case, with the verdict it gave there (if recorded)."""
    from tembayes.calibrate.run import load_run
    from tembayes.data import load_batch
    from tembayes.gap.evidence import ALPHA

    run, batch = load_run(case / "run"), load_batch(case / "batch")
    ids = [m for m in run.module_ids if batch.modules[m].validations]
    alpha = ALPHA / (sum(len(batch.modules[m].validations) for m in ids) + len(ids))  # as gap's plan
    gap = case / "gap.json"
    verdict = json.loads(gap.read_text())["verdict"] if gap.is_file() else None
    return {
        "case": case.name,
        "folder": str(case),
        "gap_verdict_recorded": verdict,
        "modules": {m: check_module(run, batch, m, alpha) for m in ids},
    }


def _row(c):
    rows = []
    for m, d in c["modules"].items():
        w, n = d["white"], d["noise_model"]
        rows.append(
            f"| {Path(c['folder']).parent.name}/{c['case']} | {m} | {c['gap_verdict_recorded'] or '-'} | {len(w['cells'])} | "
            f"{w['worst']['score']:.2f} | {w['mean_z2']:.3f} | {len(n['cells'])} | {n['worst']['score']:.2f} | "
            f"{n['mean_z2']:.3f} | {', '.join(f'{v:.2f}' for v in d['noise']['scale'])} | "
            f"{', '.join(f'{v:.2f}' for v in d['noise']['offset_over_noise'])} |"
        )
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example: python analyses/window_noise_check.py /work/gapnull_rf_high --label reference-faces_high_null",
    )
    ap.add_argument("work", nargs="*", type=Path, help="gap-benchmark work folders (their CASE/run and CASE/batch)")
    ap.add_argument("--label", required=True)
    ap.add_argument("--summarise", action="store_true", help="only write the .md again from the recorded .json")
    args = ap.parse_args(argv)
    if not args.work and not args.summarise:
        ap.error("name at least one work folder (or --summarise a recorded label)")
    warnings.simplefilter("ignore", RuntimeWarning)
    stem = RESULTS / f"window_noise_check_{args.label}"
    if args.summarise:
        doc = json.loads(stem.with_suffix(".json").read_text())
        summary, results = doc["summary"], doc["cases"]
    else:
        summary, results = _check_all(args.work)
        RESULTS.mkdir(exist_ok=True)
        stem.with_suffix(".json").write_text(json.dumps({"summary": summary, "cases": results}, indent=1))
    stem.with_suffix(".md").write_text(_markdown(args, summary, results))
    print(json.dumps(summary))


def _check_all(work):
    """``(summary, cases)`` of every case with a run under the folders ``work``."""
    cases = sorted(
        (c for w in work for c in w.iterdir() if (c / "run" / "summary.json").is_file()),
        key=lambda c: (str(c.parent), c.name),
    )
    results = []
    for c in cases:
        results.append(check_case(c))
        for m, d in results[-1]["modules"].items():
            print(f"{c} {m}: white {len(d['white']['cells'])} cells, noise model {len(d['noise_model']['cells'])}")
    mods = [d for c in results for d in c["modules"].values()]
    summary = {
        "cases": len(results),
        "modules": len(mods),
        "modules_with_cells_white": sum(bool(d["white"]["cells"]) for d in mods),
        "modules_with_cells_noise_model": sum(bool(d["noise_model"]["cells"]) for d in mods),
        "work": [str(w) for w in work],
    }
    return summary, results


def _markdown(args, summary, results):
    """The record's table."""
    mods = [d for c in results for d in c["modules"].values()]
    md = [
        f"# Identification windows: white noise against the calibration's noise model ({args.label})",
        "",
        f"`python analyses/window_noise_check.py {' '.join(summary['work'])} --label {args.label}`",
        "",
        f"Modules with a significant, material window cell: white {summary['modules_with_cells_white']}, "
        f"noise model {summary['modules_with_cells_noise_model']} (of {len(mods)}).",
        "",
        "| case | module | gap verdict recorded | white: cells | worst | mean z² | noise model: cells | worst | "
        "mean z² | noise scale (V, dT, T̄) | offset / noise |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        *[r for c in results for r in _row(c)],
        "",
    ]
    return "\n".join(md)


if __name__ == "__main__":
    main()
