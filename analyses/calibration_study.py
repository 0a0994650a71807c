"""Is the calibration's uncertainty honest?  Coverage, outliers, negative control.

Generates bench batches (the virtual bench: a finer rig and module than the
calibration model, unit-to-unit spread, drifts, noise), calibrates each with
``tembayes.calibrate.calibrate_batch`` exactly as ``tembayes calibrate`` does,
and compares with the bench's ``truth.json`` (which the calibration never
reads):

- **coverage**: for every module and parameter, is the truth inside the
  central 90 % interval?  Target 85-95 % per parameter (the binomial 95 %
  band for ~100 modules is about +-6 points around 90 %);
- **outlier detection**: 3-module batches (half with one outlier whose S0
  sits 4 % apart): the outlier gets the batch's highest ``outlier_prob``,
  above 0.5, the others stay below 0.3; 8-module batches: above 0.9, below
  0.1; batches without an outlier flag nobody above 0.3; and a calibration
  table (modules binned by ``outlier_prob`` against the observed fraction of
  outliers);
- **negative control**: the same sampler on the prior alone returns the
  prior (KS tests per coordinate);
- timings per module.

    python analyses/calibration_study.py                 # full study (~40 min on 2 cores)
    python analyses/calibration_study.py --quick         # 4 batches, a smoke run
    python analyses/calibration_study.py --jobs 1        # one batch at a time
    python analyses/calibration_study.py --repopulate    # refit only the population stage
    python analyses/calibration_study.py --cached-only   # summarise the batches done so far

Bench batches and runs are cached under ``--work`` (default
``runs/calibration_study``) and reused; results go to
``analyses/results/calibration_study.json``.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tembayes.bench import BenchConfig, simulate_batch  # noqa: E402
from tembayes.calibrate import calibrate_batch  # noqa: E402
from tembayes.calibrate.module import sample_prior_only  # noqa: E402
from tembayes.constants import MODULE_PARAMETERS  # noqa: E402
from tembayes.data import load_batch, write_json  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "calibration_study.json"
RIG = ("g_cooler", "g_paste_hot", "g_paste_cold", "c_plate_hot", "c_plate_cold", "c_legs", "leak_top", "leak_bottom")


def design(quick=False):
    """(name, n_modules, seed, outlier id or None) of every study batch."""
    out = []
    n3, n8 = (2, 2) if quick else (14, 8)
    for i in range(n3):
        out.append((f"b3_{i:02d}", 3, 2000 + i, f"TEM{i % 3 + 1}" if i % 2 else None))
    for i in range(n8):
        out.append((f"b8_{i:02d}", 8, 3000 + i, f"TEM{(3 * i) % 8 + 1}" if i % 2 else None))
    return out


def run_one(args):
    name, n, seed, outlier, work, repopulate = args
    warnings.simplefilter("ignore")
    work = Path(work)
    bdir = work / "batches" / name
    if not (bdir / "truth.json").exists():
        simulate_batch(
            bdir,
            BenchConfig(n_modules=n, seed=seed, outlier=outlier, n_validations=0),
            overwrite=True,
            progress=lambda m: None,
        )
    rdir = work / "runs" / name
    t0 = time.perf_counter()
    if repopulate and (rdir / "summary.json").exists():
        (rdir / "summary.json").unlink()  # modules are reused; the population is refitted
    if (rdir / "summary.json").exists():
        summ = json.loads((rdir / "summary.json").read_text())
    else:
        summ = calibrate_batch(load_batch(bdir), rdir, seed=0, resume=True)
    truth = json.loads((bdir / "truth.json").read_text())
    return name, summ, truth, time.perf_counter() - t0


def coverage_table(records):
    out = {}
    for k in MODULE_PARAMETERS + RIG:
        inside = np.array([r["inside"][k] for r in records if k in r["inside"]])
        z = np.array([r["z"][k] for r in records if k in r["z"]])
        n = len(inside)
        lo, hi = stats.binom.ppf([0.025, 0.975], n, 0.9) / n
        out[k] = {
            "n": n,
            "coverage90": float(inside.mean()),
            "binomial_band": [float(lo), float(hi)],
            "z_mean": float(z.mean()),
            "z_sd": float(z.std(ddof=1)),
        }
    return out


def outlier_table(batches):
    res = {"3_with": [], "3_without": [], "8_with": [], "8_without": []}
    probs, labels = [], []
    for b in batches:
        p = {mid: m["outlier_prob"] for mid, m in b["summary"]["modules"].items()}
        n = len(p)
        out = b["truth"]["outlier"]
        for mid, v in p.items():
            probs.append(v)
            labels.append(mid == out)
        key = f"{3 if n <= 3 else 8}_{'with' if out else 'without'}"
        if out:
            others = [v for mid, v in p.items() if mid != out]
            hi, lo = (0.5, 0.3) if n <= 3 else (0.9, 0.1)
            ok = max(p, key=p.get) == out and p[out] > hi and max(others) < lo
            res[key].append(
                {"batch": b["name"], "outlier": out, "prob": p[out], "max_other": max(others), "pass": bool(ok)}
            )
        else:
            res[key].append({"batch": b["name"], "max_prob": max(p.values()), "pass": bool(max(p.values()) <= 0.3)})
    summary = {k: {"n": len(v), "passed": int(sum(x["pass"] for x in v)), "batches": v} for k, v in res.items()}
    probs, labels = np.array(probs), np.array(labels)
    edges = [0.0, 0.1, 0.3, 0.5, 0.7, 0.9, 1.0001]
    calib = []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (probs >= a) & (probs < b)
        calib.append(
            {
                "bin": [a, min(b, 1.0)],
                "n": int(sel.sum()),
                "mean_prob": float(probs[sel].mean()) if sel.any() else None,
                "outlier_fraction": float(labels[sel].mean()) if sel.any() else None,
            }
        )
    summary["calibration"] = calib
    return summary


def negative_control(work):
    bdir = Path(work) / "batches" / "b3_00"
    b = load_batch(bdir)
    m = next(iter(b.modules.values()))
    draws, space, run = sample_prior_only(m, b.datasheet, rig_config=b.rig_config, seed=0)
    out = {}
    for pr in space.priors:
        if pr.kind == "uniform":
            x, ref = np.ravel(draws[pr.name]), stats.uniform(pr.center - pr.scale, 2 * pr.scale)
        else:
            # the value's standard score under its prior (its log, logit or itself) is N(0, 1)
            x, ref = np.ravel(pr.z(draws[pr.name])), stats.norm()
        x = x[:: max(1, len(x) // 1000)]  # ~independent draws (as the test does)
        out[pr.name] = {"ks_pvalue": float(stats.kstest(x, ref.cdf).pvalue), "sd_ratio": float(np.std(x) / ref.std())}
    return {
        "converged": bool(run.converged),
        "steps": run.steps,
        "parameters": out,
        "min_pvalue": min(v["ks_pvalue"] for v in out.values()),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="4 batches only")
    ap.add_argument("--jobs", type=int, default=2, help="batches calibrated in parallel (default 2)")
    ap.add_argument("--work", type=Path, default=Path("runs/calibration_study"), help="cache folder")
    ap.add_argument(
        "--repopulate",
        action="store_true",
        help="refit the population stage of cached runs (module posteriors are reused)",
    )
    ap.add_argument(
        "--cached-only",
        action="store_true",
        help="summarise the batches already calibrated in --work (a partial study; n is reported)",
    )
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    jobs = [(*d, str(args.work), args.repopulate) for d in design(args.quick)]
    if args.cached_only:
        jobs = [j for j in jobs if (args.work / "runs" / j[0] / "summary.json").exists()]
    batches, records, times = [], [], []
    with ProcessPoolExecutor(max_workers=args.jobs) as ex:
        for name, summ, truth, dt in ex.map(run_one, jobs):
            batches.append({"name": name, "summary": summ, "truth": truth})
            for mid, m in summ["modules"].items():
                t = truth["modules"][mid]
                rec = {"batch": name, "module": mid, "inside": {}, "z": {}}
                for k in MODULE_PARAMETERS:
                    rec["inside"][k] = bool(m[k]["q05"] <= t[k] <= m[k]["q95"])
                    rec["z"][k] = (m[k]["mean"] - t[k]) / m[k]["sd"]
                for k in RIG:
                    s = m["nuisance"].get(k)
                    if s is not None:
                        rec["inside"][k] = bool(s["q05"] <= t["rig"][k] <= s["q95"])
                        rec["z"][k] = (s["mean"] - t["rig"][k]) / s["sd"]
                rec["converged"] = m["diagnostics"]["converged"]
                rec["seconds"] = m["diagnostics"]["seconds"]
                records.append(rec)
                times.append(m["diagnostics"]["seconds"])
            print(f"{name}: {len(summ['modules'])} modules, {dt:.0f} s", flush=True)
    cov = coverage_table(records)
    out_tab = outlier_table(batches)
    neg = negative_control(args.work)
    result = {
        "n_modules": len(records),
        "partial": bool(args.cached_only and len(jobs) < len(design(args.quick))),
        "n_batches": len(batches),
        "converged_fraction": float(np.mean([r["converged"] for r in records])),
        "coverage": cov,
        "outliers": out_tab,
        "negative_control": neg,
        "seconds_per_module": {"median": float(np.median(times)), "max": float(np.max(times))},
        "wall_seconds": time.perf_counter() - t0,
    }
    print(f"\n{len(records)} modules in {len(batches)} batches; converged {result['converged_fraction']:.0%}")
    print(f"{'parameter':<16s} {'coverage90':>10s} {'band':>13s} {'z mean':>7s} {'z sd':>6s}")
    for k, v in cov.items():
        print(
            f"{k:<16s} {v['coverage90']:>10.1%} {v['binomial_band'][0]:>6.0%}-{v['binomial_band'][1]:<6.0%}"
            f" {v['z_mean']:>+7.2f} {v['z_sd']:>6.2f}"
        )
    print("\noutliers (passed / batches):")
    for k in ("3_with", "3_without", "8_with", "8_without"):
        print(f"  {k:<10s} {out_tab[k]['passed']}/{out_tab[k]['n']}")
    print("calibration (outlier_prob bin: n, mean prob, observed outlier fraction):")
    for c in out_tab["calibration"]:
        if c["n"]:
            print(
                f"  [{c['bin'][0]:.1f}, {c['bin'][1]:.1f}): {c['n']:>4d}  {c['mean_prob']:.2f}  "
                f"{c['outlier_fraction']:.2f}"
            )
    print(f"negative control: min KS p-value {neg['min_pvalue']:.3f} over {len(neg['parameters'])} coordinates")
    print(
        f"seconds per module: median {result['seconds_per_module']['median']:.0f}, "
        f"max {result['seconds_per_module']['max']:.0f}"
    )
    if not args.quick:
        write_json(RESULTS, result)
        print(f"wrote {RESULTS}")
    return result


if __name__ == "__main__":
    main()
