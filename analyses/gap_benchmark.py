"""Blind check of the gap diagnosis (issue 6): does ``tembayes gap`` name the effect it was not told?

For every row -- the null bench (no effect), each catalogue effect at its
default magnitude, and each effect *withheld* (the diagnosis run with that
effect removed from its catalogue) -- and every seed:

1. ``tembayes simulate`` a one-module bench batch (identification at 5 Hz, a
   4-hour validation run at 1 Hz) with the effect switched on;
2. ``tembayes calibrate`` it with the base model;
3. diagnose it with :func:`tembayes.gap.diagnose.diagnose`, exactly what
   ``tembayes gap`` runs, which reads the batch's CSV files and the run only
   (never ``truth.json``; the benchmark knows the effect from its own row).

Printed: the confusion matrix (true effect x diagnosed best, or the verdict
when there is no best), top-1 attribution on the catalogue rows (strict, and
with the confusable groups below scored as one), the null false-alarm rate,
the withheld rows not called ``explained``, and the shrink of the gap when
the true effect is recalibrated.

Confusable groups, stated before the runs (physics, not results):

- ``sensor_lag`` / ``contact_resistance``: both delay the sensors' view of a
  block's response to the module's heat;
- ``k_temperature`` / ``ambient_leak``: both change the steady heat balance
  in proportion to the distance from room temperature.

Targets: top-1 >= 0.85 (groups as one), null false alarm <= 10 %, withheld not
``explained`` >= 80 %, shrink >= 50 % when the true effect is added.

    python analyses/gap_benchmark.py                 # 5 seeds x (null + 8 effects + 8 withheld), resumable
    python analyses/gap_benchmark.py --seeds 2 --effects sensor_lag joule_split
    python analyses/gap_benchmark.py --shard 0/2 & python analyses/gap_benchmark.py --shard 1/2; \
        python analyses/gap_benchmark.py --summarise

Each case is cached under ``runs/gap_benchmark/<effect>_s<seed>/`` (batch,
run, ``gap.json``, ``gap_withheld.json``); an interrupted benchmark resumes.
About 5 min per effect case on 2 cores.  Results:
``analyses/results/gap_benchmark.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

RESULTS = Path(__file__).resolve().parent / "results"
GROUPS = (("sensor_lag", "contact_resistance"), ("k_temperature", "ambient_leak"))


def _group(effect):
    for g in GROUPS:
        if effect in g:
            return set(g)
    return {effect}


def _tembayes(*args, check=True):
    subprocess.run([sys.executable, "-m", "tembayes", *args], check=check, stdout=subprocess.DEVNULL,
                   stderr=subprocess.DEVNULL)


def _case(work, effect, seed, withheld, compute=True):
    from tembayes.calibrate.run import load_run
    from tembayes.data import load_batch
    from tembayes.data.write import write_json
    from tembayes.gap.diagnose import diagnose

    d = work / f"{effect or 'null'}_s{seed}"
    batch, run = d / "batch", d / "run"
    if not compute:  # summarising: the cached results only
        tags = ["gap"] + (["gap_withheld"] if withheld and effect else [])
        if not all((d / f"{t}.json").is_file() for t in tags):
            return None
        return {t: json.loads((d / f"{t}.json").read_text()) for t in tags}
    if not (run / "summary.json").is_file():
        d.mkdir(parents=True, exist_ok=True)
        eff = ["--effect", effect] if effect else []
        _tembayes("simulate", str(batch), "--modules", "1", "--seed", str(1000 + seed), "--validation-rate", "1",
                  "--overwrite", *eff)
        # exit status 1 = a module not converged: a misspecified model often is; the run is written
        _tembayes("calibrate", str(batch), "--out", str(run), "--seed", str(seed), "--no-figures", "--quiet",
                  "--overwrite", check=False)
        if not (run / "summary.json").is_file():
            raise RuntimeError(f"calibrating {batch} wrote no run")
    out, cache = {}, {}  # the withheld diagnosis reuses the other candidates' recalibrations
    for tag, exclude in (("gap", ()),) + ((("gap_withheld", (effect,)),) if withheld and effect else ()):
        f = d / f"{tag}.json"
        if not f.is_file():
            t0 = time.perf_counter()
            diag = diagnose(load_run(run), load_batch(batch), exclude=exclude, seed=seed, cache=cache)
            doc = diag.to_json()
            doc["wall_s"] = time.perf_counter() - t0
            write_json(f, doc)
        out[tag] = json.loads(f.read_text())
    return out


def _called(doc):
    return doc["best"] if doc["best"] else doc["verdict"]


def summarise(cases):
    """Confusion matrix and the issue's scores from ``{(effect, seed): {"gap": doc, "gap_withheld": doc}}``."""
    rows = {}
    for (effect, seed), docs in cases.items():
        rows.setdefault(effect or "null", []).append(_called(docs["gap"]))
        if "gap_withheld" in docs:
            rows.setdefault(f"withheld {effect}", []).append(_called(docs["gap_withheld"]))
    strict, grouped, n_cat, shrinks, times = 0, 0, 0, {}, []
    for (effect, seed), docs in cases.items():
        times.append(docs["gap"]["seconds"])
        if not effect:
            continue
        n_cat += 1
        best = docs["gap"]["best"]
        strict += best == effect
        grouped += best is not None and (best in _group(effect) or effect in docs["gap"]["best_group"])
        for r in docs["gap"]["ranking"]:
            if r["effect"] == effect and r.get("evidence_kind") == "heldout_elpd" and r.get("shrink") is not None:
                shrinks.setdefault(effect, []).append(r["shrink"])
    null = [d["gap"]["verdict"] for (e, _), d in cases.items() if not e]
    held = [d["gap_withheld"]["verdict"] for (e, _), d in cases.items() if e and "gap_withheld" in d]
    return {
        "confusion": {k: {c: v.count(c) for c in sorted(set(v))} for k, v in rows.items()},
        "top1_strict": strict / n_cat if n_cat else None,
        "top1_grouped": grouped / n_cat if n_cat else None,
        "n_catalogue_cases": n_cat,
        "null_false_alarm": float(np.mean([v != "no_gap" for v in null])) if null else None,
        "n_null": len(null),
        "withheld_not_explained": float(np.mean([v != "explained" for v in held])) if held else None,
        "n_withheld": len(held),
        "shrink_true_effect": {k: {"median": float(np.median(v)), "min": float(np.min(v)), "n": len(v)}
                               for k, v in shrinks.items()},
        "diagnosis_seconds": {"median": float(np.median(times)), "max": float(np.max(times))} if times else None,
        "groups": [list(g) for g in GROUPS],
        "targets": {"top1_grouped": 0.85, "null_false_alarm": 0.10, "withheld_not_explained": 0.80,
                    "shrink": 0.50},
    }


