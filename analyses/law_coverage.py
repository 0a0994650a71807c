"""Law coverage on both benches: are the posterior's 90 % intervals honest?

Batches of bench modules of two module types are simulated (the standard
bench, the calibration model's structure; or the high-fidelity out-of-model
bench), calibrated with ``tembayes calibrate`` (a model form and discrepancy
method chosen here), and each module's posterior compared with its truth:

- coverage of the 90 % intervals per law parameter and K, with its binomial
  95 % band;
- the median |error| of the posterior mean and the median 90 % width, in %;
- the median z (error in posterior sds) and the worst ones.

Resumable: every batch and run is cached under ``--work``; rerun to continue,
``--summarise`` to print and record what is there. A study continued on
another machine runs its remaining batches (``--first-batch``) and summarises
with ``--keep-recorded``: the recorded results' modules of the batches that
have no run under ``--work`` are kept.

    python analyses/law_coverage.py --fidelity high --model full --discrepancy window-sandwich --batches 13
    python analyses/law_coverage.py --fidelity standard --physics full --model full --batches 13
    python analyses/law_coverage.py ... --summarise
    python analyses/law_coverage.py ... --tag s11 --summarise --compare-to high-paper-full-robust-nested
    python analyses/law_coverage.py ... --calibration-rig analyses/rigs/reference-seats-held.toml --tag held
    python analyses/law_coverage.py ... --tag held --summarise --against-recorded high-paper-full-robust-samp
    python analyses/law_coverage.py --rig heatsink-al --fidelity standard --physics full --batches 4

Writes analyses/results/law_coverage_<label>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
from scipy.stats import binom

from tembayes.physics.rigread import SHIPPED

ROOT = Path(__file__).resolve().parent.parent
PARAMS = ("R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K")
#: The sd of a sensor's depth offset on the out-of-model bench (uniform within +-0.25 mm) [mm].
DEPTH_SD_MM = 0.5 / np.sqrt(12.0)
#: The thermistors' nominal depth below their block's nearer face on the reference rig [mm].
NOMINAL_DEPTH_MM = 2.5
#: The two module types: TEC1-12706 class and a 3 ohm, 3.9 A class.
TYPES = {
    "TEC1-12706": '[module_type]\nname = "TEC1-12706"\nth_C = 25.0\nimax_A = 6.4\nvmax_V = 14.4\ndtmax_K = 66.0\n'
    "qmax_W = 50.0\n",
    "3ohm-3.9A": '[module_type]\nname = "3ohm-3.9A"\nth_C = 25.0\nimax_A = 3.9\nvmax_V = 15.4\ndtmax_K = 68.0\n'
    "qmax_W = 34.0\n",
}


def bench_label(args):
    rig = "" if args.rig == "reference" else f"{args.rig}-"
    return f"{rig}{args.fidelity}-{args.physics}"


def label(args):
    return f"{bench_label(args)}-{args.model}-{args.discrepancy}" + (f"-{args.tag}" if args.tag else "")


def run(cmd):
    p = subprocess.run([sys.executable, "-m", "tembayes", *map(str, cmd)], capture_output=True, text=True, check=False)
    if p.returncode not in (0, 1):
        raise RuntimeError(f"{' '.join(map(str, cmd))}: {p.stderr.strip().splitlines()[-1:]}")
    return p


def one_batch(args, work, t, b):
    name = f"{t}-b{b}"
    bdir = work / "batches" / bench_label(args) / name
    if not (bdir / "truth.json").exists():
        ds = work / f"{t}.toml"
        ds.write_text(TYPES[t])
        seed = 1000 * (list(TYPES).index(t) + 1) + b
        run(
            [
                "simulate",
                bdir,
                "--modules",
                args.modules,
                "--fidelity",
                args.fidelity,
                "--physics",
                args.physics,
                "--datasheet",
                ds,
                "--seed",
                seed,
                "--validations",
                0,
                "--rig",
                args.rig,
                "--overwrite",
            ]
        )
    rdir = work / "runs" / label(args) / name
    if not (rdir / "summary.json").exists():
        cal = bdir
        if args.calibration_rig:
            cal = with_rig_file(bdir, args.calibration_rig, work / "calibration-rig" / label(args) / name, args.rig)
        run(
            [
                "calibrate",
                cal,
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
                args.workers,
                "--overwrite",
            ]
        )
    return bdir, rdir


def with_rig_file(bdir, rig_file, dest, preset):
    """A copy of the batch ``bdir`` at ``dest`` whose batch.toml calibrates with ``rig_file`` instead of ``preset``.

    The bench stays the preset's; only the calibration's description of the
    rig changes (e.g. a parameter sampled instead of held).  A copy made
    before with another rig file is refused: its runs are of that file.
    """
    if (dest / "batch.toml").exists():
        if (dest / "rig.toml").read_bytes() != Path(rig_file).read_bytes():
            raise SystemExit(f"{dest}: made with another rig file than {rig_file}; give another --tag")
        return dest
    text = (bdir / "batch.toml").read_text()
    line = f'preset = "{preset}"'
    if not re.search(f"^{re.escape(line)}$", text, flags=re.M):
        raise SystemExit(f"{bdir / 'batch.toml'}: no [rig] {line} to replace with --calibration-rig")
    tmp = dest.with_name(dest.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(bdir, tmp, ignore=shutil.ignore_patterns("truth.json"))
    shutil.copyfile(rig_file, tmp / "rig.toml")
    (tmp / "batch.toml").write_text(re.sub(f"^{re.escape(line)}$", 'file = "rig.toml"', text, flags=re.M))
    tmp.rename(dest)
    return dest


def rows(work, args):
    out = []
    for bdir in sorted((work / "batches" / bench_label(args)).glob("*")):
        rdir = work / "runs" / label(args) / bdir.name
        if not (rdir / "summary.json").exists():
            continue
        s = json.loads((rdir / "summary.json").read_text())
        truth = json.loads((bdir / "truth.json").read_text())
        for mid, m in s["modules"].items():
            row = {
                "batch": bdir.name,
                "module": mid,
                "converged": bool(m["diagnostics"]["converged"]),
                "seconds": m["diagnostics"].get("seconds"),
                "adequacy": m["diagnostics"].get("adequacy", {}).get("verdict"),
            }
            sides = truth.get("bench_layout", {}).get("depth_sides")
            if sides:  # the out-of-model bench's sensor offsets [mm], towards the next cell from the cooler
                rb = truth["modules"][mid]["rig_bench"]
                dx_mm = 10.0 / 18
                row["depth_offset_mm"] = {c: sides[c] * rb[f"v_{c}"] * dx_mm for c in ("T2", "T3")}
            bench = truth["modules"][mid]["rig_bench"]
            seats = sensor_seats(m.get("nuisance") or {}, row.get("depth_offset_mm"), bench)
            if seats:
                row["depth_mm"] = seats
            if "g_lead" in bench:  # any rig's out-of-model bench: how far its sensors read towards the room
                row["lead_share"] = bench["g_lead"] / bench["g_sensor"]
            held = (m["diagnostics"].get("discrepancy") or {}).get("held_sd_over_posterior_sd") or {}
            for p in PARAMS:
                tv = truth["modules"][mid][p]
                e = m[p]
                # each held rig value's share of the law's sd, over the sd before they were carried over
                share = {q: held[q][p] for q in held}
                row[p] = {
                    "err_pct": 100 * (e["mean"] / tv - 1),
                    "z": (e["mean"] - tv) / e["sd"],
                    "z_core": (e["mean"] - tv) / e["sd"] * float(np.sqrt(1.0 + sum(v * v for v in share.values()))),
                    "held_share": share,
                    "width_pct": 100 * (e["q95"] - e["q05"]) / abs(tv),
                    "inside": e["q05"] <= tv <= e["q95"],
                }
            out.append(row)
    return out


def sensor_seats(nuisance, offset_mm, bench):
    """The sampled thermistor depths against the bench's: ``{"T2": {"true", "mean", "sd"}, ...}`` [mm].

    Only for the depths the calibration sampled (in ``nuisance``).  On the
    out-of-model bench the true depth is the nominal one moved by the sensor's
    offset towards the cooler's far side: shallower for T2 (its block's nearer
    face is the module's, away from the cooler), deeper for T3; the in-model
    bench records the depth itself.
    """
    out = {}
    for c, away in (("T2", -1.0), ("T3", 1.0)):
        post = nuisance.get(f"depth_{c}")
        if post is None:
            continue
        if offset_mm is not None:
            true = NOMINAL_DEPTH_MM + away * offset_mm[c]
        elif f"depth_{c}" in bench:
            true = 1e3 * bench[f"depth_{c}"]
        else:
            continue
        out[c] = {"true": float(true), "mean": 1e3 * post["mean"], "sd": 1e3 * post["sd"]}
    return out


def seat_recovery(r):
    """Per sampled depth: how well the runs found the bench's seats (rms error, median sd, the truths' spread) [mm]."""
    out = {}
    for c in ("T2", "T3"):
        d = [x["depth_mm"][c] for x in r if c in x.get("depth_mm", {})]
        if len(d) < 3:
            continue
        t, m, s = (np.array([x[k] for x in d]) for k in ("true", "mean", "sd"))
        out[c] = {
            "n": len(d),
            "rms_error_mm": float(np.sqrt(np.mean((m - t) ** 2))),
            "median_sd_mm": float(np.median(s)),
            "sd_of_truths_mm": float(np.std(t)),
            "corr": float(np.corrcoef(t, m)[0, 1]),
        }
    return out


#: The per-law statistics :func:`against_recorded` compares: coverage, rms z, mean z, median |error| %, median width %.
_PAIRED_STATS = (
    lambda v, p: np.mean([x[p]["inside"] for x in v]),
    lambda v, p: np.sqrt(np.mean([x[p]["z"] ** 2 for x in v])),
    lambda v, p: np.mean([x[p]["z"] for x in v]),
    lambda v, p: np.median([abs(x[p]["err_pct"]) for x in v]),
    lambda v, p: np.median([x[p]["width_pct"] for x in v]),
)


def recorded_file(other):
    """The results file of the label ``other``."""
    return ROOT / "analyses" / "results" / f"law_coverage_{other}.json"


def against_recorded(r, other):
    """Module-by-module comparison with the recorded results of the label ``other`` (its results file).

    For the studies whose runs are not under ``--work`` (made on another
    machine): on the modules both have, per law the coverage there and here,
    the rms and mean of z, the median |error| and the median 90 % width.
    """
    path = recorded_file(other)
    old = {(x["batch"], x["module"]): x for x in json.loads(path.read_text())["modules"]}
    here = [x for x in r if (x["batch"], x["module"]) in old]
    there = [old[(x["batch"], x["module"])] for x in here]
    lines = [
        "",
        f"Against the recorded `{other}` on the same {len(here)} modules (there / here):",
        "",
        "| | coverage 90 % | rms z | mean z | median abs error % | median 90 % width % |",
        "|---|---|---|---|---|---|",
    ]
    for p in PARAMS:
        cols = [f"{f(there, p):.3f} / {f(here, p):.3f}" for f in _PAIRED_STATS]
        lines.append(f"| {p} | " + " | ".join(cols) + " |")
    return lines


#: The benches draw a rig value as a normal truncated to its documented range with sd = range / 6
#: (``tembayes.bench.bench._draw_rig``); the calibration's prior takes the range as +-2 sd (sd = range / 4).
BENCH_OVER_PRIOR_SD = 4.0 / 6.0


def carried_at_bench_spread(r, held="g_ceramic", factor=BENCH_OVER_PRIOR_SD):
    """Per law: the 90 % coverage, normal approximation, with ``held``'s carried share scaled by ``factor``.

    What the coverage would be had the calibration carried ``held`` over at
    the spread the bench draws its truths with (the mean is not moved by the
    carry-over, only the sd: ``z = z_core / sqrt(1 + sum of shares^2)``).
    Beside it the same approximation with the shares as carried, to show the
    approximation reproduces the recorded coverage.
    """
    out = {}
    for p in PARAMS:
        zc = np.array([x[p]["z_core"] for x in r])

        def cov(f, p=p, zc=zc):
            tot = [
                np.sqrt(1.0 + sum((v * (f if k == held else 1.0)) ** 2 for k, v in x[p]["held_share"].items()))
                for x in r
            ]
            return float(np.mean(np.abs(zc / np.array(tot)) < 1.6448536))

        out[p] = {"as_carried": cov(1.0), "at_bench_spread": cov(factor)}
    return out


def depth_response(off):
    """How the laws' errors follow the sensors' true depth offsets, against what the calibration carried over.

    Per law: the error in sds of the posterior before the held rig values were
    carried over (``z_core``) regressed on the T2 and T3 offsets in units of
    the uniform draw's sd (``DEPTH_SD_MM``); the slopes are what the bench's
    offsets did to the laws, ``held_*`` the median share the calibration gave
    each held depth (the same units: core sds per draw sd), and ``resid_sd``
    what is left (1 for an honest core).
    """
    out = {}
    for p in PARAMS:
        X = np.column_stack(
            [np.ones(len(off))] + [[x["depth_offset_mm"][c] / DEPTH_SD_MM for x in off] for c in ("T2", "T3")]
        )
        zc = np.array([x[p]["z_core"] for x in off])
        beta, *_ = np.linalg.lstsq(X, zc, rcond=None)
        out[p] = {
            "slope_T2": float(beta[1]),
            "slope_T3": float(beta[2]),
            "held_T2": float(np.median([x[p]["held_share"].get("depth_T2", 0.0) for x in off])),
            "held_T3": float(np.median([x[p]["held_share"].get("depth_T3", 0.0) for x in off])),
            "held_ceramic": float(np.median([x[p]["held_share"].get("g_ceramic", 0.0) for x in off])),
            "sd_z_core": float(np.std(zc)),
            "resid_sd": float(np.std(zc - X @ beta)),
        }
    return out


def summarise(r):
    n = len(r)
    lo, hi = binom.ppf(0.025, n, 0.9) / n, binom.ppf(0.975, n, 0.9) / n
    doc = {
        "n_modules": n,
        "band90": [lo, hi],
        "converged": sum(x["converged"] for x in r),
        "median_seconds": float(np.median([x["seconds"] for x in r if x["seconds"]])) if n else None,
        # runs made before the adequacy verdict have none
        "adequacy_fits": sum(x.get("adequacy") == "fits" for x in r) if any(x.get("adequacy") for x in r) else None,
    }
    off = [x for x in r if "depth_offset_mm" in x]
    if len(off) > 2:  # does the laws' error follow the sensors' depths?
        doc["corr_z_with_depth_offset"] = {
            p: {
                c: float(np.corrcoef([x["depth_offset_mm"][c] for x in off], [x[p]["z"] for x in off])[0, 1])
                for c in ("T2", "T3")
            }
            for p in ("R0_ohm", "S0_V_per_K", "K_W_per_K")
        }
    if len(off) > 5 and all(x[PARAMS[0]]["held_share"] for x in off):
        doc["depth_response"] = depth_response(off)
    if n and all(x[PARAMS[0]]["held_share"].get("g_ceramic") is not None for x in r):
        doc["coverage90_ceramic_at_bench_spread"] = carried_at_bench_spread(r)
    seats = seat_recovery(r)
    if seats:
        doc["sampled_depths"] = seats
    batches = sorted({x["batch"] for x in r})
    boot = np.random.default_rng(0).integers(0, len(batches), size=(2000, len(batches)))
    for p in PARAMS:
        # a batch's modules share its rig (the sensors' depths): resample batches, not modules
        per = [[x[p]["inside"] for x in r if x["batch"] == b] for b in batches]
        hits, counts = np.array([sum(v) for v in per]), np.array([len(v) for v in per])
        cov = hits[boot].sum(axis=1) / counts[boot].sum(axis=1)
        doc[p] = {
            "coverage90_batch_bootstrap95": [float(np.quantile(cov, 0.025)), float(np.quantile(cov, 0.975))],
            "coverage90": float(np.mean([x[p]["inside"] for x in r])),
            "median_abs_err_pct": float(np.median([abs(x[p]["err_pct"]) for x in r])),
            "median_width90_pct": float(np.median([x[p]["width_pct"] for x in r])),
            "median_abs_z": float(np.median([abs(x[p]["z"]) for x in r])),
            "max_abs_z": float(np.max([abs(x[p]["z"]) for x in r])),
        }
    return doc


def paired(work, args, other):
    """Module-by-module comparison with the runs of the label ``other`` on the same batches.

    Per law: the shift of the posterior mean in the other run's sds, the ratio
    of the sds, and how many intervals cover the truth in each; the steps per
    module.  Measures a change of the sampler on identical data.
    """
    out = {p: {"shift": [], "sd_ratio": [], "covered": [0, 0]} for p in PARAMS}
    steps = []
    for bdir in sorted((work / "batches" / bench_label(args)).glob("*")):
        a, b = (work / "runs" / lab / bdir.name / "summary.json" for lab in (other, label(args)))
        if not (a.exists() and b.exists()):
            continue
        old, new = json.loads(a.read_text())["modules"], json.loads(b.read_text())["modules"]
        truth = json.loads((bdir / "truth.json").read_text())["modules"]
        for mid in set(old) & set(new):
            steps.append((old[mid]["diagnostics"]["steps"], new[mid]["diagnostics"]["steps"]))
            for p in PARAMS:
                o, n, t = old[mid][p], new[mid][p], truth[mid][p]
                out[p]["shift"].append((n["mean"] - o["mean"]) / o["sd"])
                out[p]["sd_ratio"].append(n["sd"] / o["sd"])
                out[p]["covered"][0] += o["q05"] <= t <= o["q95"]
                out[p]["covered"][1] += n["q05"] <= t <= n["q95"]
    lines = [
        "",
        f"Against `{other}` on the same {len(steps)} modules (steps per module, median: "
        f"{np.median([x[0] for x in steps]) if steps else '-'} there, {np.median([x[1] for x in steps]) if steps else '-'} here):",
        "",
        "| | mean shift in its sds: median (max abs) | sd here / there: median [range] | covered there / here |",
        "|---|---|---|---|",
    ]
    for p in PARAMS:
        d, r = np.array(out[p]["shift"]), np.array(out[p]["sd_ratio"])
        if len(d):
            lines.append(
                f"| {p} | {np.median(d):+.2f} ({np.max(np.abs(d)):.2f}) | {np.median(r):.3f} [{r.min():.2f}, {r.max():.2f}] "
                f"| {out[p]['covered'][0]} / {out[p]['covered'][1]} |"
            )
    return lines


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fidelity", choices=("standard", "high"), default="high")
    ap.add_argument("--physics", choices=("paper", "full"), default="paper", help="the standard bench's physics")
    ap.add_argument("--model", choices=("paper", "full"), default="full")
    ap.add_argument("--discrepancy", choices=("none", "window-sandwich", "robust"), default="robust")
    ap.add_argument("--batches", type=int, default=13, help="batches per module type")
    ap.add_argument(
        "--first-batch", type=int, default=0, help="run batches from this index on (the others are not run)"
    )
    ap.add_argument(
        "--keep-recorded",
        action="store_true",
        help="summarise with the recorded results' modules of batches that have no run under --work "
        "(a study continued on another machine)",
    )
    ap.add_argument("--modules", type=int, default=4, help="modules per batch")
    ap.add_argument("--rig", default="reference", help="a shipped rig or a rig file (tembayes simulate --rig)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--work", type=Path, default=Path("/tmp/tembayes-law-coverage"))
    ap.add_argument("--shard", default="0/1", help="K/N: this process does every N-th batch from K")
    ap.add_argument("--summarise", action="store_true")
    ap.add_argument("--tag", default="", help="appended to the results' label (a variant of the code)")
    ap.add_argument(
        "--compare-to",
        metavar="LABEL",
        help="also compare module by module with the runs of another label under --work (e.g. the same study "
        "before a change of the sampler)",
    )
    ap.add_argument(
        "--calibration-rig",
        type=Path,
        metavar="FILE",
        help="calibrate with this rig file instead of the bench's preset (the bench is unchanged; needs --tag)",
    )
    ap.add_argument(
        "--against-recorded",
        metavar="LABEL",
        help="also compare module by module with another label's recorded results file (its runs need not be "
        "under --work)",
    )
    args = ap.parse_args()
    if args.calibration_rig and not args.tag:
        ap.error("--calibration-rig needs a --tag to tell its runs from the preset's")
    if args.calibration_rig and not args.calibration_rig.is_file():
        ap.error(f"--calibration-rig {args.calibration_rig}: no such file")
    if args.calibration_rig and args.rig not in SHIPPED:
        ap.error(
            f"--calibration-rig replaces a shipped rig's preset; --rig {args.rig} is not one of {', '.join(SHIPPED)}"
        )
    if args.against_recorded == label(args):
        ap.error(f"--against-recorded {args.against_recorded} is this run's own label; give another study's")
    if args.against_recorded and not recorded_file(args.against_recorded).exists():
        ap.error(f"--against-recorded: no results file {recorded_file(args.against_recorded)}; give a recorded label")
    args.work.mkdir(parents=True, exist_ok=True)
    if not args.summarise:
        k, n = (int(x) for x in args.shard.split("/"))
        jobs = [(t, b) for b in range(args.first_batch, args.batches) for t in TYPES]
        for i, (t, b) in enumerate(jobs):
            if i % n == k:
                one_batch(args, args.work, t, b)
                print(f"done {t} batch {b}", flush=True)
    r = rows(args.work, args)
    res = ROOT / "analyses" / "results"
    recorded = res / f"law_coverage_{label(args)}.json"
    if args.keep_recorded and recorded.exists():
        here = {x["batch"] for x in r}
        r = [x for x in json.loads(recorded.read_text())["modules"] if x["batch"] not in here] + r
    doc = {
        "label": label(args),
        "settings": {k: str(v) for k, v in vars(args).items()},
        "summary": summarise(r),
        "modules": r,
    }
    recorded.write_text(json.dumps(doc, indent=1) + "\n")
    s = doc["summary"]
    lines = [
        f"# Law coverage: {label(args)}",
        "",
        f"{s['n_modules']} modules ({s['converged']} converged, {s['adequacy_fits'] if s['adequacy_fits'] is not None else 'no verdict:'} whose model fits), 90 % band "
        f"[{s['band90'][0]:.3f}, {s['band90'][1]:.3f}]; median {s['median_seconds']:.0f} s per module",
        "",
        "| | coverage 90 % | its 95 % interval (batches resampled) | median abs error % | median 90 % width % "
        "| median abs z | max abs z |",
        "|---|---|---|---|---|---|---|",
    ]
    for p in PARAMS:
        q = s[p]
        lo, hi = q["coverage90_batch_bootstrap95"]
        lines.append(
            f"| {p} | {q['coverage90']:.3f} | {lo:.3f}–{hi:.3f} | {q['median_abs_err_pct']:.3f} | {q['median_width90_pct']:.3f} "
            f"| {q['median_abs_z']:.2f} | {q['max_abs_z']:.1f} |"
        )
    if "corr_z_with_depth_offset" in s:
        lines += [
            "",
            "Correlation of the error in posterior sds (z) with the sensors' depth offsets:",
            "",
            "| | T2 | T3 |",
            "|---|---|---|",
        ]
        lines += [f"| {p} | {c['T2']:+.2f} | {c['T3']:+.2f} |" for p, c in s["corr_z_with_depth_offset"].items()]
    if "depth_response" in s:
        lines += [
            "",
            "The errors against the sensors' true depth offsets: each law's error in sds of the posterior before the "
            "held rig values were carried over, regressed on the T2 and T3 offsets (per sd of the offsets' uniform "
            "draw); beside each slope the median share the calibration carried over for that depth (and for the "
            "ceramic); the sd of the errors before and after the regression:",
            "",
            "| | slope T2 | carried T2 | slope T3 | carried T3 | carried ceramic | sd | sd after |",
            "|---|---|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {p} | {d['slope_T2']:+.2f} | {d['held_T2']:.2f} | {d['slope_T3']:+.2f} | {d['held_T3']:.2f} "
            f"| {d['held_ceramic']:.2f} | {d['sd_z_core']:.2f} | {d['resid_sd']:.2f} |"
            for p, d in s["depth_response"].items()
        ]
    if "coverage90_ceramic_at_bench_spread" in s:
        c = s["coverage90_ceramic_at_bench_spread"]
        lines += [
            "",
            "Coverage 90 % (normal approximation) as carried, and with the ceramic carried at the spread the bench "
            "draws it with (sd = range / 6; the calibration's prior: range / 4):",
            "",
            "| | as carried | ceramic at the bench's spread |",
            "|---|---|---|",
        ]
        lines += [f"| {p} | {d['as_carried']:.3f} | {d['at_bench_spread']:.3f} |" for p, d in c.items()]
    if "sampled_depths" in s:
        lines += [
            "",
            "The thermistors' depths the runs sampled, against the bench's [mm]:",
            "",
            "| | modules | rms error | median posterior sd | sd of the bench's depths | correlation |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {c} | {d['n']} | {d['rms_error_mm']:.3f} | {d['median_sd_mm']:.3f} | {d['sd_of_truths_mm']:.3f} | {d['corr']:.2f} |"
            for c, d in s["sampled_depths"].items()
        ]
    if args.compare_to:
        lines += paired(args.work, args, args.compare_to)
    if args.against_recorded:
        lines += against_recorded(r, args.against_recorded)
    (res / f"law_coverage_{label(args)}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
