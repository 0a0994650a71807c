"""How far the calibration model sits from the virtual bench at the *true* parameters.

The bench is a higher-fidelity world (6-cell blocks, plates plus 4 leg cells
with Joule heat at the local resistance, tabs).  This study simulates each
bench module's own experiments with the reference-rig model given the true
law parameters and the true rig values (``truth.json``: ``rig``), once with
the paper's lumped module and once with the legs resolved into 2 cells, and
reports the RMSE and max error per sensor and on the voltage.  What remains is
the bench-vs-model mismatch a calibration must model or absorb.

Run:  python analyses/model_vs_bench.py [--seeds 0 1 2] [--rate 1]
Writes analyses/results/model_vs_bench.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from tembayes.bench import BenchConfig, simulate_batch
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data import load_batch, write_json
from tembayes.physics import Inputs, simulate
from tembayes.physics.rigread import rig_from_config

RESULTS = Path(__file__).parent / "results"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--rate", type=float, default=1.0)
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            out = Path(tmp) / f"b{seed}"
            simulate_batch(out, BenchConfig(n_modules=3, seed=seed, rate=args.rate), progress=lambda m: None)
            batch = load_batch(out)
            truth = json.loads((out / "truth.json").read_text())
            for mid, module in batch.modules.items():
                t = truth["modules"][mid]
                params = {k: t[k] for k in MODULE_PARAMETERS} | t["rig"]
                for exp in (module.identification, *module.validations):
                    for legs in (0, 2):
                        sim = simulate(Inputs.from_experiment(exp), params, rig=rig_from_config(None, legs))
                        r = exp.sensors - sim.sensors[0]
                        rv = exp.voltage - sim.voltage[0]
                        rows.append(
                            {
                                "seed": seed,
                                "module": mid,
                                "experiment": exp.path.name,
                                "leg_cells": legs,
                                "rmse_K": dict(zip(sim.channels, np.sqrt((r**2).mean(axis=1)).tolist())),
                                "max_K": dict(zip(sim.channels, np.abs(r).max(axis=1).tolist())),
                                "rmse_V": float(np.sqrt((rv**2).mean())),
                            }
                        )
    print(f"{'model':<14s}{'experiment':<20s}{'T3 RMSE [K]':>16s}{'T4 RMSE [K]':>16s}{'V RMSE [mV]':>16s}")
    summary = {}
    for legs in (0, 2):
        for kind in ("identification", "validation"):
            sel = [r for r in rows if r["leg_cells"] == legs and r["experiment"].startswith(kind)]
            t3 = [r["rmse_K"]["T3_C"] for r in sel]
            t4 = [r["rmse_K"]["T4_C"] for r in sel]
            v = [1e3 * r["rmse_V"] for r in sel]
            name = "lumped" if legs == 0 else f"legs={legs}"
            summary[f"{name}/{kind}"] = {
                "T3_rmse_K": [min(t3), max(t3)],
                "T4_rmse_K": [min(t4), max(t4)],
                "V_rmse_mV": [min(v), max(v)],
            }
            print(
                f"{name:<14s}{kind:<20s}{min(t3):7.3f}-{max(t3):.3f}{min(t4):9.3f}-{max(t4):.3f}"
                f"{min(v):10.2f}-{max(v):.2f}"
            )
    RESULTS.mkdir(exist_ok=True)
    write_json(
        RESULTS / "model_vs_bench.json", {"seeds": args.seeds, "rate_Hz": args.rate, "summary": summary, "rows": rows}
    )
    print(f"wrote {RESULTS / 'model_vs_bench.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
