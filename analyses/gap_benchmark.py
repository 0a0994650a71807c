"""Blind check of the gap diagnosis: does ``tembayes gap`` name the effect it was not told?

For every row -- the null bench (no effect), each catalogue effect at its
default magnitude, and each effect *withheld* (the diagnosis run with that
effect removed from its catalogue) -- and every seed:

1. ``tembayes simulate`` a one-module bench batch (identification at 5 Hz, a
   4-hour validation run at 1 Hz) with the effect switched on;
2. ``tembayes calibrate`` it with the base model (its defaults);
3. diagnose it with :func:`tembayes.gap.diagnose.diagnose`, exactly what
   ``tembayes gap`` runs, which reads the batch's CSV files and the run only
   (never ``truth.json``; the benchmark knows the effect from its own row).

Printed: the confusion matrix (true effect x diagnosed best, or the verdict
when there is no best), top-1 attribution on the catalogue rows (strict, and
with the confusable groups below scored as one), the null false-alarm rate,
the withheld rows not called ``explained``, the shrink of the gap when the
true effect is recalibrated, and the effect's size recovered against the
bench's (from the catalogue's defaults, the same numbers ``simulate`` used).

The same cases answer whether the laws stay honest with an effect the model
does not have: each case's ``laws.json`` holds the base run's 90 % intervals,
its adequacy verdict, and the intervals of the gap's recalibration (the best
effect added) against ``truth.json``; summarised per effect as the coverage,
the share covered *or* flagged by the adequacy verdict, and the coverage after
the gap (targets: both >= 0.80).  Effects the default model contains
(``thomson``, ``sensor_lag``, ``k_temperature``) are in-model rows.

Stated before the runs (physics, not results):

- confusable groups: ``sensor_lag`` / ``contact_resistance`` (both delay the
  sensors' view of a block's response to the module's heat) and
  ``k_temperature`` / ``ambient_leak`` (both change the steady heat balance
  in proportion to the distance from room temperature);
- the shrink is scored where the base model leaves a *held-out* gap (the
  validation runs or the identification run's held-out step windows:
  ``gap.json``'s ``gap_in``).  An effect the base model absorbs in one of its
  own rig parameters -- ``contact_resistance`` is a paste conductance below
  any paste, ``ambient_leak`` an enclosure leak above the enclosure's, both
  by construction of the rig -- leaves no held-out gap to shrink; there the
  "how far" is whether the effect puts the parameter back in its documented
  range, scored as such.

Targets: top-1 >= 0.85 (groups as one), null false alarm <= 10 %, withheld not
``explained`` >= 80 %, shrink >= 50 % when the true effect is added.

    python analyses/gap_benchmark.py                 # 5 seeds x (null + 8 effects + 8 withheld), resumable
    python analyses/gap_benchmark.py --seeds 2 --effects sensor_lag joule_split
    python analyses/gap_benchmark.py --shard 0/2 & python analyses/gap_benchmark.py --shard 1/2; \
        python analyses/gap_benchmark.py --summarise

Another rig (``--rig``, a shipped rig or a rig file, simulated by ``tembayes
simulate --rig`` at the standard fidelity): the null cases only unless
``--effects`` names some, cached under ``runs/gap_benchmark_<rig>/`` and
recorded as ``gap_benchmark_<rig>_null`` (``--label`` overrides).  The null
cases' verdicts are listed one by one with what raised an alarm (the
significant cells, the out-of-range parameters, the gap in K):

    python analyses/gap_benchmark.py --rig heatsink-al --seeds 10 --jobs 1

Each case is cached under ``runs/gap_benchmark/<effect>_s<seed>/`` (batch,
run, ``gap.json``, ``gap_withheld.json``, ``timing.json``); an interrupted
benchmark resumes at its first unfinished case.
About 10 min per effect case on 2 cores (base calibration 2-10 min on one
core, diagnosis 3-8 min on two).  Results:
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
    subprocess.run(
        [sys.executable, "-m", "tembayes", *args], check=check, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )


def _case(work, effect, seed, withheld, compute=True, fidelity="standard", rig=None, jobs=None):
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
    timing = {}
    if not (run / "summary.json").is_file():
        d.mkdir(parents=True, exist_ok=True)
        eff = ["--effect", effect] if effect else []
        t0 = time.perf_counter()
        _tembayes(
            "simulate",
            str(batch),
            "--modules",
            "1",
            "--seed",
            str(1000 + seed),
            "--validation-rate",
            "1",
            "--fidelity",
            fidelity,
            "--overwrite",
            *eff,
            *(["--rig", rig] if rig else []),
        )
        timing["simulate_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        # exit status 1 = a module not converged: a misspecified model often is; the run is written
        _tembayes(
            "calibrate",
            str(batch),
            "--out",
            str(run),
            "--seed",
            str(seed),
            "--no-figures",
            "--quiet",
            "--overwrite",
            check=False,
        )
        if not (run / "summary.json").is_file():
            raise RuntimeError(f"calibrating {batch} wrote no run")
        timing["calibrate_s"] = time.perf_counter() - t0
        (d / "timing.json").write_text(json.dumps(timing, indent=1))
    out, cache = {}, {}  # the withheld diagnosis reuses the other candidates' recalibrations
    for tag, exclude in (("gap", ()),) + ((("gap_withheld", (effect,)),) if withheld and effect else ()):
        f = d / f"{tag}.json"
        if not f.is_file():
            t0 = time.perf_counter()
            diag = diagnose(load_run(run), load_batch(batch), exclude=exclude, seed=seed, cache=cache, jobs=jobs)
            doc = diag.to_json()
            doc["wall_s"] = time.perf_counter() - t0
            if tag == "gap":
                write_json(d / "laws.json", _laws(d, diag))
            write_json(f, doc)
        out[tag] = json.loads(f.read_text())
    return out


def _laws(d, diag):
    """The laws against the bench's truth: the base run's (with its adequacy verdict) and the gap's recalibration's."""
    from tembayes.calibrate.results import stats
    from tembayes.calibrate.run import load_run
    from tembayes.constants import MODULE_PARAMETERS

    truth = json.loads((d / "batch" / "truth.json").read_text())
    base = load_run(d / "run").summary
    out = {}
    for mid, m in base.modules.items():
        recal = diag.recalibration.get(mid)
        out[mid] = {
            "truth": {k: truth["modules"][mid][k] for k in MODULE_PARAMETERS},
            "base": {k: {"q05": m.laws[k].q05, "q95": m.laws[k].q95} for k in MODULE_PARAMETERS},
            "adequacy_flagged": m.adequacy_failed,
            "converged": m.converged,
            "recalibrated_with": diag.best if recal is not None else None,
            "recalibrated": None if recal is None else {k: stats(recal.draws[k]) for k in MODULE_PARAMETERS},
        }
    return out


def _by_parameter(v):
    """``R0 0.90, R1 0.80, ...``: a law row's coverage per parameter (absent in rows summarised before it)."""
    by = v.get("coverage90_by_parameter") or {}
    return ", ".join(f"{k.split('_')[0]} {c:.2f}" for k, c in by.items()) or "–"