def _markdown(s):
    lines = ["# Gap diagnosis: blind benchmark", "",
             "`python analyses/gap_benchmark.py` (one-module bench batches, 4 h validation at 1 Hz).", "",
             "| true effect | diagnosed (best, or verdict) |", "|---|---|"]
    for k, v in s["confusion"].items():
        lines.append(f"| {k} | " + ", ".join(f"{c} x{n}" for c, n in v.items()) + " |")
    lines += ["", f"- top-1 (groups {s['groups']} as one): {s['top1_grouped']} "
                  f"(strict {s['top1_strict']}) over {s['n_catalogue_cases']} cases; target >= 0.85",
              f"- null false alarm: {s['null_false_alarm']} over {s['n_null']}; target <= 0.10",
              f"- withheld not called explained: {s['withheld_not_explained']} over {s['n_withheld']}; "
              "target >= 0.80",
              f"- shrink with the true effect: {s['shrink_true_effect']}; target >= 0.50",
              f"- diagnosis time per batch: {s['diagnosis_seconds']}"]
    return "\n".join(lines) + "\n"


def main(argv=None):
    from tembayes.physics.effects import CATALOGUE

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="example: python analyses/gap_benchmark.py --seeds 5")
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--effects", nargs="*", default=list(CATALOGUE))
    ap.add_argument("--no-null", action="store_true")
    ap.add_argument("--no-withheld", action="store_true")
    ap.add_argument("--work", type=Path, default=Path("runs/gap_benchmark"))
    ap.add_argument("--shard", default="0/1", metavar="I/N",
                    help="run every N-th case from the I-th (two shards fill 2 cores while one calibrates)")
    ap.add_argument("--summarise", action="store_true", help="only summarise the cases already cached")
    args = ap.parse_args(argv)
    i_shard, n_shard = (int(x) for x in args.shard.split("/"))
    cases = {}
    todo = ([] if args.no_null else [None]) + list(args.effects)
    for k, (seed, effect) in enumerate((s, e) for s in range(args.seeds) for e in todo):
        if args.summarise:
            docs = _case(args.work, effect, seed, not args.no_withheld, compute=False)
            if docs is not None:
                cases[(effect, seed)] = docs
            continue
        if k % n_shard != i_shard:
            continue
        t0 = time.perf_counter()
        cases[(effect, seed)] = docs = _case(args.work, effect, seed, not args.no_withheld)
        msg = f"[{effect or 'null'} s{seed}] {_called(docs['gap'])}"
        if "gap_withheld" in docs:
            msg += f"; withheld: {_called(docs['gap_withheld'])}"
        print(msg + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    s = summarise(cases)
    if n_shard > 1 and not args.summarise:
        print(_markdown(s))  # this shard's cases; `--summarise` writes the whole table
        return
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "gap_benchmark.json").write_text(json.dumps(s, indent=1))
    (RESULTS / "gap_benchmark.md").write_text(_markdown(s))
    print(_markdown(s))


if __name__ == "__main__":
    main()
