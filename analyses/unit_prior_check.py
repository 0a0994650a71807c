"""A new unit of a known type after a short test: does the type's population as its prior help, and stay honest?

One lot of a module type on the out-of-model bench (``--fidelity high``; one
seed draws the type's centre, the rig and every unit): its first
``--earlier`` units are the earlier batch, identified on the 0.83 h staircase
(0.2 A, 120 s) and calibrated as usual; ``--new`` more units of the same lot
run the short staircase (``--design STEP:HOLD``) and are calibrated in
batches of ``--per-batch``, once with the earlier run's population as each
unit's prior on the laws (``calibrate --unit-prior``) and once without.  Per
law: coverage of the truth by the 90 % intervals, the median ratio of the
unit's sd with / without the prior, and the sd ``design --population``
predicted; and the share of units whose R0 and S0 both reach 0.5 % (sd).

The bench draws a new type centre for every seed, as a new lot of a real type
would differ (R0 by ~4 %, the slopes by 10-15 %): ``design_check.py
--population`` on batches of other seeds is the negative control, a prior
taken from another lot.

    python analyses/unit_prior_check.py --design 0.2:100        (~1 h on 1 core)
    python analyses/unit_prior_check.py --design 0.2:100 --summarise

Writes analyses/results/unit_prior_check_s<STEP>-h<HOLD>.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from design_check import _reach  # noqa: E402
from law_coverage import PARAMS, TYPES, run  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "analyses" / "results"
EARLIER_PROTOCOL = (0.2, 120.0)


def _protocol(work, designer, step, hold):
    from tembayes.design.protocol import write_protocol

    f = work / f"protocol-s{step:g}-h{hold:g}.csv"
    if not f.exists():
        write_protocol(f, designer.protocol(step, hold))
    return f


def _simulate(out, n, args, dsfile, proto):
    if not (out / "truth.json").exists():
        run(["simulate", out, "--modules", n, "--fidelity", "high", "--datasheet", dsfile, "--seed", args.seed,
             "--validations", 0, "--protocol", proto, "--overwrite"])  # fmt: skip


def _calibrate(batch, out, *extra):
    if not (out / "summary.json").exists():
        run(["calibrate", batch, "--out", out, "--seed", 0, "--quiet", "--no-figures", "--workers", 1,
             "--overwrite", *extra])  # fmt: skip


def _tag(args):
    """The new units' staircase as a folder name."""
    step, hold = (float(v) for v in args.design.split(":"))
    return f"s{step:g}-h{hold:g}"


def new_batches(work, args):
    """The new units of the lot, split into batch folders of ``--per-batch`` (truth.json kept for the check)."""
    lot = work / f"lot-{_tag(args)}"
    truth = json.loads((lot / "truth.json").read_text())
    ids = [f"TEM{i + 1}" for i in range(args.earlier, args.earlier + args.new)]
    out = []
    for b in range(0, len(ids), args.per_batch):
        d = work / "new" / _tag(args) / f"b{b // args.per_batch}"
        if not d.exists():
            tmp = d.with_name(d.name + ".tmp")
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir(parents=True)
            shutil.copy(lot / "batch.toml", tmp / "batch.toml")
            part = ids[b : b + args.per_batch]
            for m in part:
                shutil.copytree(lot / m, tmp / m)
            (tmp / "truth.json").write_text(json.dumps({**truth, "modules": {m: truth["modules"][m] for m in part}}))
            tmp.rename(d)
        out.append(d)
    return out


def rows(batch, rdir):
    """Per module: each law's sd, mean and whether the 90 % interval holds the truth."""
    if not (rdir / "summary.json").exists():
        return []
    s = json.loads((rdir / "summary.json").read_text())
    truth = json.loads((batch / "truth.json").read_text())
    out = []
    for mid, m in s["modules"].items():
        row = {"module": f"{batch.name}/{mid}"}
        for p in PARAMS:
            tv, e = truth["modules"][mid][p], m[p]
            row[p] = {
                "sd": e["sd"],
                "mean": e["mean"],
                "inside": e["q05"] <= tv <= e["q95"],
                "z": (e["mean"] - tv) / e["sd"],
            }
        out.append(row)
    return out


def summarise(with_prior, without, predicted, prior_json):
    both = {r["module"] for r in with_prior} & {r["module"] for r in without}
    w = {r["module"]: r for r in with_prior}
    n = {r["module"]: r for r in without}
    laws = {}
    for p in PARAMS:
        laws[p] = {
            "coverage90_with": float(np.mean([r[p]["inside"] for r in with_prior])) if with_prior else None,
            "coverage90_without": float(np.mean([r[p]["inside"] for r in without])) if without else None,
            "z_mean_with": float(np.mean([r[p]["z"] for r in with_prior])) if with_prior else None,
            "z_mean_without": float(np.mean([r[p]["z"] for r in without])) if without else None,
            "sd_with_over_without": float(np.median([w[m][p]["sd"] / n[m][p]["sd"] for m in both])) if both else None,
            "predicted_sd_rel_with": predicted["with"][p],
            "predicted_sd_rel_without": predicted["without"][p],
            "realised_sd_rel_with_median": float(np.median([r[p]["sd"] / abs(r[p]["mean"]) for r in with_prior]))
            if with_prior
            else None,
            "prior_sd_rel": prior_json["priors"][p]["scale"]
            if p in ("R0_ohm", "S0_V_per_K", "K_W_per_K")
            else prior_json["priors"][p]["scale"] / abs(prior_json["priors"][p]["center"]),
        }
    return {
        "modules_with": len(with_prior),
        "modules_without": len(without),
        "laws": laws,
        "R0_S0_reach_0.5%": {"with": _reach(with_prior), "without": _reach(without)},
        "unit_prior": prior_json,
    }