def law_coverage(work, cases):
    """Per effect: the base laws' 90 % coverage, the share covered or flagged, the coverage after the gap's recalibration."""
    from tembayes.constants import MODULE_PARAMETERS

    per = {}
    for effect, seed in cases:
        f = work / f"{effect or 'null'}_s{seed}" / "laws.json"
        if not f.is_file():
            continue
        for m in json.loads(f.read_text()).values():
            after = m["recalibrated"] or m["base"]
            for k in MODULE_PARAMETERS:
                t = m["truth"][k]
                inside = m["base"][k]["q05"] <= t <= m["base"][k]["q95"]
                row = per.setdefault(effect or "null", {"inside": [], "inside_or_flagged": [], "after": [], "by": {}})
                row["inside"].append(inside)
                row["by"].setdefault(k, []).append(inside)
                row["inside_or_flagged"].append(inside or m["adequacy_flagged"])
                row["after"].append(after[k]["q05"] <= t <= after[k]["q95"])
    return {
        e: {
            "modules": len(r["inside"]) // len(MODULE_PARAMETERS),
            "coverage90": float(np.mean(r["inside"])),
            "covered_or_flagged": float(np.mean(r["inside_or_flagged"])),
            "coverage90_after_gap": float(np.mean(r["after"])),
            # a module's five laws miss together (the R0-S0-K ridge): per parameter, over modules
            "coverage90_by_parameter": {k: float(np.mean(v)) for k, v in r["by"].items()},
        }
        for e, r in per.items()
    }


def _called(doc):
    return doc["best"] if doc["best"] else doc["verdict"]


