"""Does a design keep its promise?  Predicted against realised posterior sds, per protocol.

For each staircase (``--designs STEP:HOLD ...``, step for the reference
module [A], hold [s]) the widths ``tembayes design`` predicts (the standard
bench's drawn modules, :class:`tembayes.design.search.Designer`) are compared
with the posterior sds ``tembayes calibrate`` realises on bench batches run
with that staircase (``simulate --protocol``): the out-of-model bench
(``--fidelity high``) by default.  The same batch seeds for every design, so
each module is calibrated under every protocol.  Per design and law: the
median of realised / predicted sd (target 0.75-1.33 for R0, S0, K and
0.67-1.5 for R1, S1), its 10-90 % range over modules, the laws' 90 %
coverage of the truth, and the mean of (posterior mean - truth) / sd over the
modules (a bias in sds; near 0 for an honest calibration).

With ``--population RUN`` (an earlier run of the type) the prediction and
every calibration take RUN's population as the units' prior on the laws
(``design --population``, ``calibrate --unit-prior``); the same batches are
calibrated, and each law's sd is compared with the same module's without
that prior where that run exists.  Both tables give the share of units whose
R0 and S0 reach 0.5 % (sd), the issue's target for a new unit of a known type.

    python analyses/design_check.py --batches 5 --modules 4                 (~1 h a design on 1 core)
    python analyses/design_check.py --batches 5 --modules 4 --summarise
    python analyses/design_check.py --batches 5 --modules 4 --designs 0.8:240 0.8:120 --population RUN

    python analyses/design_check.py --rig heatsink-al --designs 0.2:600 0.2:240 0.2:100
    python analyses/design_check.py --designs 0.2:240 0.2:240:2 --suffix rate   (STEP:HOLD:RATE, RATE in Hz; default 5)
    python analyses/design_check.py --designs 0.2:100:5:0.8:-1.8 --suffix span   (STEP:HOLD:RATE:TOP:BOTTOM, turning levels in A)

Writes analyses/results/design_check_<fidelity>[_<rig>][_<type>][_unit-prior][_<suffix>].{json,md} (no rig suffix for
the reference rig, no type suffix for TEC1-12706).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from tembayes.bench.protocols import REFERENCE_TURNS_A
from tembayes.constants import RATE_HZ

sys.path.insert(0, str(Path(__file__).resolve().parent))
from law_coverage import PARAMS, TYPES, run  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "analyses" / "results"
DEFAULT_DESIGNS = ("0.2:600", "0.2:120", "0.8:240")


def _designs(texts):
    """``STEP:HOLD[:RATE[:TOP:BOTTOM]]`` -> ``(step, hold, rate, top, bottom)``: the rate [Hz] the reference
    rig's and the turning levels [A, reference module] the reference staircase's unless given."""
    out = []
    for t in texts:
        v = t.split(":")
        if len(v) not in (2, 3, 5):
            raise SystemExit(
                f"--designs {t}: write STEP:HOLD, STEP:HOLD:RATE or STEP:HOLD:RATE:TOP:BOTTOM, e.g. 0.2:240:5:0.8:-1.8"
            )
        v = [float(x) for x in v]
        rate = v[2] if len(v) > 2 else RATE_HZ
        out.append((v[0], v[1], rate, *(v[3:] or REFERENCE_TURNS_A)))
    return out


def _name(step, hold, rate, top, bottom):
    turns = "" if (top, bottom) == REFERENCE_TURNS_A else f"-t{top:g}_{bottom:g}"
    return f"s{step:g}-h{hold:g}" + ("" if rate == RATE_HZ else f"-r{rate:g}") + turns


def _datasheet(work, t):
    from tembayes.data import load_batch_toml

    f = work / f"{t}.toml"
    f.write_text(TYPES[t])
    return f, load_batch_toml(f)[0]


def _rig_config(rig):
    """The ``[rig]`` table of ``--rig`` (None for the reference rig, as the designer takes it)."""
    from tembayes.physics.rigread import rig_source

    return None if rig == "reference" else rig_source(rig)


def predicted(designs, ds, n_draws, population=None, rig="reference"):
    """``{design name: Evaluated}`` of the designer (the standard bench's drawn modules, seed 0).

    A design slower than the rig's rate is predicted as ``tembayes design`` promises it: the same
    staircase at the rig's rate with only its data's part widened (:func:`~tembayes.design.search.at_slower_rate`).
    """
    from tembayes.calibrate.earlier import unit_prior_of_run
    from tembayes.design.search import Designer, at_slower_rate

    law_prior = None if population is None else unit_prior_of_run(population, ds.name)
    d = Designer(ds, _rig_config(rig), seed=0, n_draws=n_draws, jobs=1, say=print, law_prior=law_prior)
    fast = d.evaluate([(c[0], c[1], d.rate_hz, *c[3:]) for c in designs])
    out = [e if e.rate_Hz >= f.rate_Hz else at_slower_rate(f, e) for e, f in zip(d.evaluate(designs), fast)]
    return {_name(*c): e for c, e in zip(designs, out)}, d


def one(work, args, t, dsfile, designer, step, hold, rate, top, bottom, b):
    """Simulate and calibrate batch ``b`` of type ``t`` under one staircase sampled at ``rate`` [Hz]; the run folder."""
    from tembayes.design.protocol import write_protocol

    name = _name(step, hold, rate, top, bottom)
    proto = work / f"{t}-{name}.csv" if args.rig == "reference" else work / f"{t}-{name}-{_bench(args)}.csv"
    if not proto.exists():
        write_protocol(proto, designer.protocol(step, hold, top, bottom))
    bdir = work / "batches" / _bench(args) / name / f"{t}-b{b}"
    if not (bdir / "truth.json").exists():
        seed = 1000 * (list(TYPES).index(t) + 1) + b
        run(["simulate", bdir, "--modules", args.modules, "--fidelity", args.fidelity, "--datasheet", dsfile,
             "--seed", seed, "--validations", 0, "--protocol", proto, "--rate", rate, *_rig_option(args),
             "--overwrite"])  # fmt: skip
    rdir = work / "runs" / _bench(args) / (name + _tag(args)) / f"{t}-b{b}"
    prior = [] if args.population is None else ["--unit-prior", args.population]
    if not (rdir / "summary.json").exists():
        run(["calibrate", bdir, "--out", rdir, "--seed", 0, "--quiet", "--no-figures", "--workers", 1,
             "--overwrite", *prior])  # fmt: skip
    return bdir, rdir


def _rig_option(args):
    """``simulate``'s ``--rig``: none for the reference rig, whose out-of-model bench draws its sensor depths
    (``--rig reference`` would give the rig file's generic out-of-model bench instead)."""
    return [] if args.rig == "reference" else ["--rig", args.rig]


def _rig_label(rig):
    """A shipped rig's name, or a rig file's stem and the first digits of its content's hash (two files
    of the same name never share a folder)."""
    import hashlib

    from tembayes.physics.rigread import rig_source

    source = rig_source(rig)
    if "preset" in source:
        return source["preset"]
    return f"{Path(rig).stem}-{hashlib.sha256(Path(rig).read_bytes()).hexdigest()[:8]}"


def _bench(args):
    """The batches' and runs' folder of the bench: its fidelity, and the rig unless the reference."""
    return args.fidelity if args.rig == "reference" else f"{_rig_label(args.rig)}-{args.fidelity}"


def _tag(args):
    """The run folders' and result files' suffix: calibrated under an earlier run's population, or not."""
    return "" if args.population is None else "_unit-prior"


def rows(work, args, t, name, tag=None):
    """Per module of every calibrated batch: each law's sd, mean and whether its 90 % interval holds the truth."""
    out = []
    tag = _tag(args) if tag is None else tag
    for bdir in sorted((work / "batches" / _bench(args) / name).glob(f"{t}-b*")):
        rdir = work / "runs" / _bench(args) / (name + tag) / bdir.name
        if not (rdir / "summary.json").exists():
            continue
        s = json.loads((rdir / "summary.json").read_text())
        truth = json.loads((bdir / "truth.json").read_text())
        for mid, m in s["modules"].items():
            row = {"batch": bdir.name, "module": mid, "converged": bool(m["diagnostics"]["converged"])}
            for p in PARAMS:
                tv, e = truth["modules"][mid][p], m[p]
                row[p] = {
                    "sd": e["sd"],
                    "inside": e["q05"] <= tv <= e["q95"],
                    "mean": e["mean"],
                    "z": (e["mean"] - tv) / e["sd"],
                }
            out.append(row)
    return out


BANDS = {"R0_ohm": (0.75, 1.33), "S0_V_per_K": (0.75, 1.33), "K_W_per_K": (0.75, 1.33)}


def _paired(rs, ref_rows, p):
    """Median over the modules run under both: this design's realised sd over the reference design's."""
    ref = {(r["batch"], r["module"]): r[p]["sd"] for r in ref_rows}
    r = [x[p]["sd"] / ref[(x["batch"], x["module"])] for x in rs if (x["batch"], x["module"]) in ref]
    return float(np.median(r)) if r else None


#: The issue's target for a new unit of a known type: R0 and S0 to this relative sd.
UNIT_TARGET = 0.005


def _reach(rs):
    """Share of the modules whose R0 and S0 both reach :data:`UNIT_TARGET`, and the largest of their relative sds."""
    rel = [max(x[p]["sd"] / abs(x[p]["mean"]) for p in ("R0_ohm", "S0_V_per_K")) for x in rs]
    return {"share": float(np.mean(np.array(rel) <= UNIT_TARGET)), "largest": float(max(rel))} if rel else None


def _z_shift(rs, first_rows, p):
    """Mean over the modules run under both of z minus the first design's z, and its se with the batches as clusters.

    The batches are the independent units: a batch's modules share its rig draw, whose error they share.
    """
    ref = {(r["batch"], r["module"]): r[p]["z"] for r in first_rows}
    d = [(x["batch"], x[p]["z"] - ref[(x["batch"], x["module"])]) for x in rs if (x["batch"], x["module"]) in ref]
    if not d:
        return None, None
    means = [np.mean([v for b, v in d if b == u]) for u in sorted({b for b, _ in d})]
    se = float(np.std(means, ddof=1) / np.sqrt(len(means))) if len(means) > 1 else None
    return float(np.mean([v for _, v in d])), se


def summarise(per, pred, without=None):
    """Per design and law: realised / predicted sd, coverage, the realised sd against the first design's
    (and against the same modules without the unit prior, ``without``)."""
    out = {}
    first = next(iter(per.values()))
    for name, rs in per.items():
        e = pred[name]
        cell = {"modules": len(rs), "duration_h": e.duration_s / 3600, "laws": {}, "R0_S0_reach_0.5%": _reach(rs)}
        if without is not None:
            cell["without_unit_prior"] = {"R0_S0_reach_0.5%": _reach(without[name]), "modules": len(without[name])}
        for p in PARAMS:
            r = np.array([x[p]["sd"] for x in rs]) / e.sd[p]
            lo, hi = BANDS.get(p, (0.67, 1.5))
            cell["laws"][p] = {
                "predicted_sd_rel": e.sd[p] / abs(e.mean[p]),
                "ratio_median": float(np.median(r)) if len(r) else None,
                "ratio_p10": float(np.quantile(r, 0.1)) if len(r) else None,
                "ratio_p90": float(np.quantile(r, 0.9)) if len(r) else None,
                "band": [lo, hi],
                "coverage90": float(np.mean([x[p]["inside"] for x in rs])) if rs else None,
                # a bias of the posterior means, in their sds (0 for an honest calibration)
                "z_mean": float(np.mean([x[p]["z"] for x in rs])) if rs else None,
                "realised_over_first_design": _paired(rs, first, p),
            }
            shift, se = _z_shift(rs, first, p)
            cell["laws"][p].update(z_shift_from_first_design=shift, z_shift_se=se)
            if without is not None:
                cell["laws"][p]["realised_over_without_unit_prior"] = _paired(rs, without[name], p)
        out[name] = cell
    return out


def markdown(res, args):
    prior = args.population is not None
    pop = f" --population {args.population}" if prior else ""
    lines = [
        f"# Design check: predicted against realised posterior sds ({args.fidelity} bench"
        + (", units under an earlier run's population)" if prior else ")"),
        "",
        f"`python analyses/design_check.py --batches {args.batches} --modules {args.modules} "
        f"--fidelity {args.fidelity} --rig {args.rig} --type {args.type} --designs {' '.join(args.designs)}{pop}"
        + (f" --suffix {args.suffix}" if args.suffix else "")
        + "` (the prediction "
        f"from {args.draws} modules the standard bench draws, seed 0).",
        "",
        "| design | h | modules | law | predicted sd % | realised / predicted (median) | 10-90 % | band | coverage 90 % "
        "| mean z | z − the first design's (se, batches as clusters) | realised sd / the first design's (same modules, median) |"
        + (" with / without the unit prior |" if prior else ""),
        "|---|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if prior else ""),
    ]

    def num(v, f="{:.2f}"):
        return "–" if v is None else f.format(v)

    for name, c in res["designs"].items():
        for p, v in c["laws"].items():
            rng = "–" if v["ratio_p10"] is None else f"{v['ratio_p10']:.2f}–{v['ratio_p90']:.2f}"
            lines.append(
                f"| {name} | {c['duration_h']:.2f} | {c['modules']} | {p} | {100 * v['predicted_sd_rel']:.3f} "
                f"| {num(v['ratio_median'])} | {rng} | {v['band'][0]}–{v['band'][1]} | {num(v['coverage90'])} "
                f"| {num(v['z_mean'], '{:+.2f}')} "
                f"| {num(v['z_shift_from_first_design'], '{:+.2f}')} ({num(v['z_shift_se'])}) "
                f"| {num(v['realised_over_first_design'])} |"
                + (f" {num(v.get('realised_over_without_unit_prior'))} |" if prior else "")
            )
    lines += ["", f"Units whose R0 and S0 both reach {100 * UNIT_TARGET:g} % (sd):", ""]
    for name, c in res["designs"].items():
        r = c["R0_S0_reach_0.5%"]
        text = "no runs" if r is None else f"{r['share']:.2f} of {c['modules']} (largest {100 * r['largest']:.2f} %)"
        if prior:
            w = c["without_unit_prior"]["R0_S0_reach_0.5%"]
            n = c["without_unit_prior"]["modules"]
            text += "; without the unit prior " + (
                "not run" if w is None else f"{w['share']:.2f} of {n} (largest {100 * w['largest']:.2f} %)"
            )
        lines.append(f"- {name} ({c['duration_h']:.2f} h): {text}")
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--designs", nargs="+", default=list(DEFAULT_DESIGNS), metavar="STEP:HOLD[:RATE[:TOP:BOTTOM]]")
    ap.add_argument("--batches", type=int, default=5)
    ap.add_argument("--modules", type=int, default=4)
    ap.add_argument("--type", default="TEC1-12706", choices=list(TYPES))
    ap.add_argument("--fidelity", default="high", choices=("standard", "high"))
    ap.add_argument(
        "--rig", default="reference", help="a shipped rig or a rig file (on plates that hold both faces: 0.4 A steps)"
    )
    ap.add_argument("--draws", type=int, default=4, help="modules the prediction averages over")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "design_check")
    ap.add_argument(
        "--population", type=Path, metavar="RUN", help="an earlier run of the type: its population as the units' prior"
    )
    ap.add_argument("--summarise", action="store_true")
    ap.add_argument(
        "--suffix", default="", help="appended to the result files' name, so that one study keeps another's record"
    )
    args = ap.parse_args(argv)
    args.work.mkdir(parents=True, exist_ok=True)
    designs = _designs(args.designs)
    dsfile, ds = _datasheet(args.work, args.type)
    pred, designer = predicted(designs, ds, args.draws, args.population, args.rig)
    if not args.summarise:
        for b in range(args.batches):
            for c in designs:
                one(args.work, args, args.type, dsfile, designer, *c, b)
                print(f"{_name(*c)} b{b} done", flush=True)
    per = {_name(*c): rows(args.work, args, args.type, _name(*c)) for c in designs}
    without = None if args.population is None else {n: rows(args.work, args, args.type, n, tag="") for n in per}
    res = {"type": args.type, "fidelity": args.fidelity, "rig": args.rig, "designs": summarise(per, pred, without)}
    if args.population is not None:
        res["unit_prior"] = designer.options.law_prior.to_json()
    from tembayes.data.write import write_json

    rig = "" if args.rig == "reference" else f"_{_rig_label(args.rig)}"
    stem = (
        f"design_check_{args.fidelity}{rig}"
        + ("" if args.type == "TEC1-12706" else f"_{args.type}")
        + _tag(args)
        + (f"_{args.suffix}" if args.suffix else "")
    )
    write_json(RESULTS / f"{stem}.json", res)
    text = markdown(res, args)
    (RESULTS / f"{stem}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
