"""Runs that start from rest: is the prediction right from the first minute, and is no gap seen?

One-module bench batches whose validation run starts from rest (every node at
the water and air temperatures) with the current switched straight to its
first level, as a user's rig does when the test begins with the supply
(``tembayes simulate --validation-start rest``).  Each is calibrated, its
validation run predicted exactly as ``tembayes predict`` does (initial state
from the run's first samples), and, with ``--gap``, diagnosed with
``tembayes gap`` (no catalogue effect on the bench: ``no_gap`` is right).

Targets: T-RMSE over the whole run within 20 % of the RMSE after the first
hour (T1-T4); ``no_gap`` on at least 90 % of the batches.

    python analyses/rest_start.py --fidelity standard --batches 10 --gap
    python analyses/rest_start.py --fidelity high --model full --discrepancy robust --batches 6
    python analyses/rest_start.py ... --summarise

Resumable (everything cached under ``--work``).  Writes
analyses/results/rest_start_<label>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
SENSORS = ("T1_C", "T2_C", "T3_C", "T4_C")


def label(args):
    return f"{args.fidelity}-{args.physics}-{args.model}-{args.discrepancy}"


def tembayes(*cmd):
    p = subprocess.run([sys.executable, "-m", "tembayes", *map(str, cmd)], capture_output=True, text=True)
    if p.returncode not in (0, 1):
        raise RuntimeError(f"tembayes {' '.join(map(str, cmd))}: {p.stderr.strip().splitlines()[-1:]}")
    return p


def rmse(r, keep):
    return [float(np.sqrt(np.mean(r[c, keep] ** 2))) for c in range(len(SENSORS))]


def one_batch(args, b):
    from tembayes.calibrate.run import load_run
    from tembayes.data import load_batch
    from tembayes.predict.predictive import predict

    work = args.work / label(args)
    bdir, rdir, res = work / f"b{b}", work / f"b{b}.run", work / f"b{b}.json"
    if res.exists():
        return json.loads(res.read_text())
    if not (bdir / "truth.json").exists():
        tembayes(
            "simulate",
            bdir,
            "--modules",
            1,
            "--fidelity",
            args.fidelity,
            "--physics",
            args.physics,
            "--validations",
            1,
            "--validation-start",
            "rest",
            "--validation-rate",
            1,
            "--seed",
            700 + b,
            "--overwrite",
        )
    if not (rdir / "summary.json").exists():
        tembayes(
            "calibrate",
            bdir,
            "--out",
            rdir,
            "--seed",
            0,
            "--model",
            args.model,
            "--discrepancy",
            args.discrepancy,
            "--quiet",
            "--no-figures",
            "--workers",
            1,
            "--overwrite",
        )
    batch = load_batch(bdir)
    exp = batch.modules["TEM1"].validations[0]
    pred = predict(load_run(rdir), exp, "TEM1", batch, n_draws=args.draws, seed=0, compare_constant=False).linear
    r = pred.residual[:4]
    t = pred.time - pred.time[0]
    doc = {
        "batch": b,
        "rmse_all_K": rmse(r, slice(None)),
        "rmse_after_1h_K": rmse(r, t >= 3600.0),
        "rmse_first_15min_K": rmse(r, t < 900.0),
        "coverage90": [float(c) for c in pred.coverage(90)[:4]],
        "first_level_A": float(pred.current[0]),
        "start_current_A": pred.start_current,
    }
    if args.gap:
        gdir = work / f"b{b}.gap"
        tembayes("gap", rdir, bdir, "--out", gdir, "--no-figures", "--jobs", 1, "--overwrite")
        g = json.loads((gdir / "gap.json").read_text())
        doc["gap_verdict"] = g.get("verdict")
    res.write_text(json.dumps(doc, indent=1) + "\n")
    return doc


def summarise(docs):
    ratio = np.array([np.array(d["rmse_all_K"]) / np.array(d["rmse_after_1h_K"]) for d in docs])
    out = {
        "n_batches": len(docs),
        "ratio_all_over_after_1h": {
            s: {
                "median": float(np.median(ratio[:, i])),
                "max": float(np.max(ratio[:, i])),
                "within_1.2": int(np.sum(ratio[:, i] <= 1.2)),
            }
            for i, s in enumerate(SENSORS)
        },
        "rmse_first_15min_mK_median": {
            s: 1e3 * float(np.median([d["rmse_first_15min_K"][i] for d in docs])) for i, s in enumerate(SENSORS)
        },
        "rmse_after_1h_mK_median": {
            s: 1e3 * float(np.median([d["rmse_after_1h_K"][i] for d in docs])) for i, s in enumerate(SENSORS)
        },
    }
    verdicts = [d["gap_verdict"] for d in docs if "gap_verdict" in d]
    if verdicts:
        out["gap"] = {
            "n": len(verdicts),
            "no_gap": verdicts.count("no_gap"),
            "verdicts": {v: verdicts.count(v) for v in sorted(set(verdicts))},
        }
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fidelity", choices=("standard", "high"), default="standard")
    ap.add_argument("--physics", choices=("paper", "full"), default="paper", help="the standard bench's physics")
    ap.add_argument("--model", choices=("paper", "full"), default="paper")
    ap.add_argument("--discrepancy", choices=("none", "window-sandwich", "robust"), default="none")
    ap.add_argument("--batches", type=int, default=10)
    ap.add_argument("--draws", type=int, default=200)
    ap.add_argument("--gap", action="store_true", help="also run tembayes gap on every batch")
    ap.add_argument("--work", type=Path, default=Path("/tmp/tembayes-rest-start"))
    ap.add_argument("--shard", default="0/1", help="K/N: this process does every N-th batch from K")
    ap.add_argument("--summarise", action="store_true")
    args = ap.parse_args()
    (args.work / label(args)).mkdir(parents=True, exist_ok=True)
    k, n = (int(x) for x in args.shard.split("/"))
    docs = []
    for b in range(args.batches):
        if args.summarise:
            f = args.work / label(args) / f"b{b}.json"
            if f.exists():
                docs.append(json.loads(f.read_text()))
        elif b % n == k:
            docs.append(one_batch(args, b))
            print(f"done batch {b}", flush=True)
    doc = {
        "label": label(args),
        "settings": {k: str(v) for k, v in vars(args).items()},
        "summary": summarise(docs),
        "batches": docs,
    }
    res = ROOT / "analyses" / "results"
    (res / f"rest_start_{label(args)}.json").write_text(json.dumps(doc, indent=1) + "\n")
    s = doc["summary"]
    lines = [
        f"# Runs that start from rest: {label(args)}",
        "",
        f"{s['n_batches']} batches, one module each",
        "",
        "| | RMSE all / after 1 h, median | max | batches within 1.2 | first 15 min RMSE [mK] | after 1 h RMSE [mK] |",
        "|---|---|---|---|---|---|",
    ]
    for sname in SENSORS:
        q = s["ratio_all_over_after_1h"][sname]
        lines.append(
            f"| {sname} | {q['median']:.3f} | {q['max']:.3f} | {q['within_1.2']}/{s['n_batches']} | "
            f"{s['rmse_first_15min_mK_median'][sname]:.1f} | {s['rmse_after_1h_mK_median'][sname]:.1f} |"
        )
    if "gap" in s:
        lines += ["", f"gap: no_gap in {s['gap']['no_gap']} of {s['gap']['n']} ({s['gap']['verdicts']})"]
    (res / f"rest_start_{label(args)}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
