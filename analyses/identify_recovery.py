"""Recovery study of the deterministic step method (``tembayes identify``) on bench batches.

For several fresh bench batches (default: 4 seeds x 3 modules, the reference
staircase at 5 Hz) the step method runs blind (it never reads truth.json);
afterwards its laws are compared with the truth:

- corrected method (``fit``) vs the paper's literal recipe (``fit_paper``):
  relative error of R0, R1, S0, S1 per module;
- jump extrapolation vs first sample: mean relative error of the per-step R
  against the true law at the step's junction temperature;
- the sensor-dT bias: S0 with the sensors' dT (corrected R) minus the
  corrected S0 (physics predicts > 0);
- hysteresis z-scores (no hysteresis on the bench: |z| mostly < 2).

Targets: R0, S0 within 2 %, R1, S1 within 20 % for ``fit``.

Run:  python analyses/identify_recovery.py [--seeds 10 11 12 13] [--validation]
      python analyses/identify_recovery.py --seeds --batch B1 --batch B2 --label reference-faces
      (about 2 min per batch on 2 cores)
Writes analyses/results/identify_recovery.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from tembayes.bench import BenchConfig, simulate_batch
from tembayes.constants import LAW_PARAMETERS, T_REF
from tembayes.data import load_batch, write_json
from tembayes.identify.pipeline import identify_module

RESULTS = Path(__file__).parent / "results"
TARGETS = {"R0_ohm": 0.02, "R1_ohm_per_K": 0.20, "S0_V_per_K": 0.02, "S1_V_per_K2": 0.20}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="*", default=[10, 11, 12, 13])
    ap.add_argument(
        "--batch",
        type=Path,
        action="append",
        default=[],
        help="also an existing batch folder with truth.json (e.g. data/example)",
    )
    ap.add_argument("--validation", action="store_true", help="also run validation experiments")
    ap.add_argument("--label", default="", help="appended to the results' name (e.g. the rig of --batch folders)")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folders = list(args.batch)
        for seed in args.seeds:
            out = Path(tmp) / f"seed{seed}"
            simulate_batch(
                out,
                BenchConfig(n_modules=3, seed=seed, n_validations=1 if args.validation else 0, validation_rate=1.0),
                progress=lambda m: None,
            )
            folders.append(out)
        for folder in folders:
            batch = load_batch(folder)
            truth = json.loads((Path(folder) / "truth.json").read_text())
            for mid, module in batch.modules.items():
                t0 = time.perf_counter()
                r = identify_module(module, batch.datasheet, rig_config=batch.rig_config)
                t = truth["modules"][mid]
                row = {
                    "batch": str(folder) if folder in args.batch else Path(folder).name,
                    "module": mid,
                    "seconds": time.perf_counter() - t0,
                }
                row["fit_err"] = {k: r.fit[k] / t[k] - 1 for k in LAW_PARAMETERS}
                row["paper_err"] = {k: r.fit_paper[k] / t[k] - 1 for k in LAW_PARAMETERS}
                row["K_err"] = r.rig_fit.values["K_W_per_K"] / t["K_W_per_K"] - 1
                row["sensor_dT_bias_S0"] = r.lines["S_sensor_dT"].a / r.lines["S"].a - 1

                def R_true(T, t=t):
                    return t["R0_ohm"] + t["R1_ohm_per_K"] * (np.asarray(T) - T_REF)

                ext = np.array([s["jump"].R / R_true(s["Tavg_R"]) - 1 for s in r.steps])
                first = np.array([s["jump"].R_first / R_true(s["Tavg_R"]) - 1 for s in r.steps])
                row["jump_err_mean"] = float(ext.mean())
                row["first_sample_err_mean"] = float(first.mean())
                row["hysteresis_z"] = {k: v["z"] for k, v in r.hysteresis.items()}
                row["within_targets"] = all(abs(row["fit_err"][k]) <= TARGETS[k] for k in LAW_PARAMETERS)
                if args.validation:
                    row["validation_T3_rmse"] = {
                        f: {m: e["T3_C"]["rmse"] for m, e in v.items()} for f, v in r.validation.items()
                    }
                rows.append(row)
                e = row["fit_err"]
                p = row["paper_err"]
                print(
                    f"{row['batch']:<14s}{mid:<6s} fit: "
                    + " ".join(f"{k[:2]} {100 * e[k]:+6.2f}%" for k in e)
                    + " | paper: "
                    + " ".join(f"{k[:2]} {100 * p[k]:+6.2f}%" for k in p)
                    + f" | jump {100 * row['jump_err_mean']:+.2f}% first {100 * row['first_sample_err_mean']:+.2f}%"
                    + f" | {'OK' if row['within_targets'] else 'MISS'}",
                    flush=True,
                )
    summary = {
        "n_modules": len(rows),
        "within_targets": sum(r["within_targets"] for r in rows),
        "max_abs_fit_err": {k: max(abs(r["fit_err"][k]) for r in rows) for k in LAW_PARAMETERS},
        "max_abs_paper_err": {k: max(abs(r["paper_err"][k]) for r in rows) for k in LAW_PARAMETERS},
        "mean_abs_jump_err": float(np.mean([abs(r["jump_err_mean"]) for r in rows])),
        "mean_abs_first_sample_err": float(np.mean([abs(r["first_sample_err_mean"]) for r in rows])),
        "sensor_dT_bias_S0_range": [
            min(r["sensor_dT_bias_S0"] for r in rows),
            max(r["sensor_dT_bias_S0"] for r in rows),
        ],
        "max_abs_hysteresis_z": max(abs(z) for r in rows for z in r["hysteresis_z"].values()),
    }
    print(json.dumps(summary, indent=2))
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / ("identify_recovery" + (f"_{args.label}" if args.label else "") + ".json")
    write_json(out, {"summary": summary, "rows": rows, "targets": TARGETS, "seeds": args.seeds})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
