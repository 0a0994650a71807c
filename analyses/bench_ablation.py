"""Which ingredient of the out-of-model bench moves a module's laws? Switch them off one at a time.

A module of a batch made by ``tembayes simulate --rig RIG --fidelity high``
(any rig file's out-of-model bench, :mod:`tembayes.bench.anyrig`) is made
again with single ingredients of that bench switched off, with the same
random streams (the same sampling times, drifts and noise), and each
variant is calibrated as ``tembayes calibrate`` does by default.  The
laws' errors in posterior sds then say which ingredient the misses come
from.  The variant ``none`` switches nothing off: it must reproduce the
batch's identification run bit for bit (refused otherwise, since the bench
code then differs from the one that made the batch).

Ingredients (:data:`SWITCHES`): ``offsets`` (each block sensor's contact
with the next cell deeper in, ``v_<column>``), ``leads`` (the sensors'
leads to the room), ``edges`` (the module plates' edge leaks), ``slow``
(the sensors' slow noise), ``all`` (the four together).

``--calibrate-rig FILE`` calibrates every variant with that rig file
instead of the batch's rig (e.g. one whose sensor depths are sampled).

    python analyses/bench_ablation.py WORK/batches/reference-faces-high-full/TEC1-12706-b1 --module TEM1 --work ABL
    python analyses/bench_ablation.py BATCH --module TEM1 --work ABL2 --switch offsets --calibrate-rig rig.toml --label sampled

Writes analyses/results/bench_ablation_<label>.{json,md}.
"""

from __future__ import annotations

import argparse
import copy
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from tembayes.bench.bench import BenchConfig, bench_setup, identification_run, run_experiment
from tembayes.data.batch import Datasheet
from tembayes.data.write import write_experiment_csv

PARAMS = ("R0_ohm", "R1_ohm_per_K", "S0_V_per_K", "S1_V_per_K2", "K_W_per_K")
#: A conductance switched off: small enough to carry no heat, positive for the network.
OFF_W_PER_K = 1e-12
SWITCHES = ("offsets", "leads", "edges", "slow", "all")
RESULTS = Path(__file__).resolve().parent / "results"


def bench_config(truth: dict, batch: Path) -> BenchConfig:
    """The configuration that made ``batch`` (its truth.json), refused unless it is an any-rig out-of-model bench."""
    g = truth["generator"]
    if g["fidelity"] != "high" or g["rig"] in (None, {"preset": "reference"}):
        sys.exit(
            f"{batch}: not a rig file's out-of-model bench (simulate --rig RIG --fidelity high); nothing to switch"
        )
    if g.get("protocol") is not None:
        sys.exit(f"{batch}: made with --protocol; remake it without one")
    rig = dict(g["rig"])
    if "file" in rig:
        rig["file"] = str((batch / rig["file"]).resolve())
    return BenchConfig(
        n_modules=len(truth["modules"]),
        seed=g["seed"],
        datasheet=Datasheet.from_table(truth["datasheet"], batch / "truth.json"),
        rate=g["rate_Hz"],
        hold=g["hold_s"],
        fidelity="high",
        rig=rig,
        n_validations=0,
    )


def switched(module: dict, run: dict, switch: str) -> tuple[dict, dict]:
    """The module's bench values and the run's options with ``switch`` off."""
    module, run = copy.deepcopy(module), dict(run)
    values = module["rig_bench"]
    off = SWITCHES[:-1] if switch == "all" else (switch,)
    for name in off:
        if name == "offsets":
            values.update({k: 0.0 for k in values if k.startswith("v_")})
        elif name == "leads":
            values["g_lead"] = OFF_W_PER_K
        elif name == "edges":
            values["leak_module"] = OFF_W_PER_K
        elif name == "slow":
            run["slow_noise"] = None
    return module, run


def make_variant(batch: Path, truth: dict, mid: str, switch: str, out: Path, rig_file: Path | None):
    """Write the one-module batch of ``switch`` to ``out``; ``none`` must reproduce the batch's run."""
    config = bench_config(truth, batch)
    bench = bench_setup(config)
    i = list(config.module_ids).index(mid)
    module, run = switched(bench.truth["modules"][mid], bench.run, switch)
    protocol = identification_run(run["rig"], config.datasheet.imax, config.hold)
    exp = run_experiment(protocol, module, bench.effects, bench.module_rngs[i], rate=config.rate, **run)
    if out.exists():
        shutil.rmtree(out)
    (out / mid).mkdir(parents=True)
    write_experiment_csv(out / mid / "identification.csv", exp)
    if switch == "none":
        made = pd.read_csv(out / mid / "identification.csv")
        given = pd.read_csv(batch / mid / "identification.csv")
        if made.shape != given.shape or not np.array_equal(made.to_numpy(), given.to_numpy()):
            sys.exit(f"{batch / mid / 'identification.csv'}: not reproduced by this code's bench; remake the batch")
    toml = (batch / "batch.toml").read_text()
    if rig_file is not None:
        shutil.copy(rig_file, out / "rig.toml")
        toml = toml.split("[rig]")[0] + '[rig]\nfile = "rig.toml"\n'
    (out / "batch.toml").write_text(toml)
    kept = {**truth, "modules": {mid: {**truth["modules"][mid], "rig_bench": module["rig_bench"]}}}
    (out / "truth.json").write_text(json.dumps(kept, indent=1))


