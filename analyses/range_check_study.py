"""Which range conflicts matter: the gap's range checks against the bench's truth.

For every case of some ``analyses/gap_benchmark.py`` work folders (``CASE/batch``,
``CASE/run``, a calibrated one-module batch with a validation run) this runs
the first step of ``tembayes gap`` (:func:`tembayes.gap.diagnose.locate`: the
held-out data, the base refit, and each range conflict's refit with it held
at its documented edge) and records, per case:

- the held-out data's gap cells (validation runs and identification windows);
- each conflict: how far outside, the new window cells and the largest law
  shift [posterior sds] of the refit that judged it, and whether it matters;
- whether ``gap`` raises an alarm (a cell, or a conflict that matters) and,
  where the batch has ``truth.json``, how far each law's posterior mean is from
  the truth [posterior sds].

On a null case an alarm is false; a conflict found not to matter should sit on
a module whose laws are not moved by it.  With a catalogue effect absorbed in a
rig parameter (``ambient_leak``, ``contact_resistance``) the conflict must matter.

    python analyses/range_check_study.py /work/rfx --label reference-faces_high
    python analyses/range_check_study.py /work/refcat --cases contact_resistance_s0 --label reference_catalogue

Writes ``analyses/results/range_checks_LABEL.{json,md}`` (the cases done are kept in
``WORK/range_checks_LABEL.jsonl``, so an interrupted study resumes).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
LAWS = ("R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K")


def study_case(case, *, seed, jobs):
    """One case's record (see the module docstring)."""
    from tembayes.calibrate.run import load_run
    from tembayes.data import load_batch
    from tembayes.gap.diagnose import locate
    from tembayes.predict.predictive import module_raw_draws

    run, batch = load_run(case / "run"), load_batch(case / "batch")
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        base = locate(run, batch, seed=seed, jobs=jobs)
    truth_file = case / "batch" / "truth.json"
    truth = json.loads(truth_file.read_text())["modules"] if truth_file.is_file() else {}
    modules = {}
    for mid in base.ids:
        raw = module_raw_draws(run, mid)
        z = {k: (float(np.mean(raw[k])) - truth[mid][k]) / float(np.std(raw[k])) for k in LAWS} if mid in truth else {}
        modules[mid] = {
            "law_z": z,
            "conflicts": [{k: r.get(k) for k in _KEYS} for r in base.conflicts[mid] if r["conflict"]],
        }
    return {
        "case": case.name,
        "validation_cells": len(base.where_validation),
        "identification_cells": len(base.where_identification),
        "parameter_gaps": [w["channel"] for w in base.parameter_gaps],
        "alarm": base.has_gap,
        "modules": modules,
        "seconds": time.perf_counter() - t0,
    }


_KEYS = (
    "parameter",
    "median",
    "low",
    "high",
    "outside_sd",
    "material",
    "held_cells",
    "held_law_shift",
    "held_cells_together",
    "held_law_shift_together",
    "held_converged",
)


def markdown(rows, command):
    """The study's table."""
    out = [
        "# Range checks: which conflicts matter",
        "",
        f"`{command}`",
        "",
        "| case | held-out cells (validation, windows) | conflict: median (range), new cells, law shift [sd], matters"
        " | alarm | max abs law z |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        for mid, m in r["modules"].items():
            conf = "; ".join(
                f"{c['parameter']} {c['median']:.4g} ({c['low']:.3g}-{c['high']:.3g}), "
                f"{'failed' if c['held_cells'] is None else c['held_cells']}, "
                f"{'–' if c['held_law_shift'] is None else format(c['held_law_shift'], '.2f')}, "
                f"**{'yes' if c['material'] else 'no'}**"
                for c in m["conflicts"]
            )
            zmax = max((abs(v) for v in m["law_z"].values()), default=None)
            out.append(
                f"| {r['case']} {mid} | {r['validation_cells']}, {r['identification_cells']} | {conf or '–'} | "
                f"{'yes' if r['alarm'] else 'no'} | {'–' if zmax is None else format(zmax, '.2f')} |"
            )
    nulls = [r for r in rows if r["case"].startswith("null")]
    if nulls:
        out += ["", f"- null cases with an alarm: {sum(r['alarm'] for r in nulls)} of {len(nulls)}"]
    return "\n".join(out) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="example: python analyses/range_check_study.py /work/rfx --label reference-faces_high",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("work", type=Path, nargs="+", help="gap_benchmark.py work folders (CASE/batch, CASE/run)")
    ap.add_argument("--cases", nargs="*", help="only these case folders (names), default every calibrated one")
    ap.add_argument("--label", required=True)
    ap.add_argument("--jobs", type=int, default=1, help="the diagnosis's worker processes")
    args = ap.parse_args(argv)
    cases = sorted(
        c
        for w in args.work
        for c in w.iterdir()
        if (c / "run" / "summary.json").is_file() and (not args.cases or c.name in args.cases)
    )
    RESULTS.mkdir(exist_ok=True)
    cache = args.work[0] / f"range_checks_{args.label}.jsonl"  # the cases done, for a resumed study
    done = (
        {json.loads(line)["case"]: json.loads(line) for line in cache.read_text().splitlines()}
        if cache.is_file()
        else {}
    )
    rows = []
    for c in cases:
        key = f"{c.parent.name}/{c.name}"
        if key not in done:
            seed = int(c.name.rsplit("_s", 1)[-1]) if "_s" in c.name else 0
            row = {**study_case(c, seed=seed, jobs=args.jobs), "case": c.name, "work": str(c.parent)}
            done[key] = {**row, "case": key}
            with cache.open("a") as f:
                f.write(json.dumps(done[key]) + "\n")
            print(f"[{key}] alarm {row['alarm']} ({row['seconds']:.0f} s)", flush=True)
        rows.append({**done[key], "case": c.name})
    command = "python analyses/range_check_study.py " + " ".join(argv if argv is not None else sys.argv[1:])
    (RESULTS / f"range_checks_{args.label}.json").write_text(json.dumps(rows, indent=1))
    (RESULTS / f"range_checks_{args.label}.md").write_text(markdown(rows, command))
    print(markdown(rows, command))


if __name__ == "__main__":
    main()
