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

Writes ``analyses/results/window_noise_check_LABEL.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import warnings
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"


def check_module(run, batch, module_id):
    """``{"white": ..., "noise_model": ..., "noise": ...}`` of one module (see the module docstring)."""
    from types import SimpleNamespace

    from tembayes.calibrate.module import laplace_fit
    from tembayes.constants import KELVIN, MODULE_PARAMETERS
    from tembayes.gap.evidence import ALPHA, material
    from tembayes.gap.where import identification_map
    from tembayes.gap.which import WindowNoise, window_cv
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
    windows = {
        "step": data.step,
        "since": data.since,
        "tmean_C": data.obs[2] - KELVIN,
        "levels": data.levels,
        "step_time": data.step_time,
        "source": data.source,
    }
    alpha = ALPHA / (len(module.validations) + 1)
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
    """Every module of one gap-benchmark case, with the verdict ``gap`` gave there (if recorded)."""
    from tembayes.calibrate.run import load_run
    from tembayes.data import load_batch

    run, batch = load_run(case / "run"), load_batch(case / "batch")
    gap = case / "gap.json"
    verdict = json.loads(gap.read_text())["verdict"] if gap.is_file() else None
    return {
        "case": case.name,
        "folder": str(case),
        "gap_verdict_recorded": verdict,
        "modules": {m: check_module(run, batch, m) for m in run.module_ids},
    }


def _row(c):
    rows = []
    for m, d in c["modules"].items():
        w, n = d["white"], d["noise_model"]
        rows.append(
            f"| {c['case']} | {m} | {c['gap_verdict_recorded'] or '-'} | {len(w['cells'])} | "
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
    ap.add_argument("work", nargs="+", type=Path, help="gap-benchmark work folders (their CASE/run and CASE/batch)")
    ap.add_argument("--label", required=True)
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore", RuntimeWarning)
    cases = sorted(
        (c for w in args.work for c in w.iterdir() if (c / "run" / "summary.json").is_file()),
        key=lambda c: (str(c.parent), c.name),
    )
    results = []
    for c in cases:
        results.append(check_case(c))
        m = next(iter(results[-1]["modules"].values()))
        print(f"{c}: white {len(m['white']['cells'])} cells, noise model {len(m['noise_model']['cells'])}", flush=True)
    mods = [d for c in results for d in c["modules"].values()]
    summary = {
        "cases": len(results),
        "modules_with_cells_white": sum(bool(d["white"]["cells"]) for d in mods),
        "modules_with_cells_noise_model": sum(bool(d["noise_model"]["cells"]) for d in mods),
        "work": [str(w) for w in args.work],
    }
    RESULTS.mkdir(exist_ok=True)
    stem = RESULTS / f"window_noise_check_{args.label}"
    stem.with_suffix(".json").write_text(json.dumps({"summary": summary, "cases": results}, indent=1))
    md = [
        f"# Identification windows: white noise against the calibration's noise model ({args.label})",
        "",
        f"`python analyses/window_noise_check.py {' '.join(map(str, args.work))} --label {args.label}`",
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
    stem.with_suffix(".md").write_text("\n".join(md))
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