def markdown(res, args):
    lines = [
        "# A new unit of a known type: its population as the prior (out-of-model bench)",
        "",
        f"`python analyses/unit_prior_check.py --earlier {args.earlier} --new {args.new} --per-batch {args.per_batch} "
        f"--design {args.design} --seed {args.seed}`: {res['modules_with']} new units of the lot with the prior, "
        f"{res['modules_without']} without; the earlier run's {args.earlier} units on the 0.83 h staircase.",
        "",
        "| law | prior sd % | predicted sd % with / without | realised sd % with (median) | sd with / without "
        "(median, same units) | coverage 90 % with | without | mean z with | without |",
        "|---|---|---|---|---|---|---|---|---|",
    ]

    def f(v, fmt="{:.2f}"):
        return "–" if v is None else fmt.format(v)

    for p, v in res["laws"].items():
        lines.append(
            f"| {p} | {f(100 * v['prior_sd_rel'])} | {f(100 * v['predicted_sd_rel_with'], '{:.3f}')} / "
            f"{f(100 * v['predicted_sd_rel_without'], '{:.3f}')} | "
            f"{f(None if v['realised_sd_rel_with_median'] is None else 100 * v['realised_sd_rel_with_median'], '{:.3f}')}"
            f" | {f(v['sd_with_over_without'], '{:.3f}')} | {f(v['coverage90_with'])} | {f(v['coverage90_without'])} "
            f"| {f(v['z_mean_with'], '{:+.2f}')} | {f(v['z_mean_without'], '{:+.2f}')} |"
        )
    lines += ["", "Units whose R0 and S0 both reach 0.5 % (sd):", ""]
    for k, x in res["R0_S0_reach_0.5%"].items():
        lines.append(
            f"- {k} the prior: "
            + ("no runs" if x is None else f"{x['share']:.2f} (largest {100 * x['largest']:.2f} %)")
        )
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--earlier", type=int, default=8, help="units of the earlier batch")
    ap.add_argument("--new", type=int, default=20, help="new units of the same lot")
    ap.add_argument("--per-batch", type=int, default=4)
    ap.add_argument("--design", default="0.2:100", metavar="STEP:HOLD", help="the new units' staircase")
    ap.add_argument("--seed", type=int, default=1900, help="the lot (type centre, rig, units)")
    ap.add_argument("--type", default="TEC1-12706", choices=list(TYPES))
    ap.add_argument("--draws", type=int, default=4, help="modules the prediction averages over")
    ap.add_argument("--work", type=Path, default=ROOT / "runs" / "unit_prior_check")
    ap.add_argument("--summarise", action="store_true")
    args = ap.parse_args(argv)
    from tembayes.calibrate.earlier import unit_prior_of_run
    from tembayes.data import load_batch_toml
    from tembayes.design.search import Designer

    work = args.work
    work.mkdir(parents=True, exist_ok=True)
    dsfile = work / f"{args.type}.toml"
    dsfile.write_text(TYPES[args.type])
    ds = load_batch_toml(dsfile)[0]
    step, hold = (float(v) for v in args.design.split(":"))
    plain = Designer(ds, None, seed=0, n_draws=args.draws, jobs=1, say=print)
    if not args.summarise:
        _simulate(work / "earlier", args.earlier, args, dsfile, _protocol(work, plain, *EARLIER_PROTOCOL))
        _calibrate(work / "earlier", work / "earlier-run")
        _simulate(work / f"lot-{_tag(args)}", args.earlier + args.new, args, dsfile, _protocol(work, plain, step, hold))
    prior = unit_prior_of_run(work / "earlier-run", ds.name)
    informed = Designer(ds, None, seed=0, n_draws=args.draws, jobs=1, say=print, law_prior=prior)
    predicted = {
        "with": informed.evaluate([(step, hold)])[0].sd_rel(),
        "without": plain.evaluate([(step, hold)])[0].sd_rel(),
    }
    with_prior, without = [], []
    for b in new_batches(work, args):
        if not args.summarise:
            _calibrate(b, work / "runs" / _tag(args) / "unit-prior" / b.name, "--unit-prior", work / "earlier-run")
            _calibrate(b, work / "runs" / _tag(args) / "datasheet" / b.name)
            print(f"{b.name} done", flush=True)
        with_prior += rows(b, work / "runs" / _tag(args) / "unit-prior" / b.name)
        without += rows(b, work / "runs" / _tag(args) / "datasheet" / b.name)
    res = summarise(with_prior, without, predicted, prior.to_json())
    from tembayes.data.write import write_json

    write_json(RESULTS / f"unit_prior_check_{_tag(args)}.json", res)
    text = markdown(res, args)
    (RESULTS / f"unit_prior_check_{_tag(args)}.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