def _true_row(doc, effect):
    """The true effect's row of a diagnosis's ranking (recalibrated or only screened), or None."""
    return next((r for r in doc["ranking"] if r["effect"] == effect), None)


def null_cases(cases):
    """The null cases one by one: the verdict and what raised it (significant cells, parameters, the gap)."""
    out = []
    for (effect, seed), docs in sorted(cases.items(), key=lambda kv: kv[0][1]):
        if effect:
            continue
        doc = docs["gap"]
        base = doc.get("base") or {}
        out.append(
            {
                "seed": seed,
                "verdict": doc["verdict"],
                "best": doc["best"],
                "gap_in": doc.get("gap_in", []),
                "validation_gap_K": base.get("gap"),
                "validation_rmse_T_K": base.get("rmse_T"),
                "identification_gap_sd": base.get("identification_gap"),
                "significant_cells_validation": sum(r.get("significant_cells", 0) for r in base.get("runs", [])),
                "where": [
                    {k: w.get(k) for k in ("channel", "regime", "kind", "module", "run", "score", "p", "outside90")}
                    for w in doc.get("where", [])
                ],
                "seconds": doc.get("wall_s", doc.get("seconds")),
            }
        )
    return out


def summarise(cases):
    """Confusion matrix and the benchmark's scores from ``{(effect, seed): {"gap": doc, "gap_withheld": doc}}``."""
    from tembayes.physics.effects import CATALOGUE

    rows = {}
    for (effect, _seed), docs in sorted(cases.items(), key=lambda kv: (kv[0][0] or "", kv[0][1])):
        rows.setdefault(effect or "null", []).append(_called(docs["gap"]))
        if "gap_withheld" in docs:
            rows.setdefault(f"withheld {effect}", []).append(_called(docs["gap_withheld"]))
    strict, grouped, n_cat, shrinks, resolved, sizes, times, group_sizes = 0, 0, 0, {}, {}, {}, [], []
    for (effect, _seed), docs in cases.items():
        doc = docs["gap"]
        times.append(doc["seconds"])
        if doc["best"]:
            group_sizes.append(len(doc["best_group"]))
        if not effect:
            continue
        n_cat += 1
        best = doc["best"]
        strict += best == effect
        grouped += best is not None and (best in _group(effect) or effect in doc["best_group"])
        r = _true_row(doc, effect)
        if r is None or r.get("evidence") is None:
            continue
        gap_in = set(doc.get("gap_in", ()))
        if gap_in & {"validation", "identification"} and r.get("shrink") is not None:
            shrinks.setdefault(effect, []).append(r["shrink"])
        elif "parameters" in gap_in:
            resolved.setdefault(effect, []).append(bool(r.get("conflicts_resolved")))
        first = CATALOGUE[effect].parameters[0]
        for _m, sz in (r.get("size") or {}).items():
            est = sz[first.name].get("median", sz[first.name].get("mode"))
            sizes.setdefault(effect, []).append(est / first.default)
    all_shrinks = [x for v in shrinks.values() for x in v]
    null = [d["gap"]["verdict"] for (e, _), d in cases.items() if not e]
    held = [d["gap_withheld"]["verdict"] for (e, _), d in cases.items() if e and "gap_withheld" in d]
    return {
        "confusion": {k: {c: v.count(c) for c in sorted(set(v))} for k, v in rows.items()},
        "top1_strict": strict / n_cat if n_cat else None,
        "top1_grouped": grouped / n_cat if n_cat else None,
        "n_catalogue_cases": n_cat,
        "mean_best_group_size": float(np.mean(group_sizes)) if group_sizes else None,
        "null_false_alarm": float(np.mean([v != "no_gap" for v in null])) if null else None,
        "n_null": len(null),
        "withheld_not_explained": float(np.mean([v != "explained" for v in held])) if held else None,
        "n_withheld": len(held),
        "shrink_true_effect": {
            k: {"median": float(np.median(v)), "min": float(np.min(v)), "n": len(v)} for k, v in shrinks.items()
        },
        "shrink_true_effect_all": float(np.median(all_shrinks)) if all_shrinks else None,
        "shrink_true_effect_min": float(np.min(all_shrinks)) if all_shrinks else None,
        "conflicts_resolved_true_effect": {
            k: {"fraction": float(np.mean(v)), "n": len(v)} for k, v in resolved.items()
        },
        "size_over_truth": {
            k: {"median": float(np.median(v)), "min": float(np.min(v)), "max": float(np.max(v)), "n": len(v)}
            for k, v in sizes.items()
        },
        "diagnosis_seconds": {"median": float(np.median(times)), "max": float(np.max(times))} if times else None,
        "groups": [list(g) for g in GROUPS],
        "targets": {"top1_grouped": 0.85, "null_false_alarm": 0.10, "withheld_not_explained": 0.80, "shrink": 0.50},
    }


