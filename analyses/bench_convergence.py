"""Benchmark: time to a converged module with the walkers' nested R-hat, against the per-walker R-hat.

A module is converged when its chain is 50 autocorrelation times long, its
bulk ESS is >= 1000 and its R-hat <= 1.01 for every law parameter.  With the
ensemble's walkers taken as chains, the per-walker split R-hat asks every
walker for ~100 autocorrelation times (its excess is ~2 tau / n), however
many walkers there are; the nested R-hat (walkers pooled in 4 superchains,
Margossian et al. 2024) leaves the length to the 50 tau and ESS targets.
Both are run here side by side on the same modules, same seed, default
model (full, robust discrepancy): wall time, steps, and how far the laws'
posterior mean and sd moved, in Monte Carlo standard errors of the faster
run (so "the same posterior" is checked, not assumed).

Modules: the shipped example (standard bench, full physics) and, with
``--high BATCH``, a batch of the out-of-model bench (``tembayes simulate
DIR --fidelity high``).

    python analyses/bench_convergence.py
    python analyses/bench_convergence.py --high runs/high-b0 --modules TEM1 TEM2

Writes ``analyses/results/bench_convergence.json``.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import arviz as az
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tembayes.calibrate import CalibrationOptions, calibrate_module  # noqa: E402
from tembayes.calibrate import sampler as smp  # noqa: E402
from tembayes.constants import MODULE_PARAMETERS  # noqa: E402
from tembayes.data import load_batch, write_json  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
NESTED = smp.nested_rhat


def walker_rhat(x, superchains=None):
    """The per-walker rank-normalised split R-hat of a ``(n, nw)`` chain (the baseline)."""
    return float(az.rhat(np.ascontiguousarray(x.T)))


def run(module, batch, rhat):
    smp.nested_rhat = NESTED if rhat == "nested" else walker_rhat
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = calibrate_module(module, batch.datasheet, rig_config=batch.rig_config, seed=0, options=CalibrationOptions())
    d = r.diagnostics
    return {
        "seconds": time.perf_counter() - t,
        "steps": d["steps"],
        "converged": d["converged"],
        "tau_max_steps": d["tau_max_steps"],
        "ess_bulk_min": d["ess_bulk_min"],
        "mean": {p: float(r.draws[p].mean()) for p in MODULE_PARAMETERS},
        "sd": {p: float(r.draws[p].std()) for p in MODULE_PARAMETERS},
        "mcse": {
            p: float(r.draws[p].std() / np.sqrt(az.ess(np.ascontiguousarray(r.draws[p]), method="mean")))
            for p in MODULE_PARAMETERS
        },
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--example", type=Path, default=ROOT / "data" / "example")
    ap.add_argument("--high", type=Path, help="a batch of the out-of-model bench")
    ap.add_argument("--modules", nargs="+", default=["TEM1", "TEM2"])
    ap.add_argument("--out", type=Path, default=ROOT / "analyses" / "results" / "bench_convergence.json")
    args = ap.parse_args()
    rows = []
    for bench, path in (("standard", args.example), ("high", args.high)):
        if path is None:
            continue
        batch = load_batch(path)
        for mid in args.modules:
            res = {k: run(batch.modules[mid], batch, k) for k in ("walkers", "nested")}
            new, old = res["nested"], res["walkers"]
            moved = {
                p: abs(new["mean"][p] - old["mean"][p]) / np.hypot(new["mcse"][p], old["mcse"][p])
                for p in MODULE_PARAMETERS
            }
            sd_ratio = {p: new["sd"][p] / old["sd"][p] for p in MODULE_PARAMETERS}
            rows.append(
                {
                    "bench": bench,
                    "module": mid,
                    **{f"{k}_rhat": v for k, v in res.items()},
                    "time_ratio": old["seconds"] / new["seconds"],
                    "mean_moved_mcse": moved,
                    "sd_ratio": sd_ratio,
                }
            )
            print(
                f"{bench:8s} {mid}: per-walker R-hat {old['seconds']:6.1f} s ({old['steps']} steps) | "
                f"nested R-hat {new['seconds']:6.1f} s ({new['steps']} steps) | ratio {old['seconds'] / new['seconds']:.2f}x"
                f" | means moved <= {max(moved.values()):.1f} MCSE | sd ratio "
                f"{min(sd_ratio.values()):.3f}-{max(sd_ratio.values()):.3f}",
                flush=True,
            )
    med_new = float(np.median([r["nested_rhat"]["seconds"] for r in rows]))
    print(
        f"median module time with nested R-hat: {med_new:.1f} s (target <= 60 s); "
        f"median ratio {np.median([r['time_ratio'] for r in rows]):.2f}x"
    )
    write_json(args.out, {"rows": rows, "median_seconds_nested": med_new})


if __name__ == "__main__":
    main()