def calibrate(variant: Path, run: Path):
    if (run / "summary.json").exists():
        return
    cmd = [sys.executable, "-m", "tembayes", "calibrate", variant, "--out", run, "--seed", "0"]
    cmd += ["--model", "full", "--discrepancy", "robust", "--quiet", "--no-figures", "--workers", "1", "--overwrite"]
    p = subprocess.run(list(map(str, cmd)), capture_output=True, text=True, check=False)
    if p.returncode not in (0, 1):
        sys.exit(f"calibrate {variant}: {p.stderr.strip().splitlines()[-1:]}")


def row(variant: Path, run: Path, mid: str, switch: str) -> dict:
    s = json.loads((run / "summary.json").read_text())["modules"][mid]
    truth = json.loads((variant / "truth.json").read_text())["modules"][mid]
    rig = {
        k: {"mean": v["mean"], "sd": v["sd"], "bench": truth["rig_bench"].get(k)}
        for k, v in s["nuisance"].items()
        if k in truth["rig_bench"]
    }
    return {
        "switch": switch,
        "converged": bool(s["diagnostics"]["converged"]),
        "z": {p: (s[p]["mean"] - truth[p]) / s[p]["sd"] for p in PARAMS},
        "inside": {p: bool(s[p]["q05"] <= truth[p] <= s[p]["q95"]) for p in PARAMS},
        "rig": rig,
    }


def markdown(rows: list[dict], args) -> str:
    lines = [
        f"# Bench ablation: {args.batch} {args.module}",
        "",
        f"`python analyses/bench_ablation.py {args.batch} --module {args.module} --switch {' '.join(args.switch)}"
        + (f" --calibrate-rig {args.calibrate_rig}" if args.calibrate_rig else "")
        + "`",
        "",
        "The laws' errors in posterior sds (the default calibration), with the bench's ingredient switched off;",
        "the rig parameters the posterior moves most, posterior mean (bench value).",
        "",
        "| switched off | " + " | ".join(PARAMS) + " | converged | rig (posterior mean, bench) |",
        "|---|" + "---|" * (len(PARAMS) + 2),
    ]
    for r in rows:
        worst = sorted(
            (k for k, v in r["rig"].items() if v["bench"]),
            key=lambda k: -abs(r["rig"][k]["mean"] / r["rig"][k]["bench"] - 1),
        )[:3]
        rig = ", ".join(f"{k} {r['rig'][k]['mean']:.4g} ({r['rig'][k]['bench']:.4g})" for k in worst)
        z = " | ".join(f"{r['z'][p]:+.2f}" for p in PARAMS)
        lines.append(f"| {r['switch']} | {z} | {'yes' if r['converged'] else 'no'} | {rig} |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("batch", type=Path, help="a batch made by tembayes simulate --rig RIG --fidelity high")
    ap.add_argument("--module", default="TEM1")
    ap.add_argument("--switch", nargs="+", choices=SWITCHES, default=list(SWITCHES))
    ap.add_argument("--work", type=Path, required=True, help="where the variants and their runs go (resumable)")
    ap.add_argument("--calibrate-rig", type=Path, help="a rig file every variant is calibrated with")
    ap.add_argument("--label", default="", help="appended to the results' name")
    args = ap.parse_args()
    truth = json.loads((args.batch / "truth.json").read_text())
    if args.module not in truth["modules"]:
        sys.exit(f"{args.batch / 'truth.json'}: no module {args.module}; it has {', '.join(truth['modules'])}")
    rows = []
    for switch in ("none", *args.switch):
        variant, run = args.work / switch, args.work / "runs" / switch
        if not (variant / "truth.json").exists():
            make_variant(args.batch, truth, args.module, switch, variant, args.calibrate_rig)
        print(f"{switch}: calibrating", file=sys.stderr, flush=True)
        calibrate(variant, run)
        rows.append(row(variant, run, args.module, switch))
    name = f"bench_ablation_{args.batch.name}_{args.module}" + (f"_{args.label}" if args.label else "")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / f"{name}.json").write_text(json.dumps({"batch": str(args.batch), "rows": rows}, indent=1))
    (RESULTS / f"{name}.md").write_text(markdown(rows, args))
    print(markdown(rows, args))


if __name__ == "__main__":
    main()