def _minutes(x):
    return "–" if x is None else f"{x:.1f} min"


def _markdown(s, command="python analyses/gap_benchmark.py"):
    on = f" on the {s['rig']} rig" if s.get("rig") else ""
    lines = [
        f"# Gap diagnosis: blind benchmark{on}",
        "",
        f"`{command}` (one-module bench batches, 4 h validation at 1 Hz).",
        "",
        "| true effect | diagnosed (best, or verdict) |",
        "|---|---|",
    ]
    for k, v in s["confusion"].items():
        lines.append(f"| {k} | " + ", ".join(f"{c} x{n}" for c, n in v.items()) + " |")

    def f(x):
        return "–" if x is None else f"{x:.2f}"

    lines += [
        "",
        f"- top-1 (groups {s['groups']} as one): {f(s['top1_grouped'])} "
        f"(strict {f(s['top1_strict'])}) over {s['n_catalogue_cases']} cases; target >= 0.85; "
        f"mean size of the reported best group {f(s['mean_best_group_size'])}",
        f"- null false alarm: {f(s['null_false_alarm'])} over {s['n_null']}; target <= 0.10",
        f"- withheld not called explained: {f(s['withheld_not_explained'])} over {s['n_withheld']}; target >= 0.80",
        f"- shrink of the held-out gap with the true effect: median {f(s['shrink_true_effect_all'])}, "
        f"least {f(s['shrink_true_effect_min'])}; target >= 0.50",
        "",
    ]
    lines += [
        "| true effect | shrink median | shrink least | n | size / bench (median, range) |",
        "|---|---|---|---|---|",
    ]
    for k in sorted(
        set(s["shrink_true_effect"]) | set(s["size_over_truth"]) | set(s["conflicts_resolved_true_effect"])
    ):
        sh = s["shrink_true_effect"].get(k)
        cr = s["conflicts_resolved_true_effect"].get(k)
        sz = s["size_over_truth"].get(k)
        cell = (
            f"{sh['median']:.2f} | {sh['min']:.2f} | {sh['n']}"
            if sh
            else f"(gap in the parameters: back in range {cr['fraction']:.0%}) | – | {cr['n']}"
            if cr
            else "– | – | 0"
        )
        size = f"{sz['median']:.2f} ({sz['min']:.2f}-{sz['max']:.2f})" if sz else "–"
        lines.append(f"| {k} | {cell} | {size} |")
    if s.get("law_coverage"):
        lines += [
            "",
            "The laws against the bench's truth (90 % intervals of the five law parameters; "
            "target: covered or flagged by the adequacy verdict, and covered after the gap's recalibration, >= 0.80):",
            "",
            "| true effect | modules | coverage | covered or flagged | coverage after gap | per parameter |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {k} | {v['modules']} | {v['coverage90']:.2f} | {v['covered_or_flagged']:.2f} "
            f"| {v['coverage90_after_gap']:.2f} | {_by_parameter(v)} |"
            for k, v in s["law_coverage"].items()
        ]
    if s.get("null_cases"):
        lines += [
            "",
            "Null cases (no effect on the bench; an alarm is any verdict but `no_gap`):",
            "",
            "| seed | verdict | gap in | validation gap | T RMSE | identification gap | alarms (channel, regime, score) "
            "| case time |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for c in s["null_cases"]:
            alarms = "; ".join(
                f"{w['module']} {w['channel']} {w['regime']}"
                + (f" ({w['run']})" if w.get("run") else "")
                + (f" score {w['score']:.2f}" if w.get("score") is not None else "")
                for w in c["where"]
            )
            g = c["validation_gap_K"]
            rm = c["validation_rmse_T_K"]
            ig = c["identification_gap_sd"]
            lines.append(
                f"| {c['seed']} | {c['verdict']}{' (' + c['best'] + ')' if c['best'] else ''} "
                f"| {', '.join(c['gap_in']) or '–'} | {'–' if g is None else f'{g:.4f} K'} "
                f"| {'–' if rm is None else f'{rm:.4f} K'} | {'–' if ig is None else f'{ig:.3f} sd'} "
                f"| {alarms or '–'} | {_minutes(c.get('case_minutes'))} |"
            )
    lines += [
        "",
        f"- diagnosis time per batch: median {s['diagnosis_seconds']['median']:.0f} s, "
        f"max {s['diagnosis_seconds']['max']:.0f} s"
        if s["diagnosis_seconds"]
        else "",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None):
    from tembayes.physics.effects import CATALOGUE

    ap = argparse.ArgumentParser(
        description=__doc__.split("\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="example: python analyses/gap_benchmark.py --seeds 5",
    )
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--effects", nargs="*", default=None, help="default: the catalogue (another rig: none)")
    ap.add_argument("--no-null", action="store_true")
    ap.add_argument("--no-withheld", action="store_true")
    ap.add_argument("--work", type=Path, default=None, help="default runs/gap_benchmark[_RIG]")
    ap.add_argument(
        "--shard",
        default="0/1",
        metavar="I/N",
        help="run every N-th case from the I-th (two shards fill 2 cores while one calibrates)",
    )
    ap.add_argument(
        "--fidelity",
        choices=("standard", "high"),
        default="standard",
        help="the bench: standard (the model's own structure) or high (out-of-model); use one --work per bench",
    )
    ap.add_argument(
        "--rig",
        default="reference",
        help="the bench's rig (tembayes simulate --rig): a shipped rig or a rig file; with --fidelity",
    )
    ap.add_argument("--jobs", type=int, default=None, help="the diagnosis's worker processes (default: cores + 1)")
    ap.add_argument("--summarise", action="store_true", help="only summarise the cases already cached")
    ap.add_argument("--label", default="", help="results as gap_benchmark_LABEL.{json,md} (a partial rerun)")
    args = ap.parse_args(argv)
    rig = None if args.rig == "reference" else args.rig
    rig_tag = Path(rig).stem if rig else ""
    if args.effects is None:
        args.effects = [] if rig else list(CATALOGUE)
    if args.work is None:
        args.work = Path("runs/gap_benchmark" + (f"_{rig_tag}" if rig else ""))
    if rig and not args.label:
        args.label = f"{rig_tag}_null" if not args.effects else rig_tag
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
        cases[(effect, seed)] = docs = _case(
            args.work, effect, seed, not args.no_withheld, fidelity=args.fidelity, rig=rig, jobs=args.jobs
        )
        msg = f"[{effect or 'null'} s{seed}] {_called(docs['gap'])}"
        if "gap_withheld" in docs:
            msg += f"; withheld: {_called(docs['gap_withheld'])}"
        print(msg + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
        if rig and n_shard == 1:  # another rig's cases are long: the results so far after each
            _record(args, cases, rig, argv, quiet=True)
    _record(args, cases, rig, argv, quiet=False, shard=n_shard > 1 and not args.summarise)


def _record(args, cases, rig, argv, *, quiet, shard=False):
    """Summarise ``cases`` and write ``analyses/results/gap_benchmark[_LABEL].{json,md}`` (a shard: print only)."""
    s = summarise(cases)
    s["law_coverage"] = law_coverage(args.work, cases)
    if rig:
        s["rig"] = rig
        s["null_cases"] = null_cases(cases)
        for c in s["null_cases"]:
            t = args.work / f"null_s{c['seed']}" / "timing.json"
            steps = json.loads(t.read_text()) if t.is_file() else {}
            if steps and c["seconds"] is not None:
                c["case_minutes"] = (steps["simulate_s"] + steps["calibrate_s"] + c["seconds"]) / 60.0
    command = "python analyses/gap_benchmark.py" + (" " + " ".join(argv or sys.argv[1:]) if rig else "")
    if shard:
        print(_markdown(s, command))  # this shard's cases; `--summarise` writes the whole table
        return
    RESULTS.mkdir(exist_ok=True)
    name = "gap_benchmark" + (f"_{args.label}" if args.label else "")
    (RESULTS / f"{name}.json").write_text(json.dumps(s, indent=1))
    (RESULTS / f"{name}.md").write_text(_markdown(s, command))
    if not quiet:
        print(_markdown(s, command))


if __name__ == "__main__":
    main()
