"""Are the predictive bands honest?  RMSE and band coverage on fresh validation runs.

Uses the calibrated bench batches of ``analyses/calibration_study.py`` (cached
under ``runs/calibration_study``; run that first).  For every calibrated
module it records a fresh 4-hour validation run on the bench (random holds of
300-1200 s between -1.6 and +0.9 A, 1 Hz, the module's true parameters, a
finer rig than the model, drifts and noise: a *correctly specified* bench, no
catalogue effect) and predicts it with ``tembayes.predict.predict`` exactly as
``tembayes predict`` does: linear laws and, side by side, R and S constant at
35 degC.  For every batch it also makes a *new* unit of the batch's type (laws
drawn from the bench's population, the batch's cooler and enclosure, a new
mount) and predicts its validation run with ``--module population``.

Targets: linear-law RMSE <= 0.25 K on each of T1-T4; 90 % band
coverage within 85-95 % on a correctly specified bench; the constant model
visibly worse at T-bar far from 35 degC.

    python analyses/predict_study.py                # all cached batches (~25 min on 2 cores)
    python analyses/predict_study.py --quick        # 2 batches
    python analyses/predict_study.py --draws 500    # as many draws as the CLI default

Results: ``analyses/results/predict_study.json`` and ``predict_study.md``.

A rig (``--rig``, the reference rig too): the law-coverage study's calibrations of that rig
(``analyses/law_coverage.py --rig RIG --fidelity F --physics full``,
model ``full``, discrepancy ``robust``): batches under
``WORK/batches/RIG-F-full``, runs under
``WORK/runs/RIG-F-full-full-robust`` (``--fidelity``: ``standard``, the
in-model bench, or ``high``, the out-of-model one).  Every calibrated module gets a
fresh validation run (the same protocol, 1 Hz) on the batch's own bench: the
rig file at the bench's resolution (:func:`tembayes.bench.bench.batch_bench_rig`;
out-of-model, with the sensor bodies, leads and edge leaks at the module's
drawn values, and the slow sensor noise) with the bench's own physics
(Thomson heat, K slope, sensor lag from ``truth.json``'s
``bench_layout.physics``), as ``tembayes simulate`` made the identification
runs.  The channels are the rig's sensors and ``voltage_V``.
The new-unit (``--module population``) part is left out there (its mount is
drawn from the reference rig's parameters), and so, unless ``--constant``, is
the constant-law comparison (it doubles the time); with ``--constant`` the
T-bar table is of the rig's cold-face sensor.  Targets there (the open
issue's): RMSE <= 0.1 K on each temperature channel, 90 % coverage in
85-95 %.

    python analyses/predict_study.py --work /work/lawcov_anyrig --rig heatsink-al --jobs 1
    python analyses/predict_study.py --work /work/lawcov_anyrig --rig reference-faces --jobs 1
    python analyses/predict_study.py --work /work/lawcov_leads --rig heatsink-al --fidelity high --jobs 1
    python analyses/predict_study.py --work WORK --rig reference --fidelity high --jobs 2

(``law_coverage.py`` writes the reference rig's folders as ``batches/<fidelity>-<physics>`` and
``runs/<label>``, without the rig's name: link them as ``WORK/batches/reference-F-full`` and
``WORK/runs/reference-F-full-full-robust``.)

Results: ``analyses/results/predict_study_RIG.json`` and ``predict_study_RIG.md``
(``predict_study_RIG-high.*`` out-of-model); the validation runs are cached under
``WORK/validations/RIG-F-full``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

RESULTS = Path(__file__).resolve().parent / "results"
CHANNELS = ("T1_C", "T2_C", "T3_C", "T4_C", "voltage_V")


def _validation(truth_module, datasheet, seed, path, truth=None, layout=None):
    """Record a fresh validation run of a bench module and load it like a user's CSV.

    ``truth`` (a batch's ``truth.json``) given: on that batch's own bench (its rig and physics),
    as :func:`tembayes.bench.bench.simulate_batch` ran it; otherwise the reference hifi rig.
    """
    from tembayes.bench import bench as B
    from tembayes.bench import hifi
    from tembayes.bench.protocols import validation_cycle
    from tembayes.data import load_experiment
    from tembayes.data.write import write_experiment_csv

    if not path.is_file():
        rng = np.random.default_rng(seed)
        proto = validation_cycle(rng, datasheet.imax)
        slow = None
        if truth is None:
            rig, physics = hifi.hifi_rig(), {}
        else:
            gen = truth["generator"]
            high = gen["fidelity"] == "high"  # its physics is its own ("high-fidelity"), in bench_layout
            config = B.BenchConfig(
                rig=gen["rig"],
                physics="full" if high else gen["physics"],
                fidelity=gen["fidelity"],
                datasheet=datasheet,
            )
            rig, physics = B.batch_bench_rig(config, truth), dict(truth["bench_layout"]["physics"])
            slow = B.SLOW_NOISE if high else None
        exp = B.run_experiment(
            proto,
            truth_module,
            physics,
            rng,
            rate=1.0,
            rig=rig,
            t0=float(np.round(rng.uniform(0, 1000), 3)),
            slow_noise=slow,
        )
        path.parent.mkdir(parents=True, exist_ok=True)
        write_experiment_csv(path, exp)
    return load_experiment(path, datasheet=datasheet, layout=layout)


def _new_unit(truth, rng):
    """A new module of the batch's type: population laws with the bench's unit spread, the batch's
    cooler and enclosure, a new mount (paste, plates, legs)."""
    from tembayes.bench import bench as B

    pop = truth["population"]
    laws = {k: v * (1.0 + B.UNIT_SPREAD[k] * rng.standard_normal()) for k, v in pop.items()}
    first = next(iter(truth["modules"].values()))["rig_bench"]
    rig = {k: first[k] for k in ("g_cooler", "leak_top", "leak_bottom")}
    for k in ("g_paste_hot", "g_paste_cold", "c_plate_hot", "c_plate_cold", "c_legs"):
        rig[k] = B._draw_rig(rng, k)
    return {**laws, "outlier": False, "rig_bench": rig}


def _dirs(work, rig, name, fidelity="standard"):
    """The batch, run and validation folders of batch ``name`` (``rig`` None: the calibration study's)."""
    if rig is None:
        return work / "batches" / name, work / "runs" / name, work / "validations" / name
    bench = f"{rig}-{fidelity}-full"
    return (
        work / "batches" / bench / name,
        work / "runs" / f"{bench}-full-robust" / name,
        work / "validations" / bench / name,
    )


def study_batch(args):
    name, work, n_draws, rig, constant, fidelity = args
    from tembayes.calibrate.run import load_run
    from tembayes.data import load_batch
    from tembayes.predict import predict

    bdir, rdir, vdir = _dirs(work, rig, name, fidelity)
    batch = load_batch(bdir)
    run = load_run(rdir)
    truth = json.loads((bdir / "truth.json").read_text())
    rows = []
    # independent runs per batch
    seed0 = zlib.crc32(f"predict-study/{name}".encode() if rig is None else f"predict-study/{rig}/{name}".encode())
    targets = [(mid, truth["modules"][mid], mid) for mid in run.module_ids]
    if rig is None:
        targets.append(("population", _new_unit(truth, np.random.default_rng(seed0 + 999)), "NEW"))
    for k, (module, tmod, tag) in enumerate(targets):
        t0 = time.perf_counter()
        exp = _validation(
            tmod,
            batch.datasheet,
            seed0 + k,
            vdir / f"{tag}.csv",
            truth=None if rig is None else truth,
            layout=None if rig is None else batch.layout,
        )
        res = predict(
            run, exp, module, batch, n_draws=n_draws, seed=k, compare_constant=constant and module != "population"
        )
        row = {
            "batch": name,
            "module": tag,
            "kind": "population" if module == "population" else "module",
            "channels": list(res.linear.channels),
            "face": list(res.linear.face),
            "linear": res.linear.metrics(),
            "linear_by_Tavg": res.linear.by_tavg(),
            "seconds": time.perf_counter() - t0,
            "predictive_s": res.linear.seconds,
        }
        if res.constant is not None:
            row["constant"] = res.constant.metrics()
            row["constant_by_Tavg"] = res.constant.by_tavg()
        rows.append(row)
        chans = row["channels"]
        print(
            f"{name}/{tag}: RMSE "
            + " ".join(f"{row['linear'][c]['rmse']:.4f}" for c in chans)
            + ", cov90 "
            + " ".join(f"{row['linear'][c]['coverage90']:.2f}" for c in chans)
            + f"  ({row['seconds']:.0f} s)",
            flush=True,
        )
    return rows


def summarise(rows, channels=CHANNELS, tavg_channel="T3_C", tavg_key="T3_rmse_by_Tavg"):
    out = {}
    for kind in ("module", "population"):
        R = [r for r in rows if r["kind"] == kind]
        if not R:
            continue
        s = {"n_runs": len(R)}
        for ch in channels:
            cov = {lv: np.array([r["linear"][ch][f"coverage{lv}"] for r in R]) for lv in (50, 90, 95)}
            rmse = np.array([r["linear"][ch]["rmse"] for r in R])
            s[ch] = {
                **{f"coverage{lv}_mean": float(cov[lv].mean()) for lv in cov},
                **{
                    f"coverage{lv}_se": float(cov[lv].std(ddof=1) / np.sqrt(len(R))) if len(R) > 1 else None
                    for lv in cov
                },
                "coverage90_runs_in_85_95": float(np.mean((cov[90] >= 0.85) & (cov[90] <= 0.95))),
                "rmse_median": float(np.median(rmse)),
                "rmse_max": float(rmse.max()),
            }
        out[kind] = s
    # constant vs linear by T-bar (pooled over module runs): RMSE per 5 K bin, sample-weighted
    bins = {}
    for r in rows:
        for model in ("linear", "constant"):
            for b in r.get(f"{model}_by_Tavg", []):
                key = b["Tavg_C_low"]
                d = bins.setdefault(key, {"linear": [0.0, 0], "constant": [0.0, 0]})
                if r["kind"] != "module":
                    continue
                d[model][0] += b["rmse"][tavg_channel] ** 2 * b["n"]
                d[model][1] += b["n"]
    out[tavg_key] = [
        {
            "Tavg_C_low": k,
            "linear": float(np.sqrt(v["linear"][0] / v["linear"][1])),
            "constant": float(np.sqrt(v["constant"][0] / v["constant"][1])),
            "n": v["linear"][1],
        }
        for k, v in sorted(bins.items())
        if v["linear"][1] and v["constant"][1]
    ]
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("runs/calibration_study"))
    ap.add_argument("--draws", type=int, default=300)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument(
        "--rig",
        default=None,
        help="a rig's law-coverage calibrations under WORK (batches/RIG-standard-full, "
        "runs/RIG-standard-full-full-robust; 'reference' too); module predictions only",
    )
    ap.add_argument("--constant", action="store_true", help="with --rig: the constant-law comparison too")
    ap.add_argument(
        "--fidelity", choices=("standard", "high"), default="standard", help="with --rig: the bench of the calibrations"
    )
    args = ap.parse_args(argv)
    rig = args.rig
    if rig is None and args.fidelity != "standard":
        sys.exit("--fidelity high needs --rig (the calibration study's batches are in-model)")
    runs = args.work / "runs" if rig is None else _dirs(args.work, rig, "", args.fidelity)[1]
    names = sorted(p.name for p in runs.iterdir() if (p / "summary.json").is_file()) if runs.is_dir() else []
    if not names:
        hint = "analyses/calibration_study.py" if rig is None else f"analyses/law_coverage.py --rig {rig}"
        sys.exit(f"no calibrated batches under {runs}: run {hint} first")
    if args.quick:
        names = names[:2]
    constant = rig is None or args.constant
    t0 = time.time()
    os.environ["NUMBA_NUM_THREADS"] = "1"  # the workers run one draw loop each
    import multiprocessing as mp

    with ProcessPoolExecutor(max_workers=args.jobs, mp_context=mp.get_context("spawn")) as ex:
        jobs = [(n, args.work, args.draws, rig, constant, args.fidelity) for n in names]
        rows = [r for rs in ex.map(study_batch, jobs) for r in rs]
    if rig is None:
        channels, cold, tkey, stem = CHANNELS, "T3_C", "T3_rmse_by_Tavg", "predict_study"
    else:  # the rig's sensors and the voltage; the T-bar table of its cold-face sensor
        channels, cold = tuple(rows[0]["channels"]), rows[0]["face"][1]
        tkey = "cold_face_rmse_by_Tavg"
        stem = f"predict_study_{rig}" + ("" if args.fidelity == "standard" else f"-{args.fidelity}")
    summ = summarise(rows, channels, cold, tkey)
    doc = {
        "command": "python analyses/predict_study.py " + " ".join(argv or sys.argv[1:]),
        **(
            {}
            if rig is None
            else {"rig": rig, "fidelity": args.fidelity, "channels": list(channels), "cold_face_channel": cold}
        ),
        "n_draws": args.draws,
        "batches": names,
        "minutes": (time.time() - t0) / 60.0,
        "summary": summ,
        "runs": rows,
    }
    RESULTS.mkdir(exist_ok=True)
    from tembayes.data import write_json

    write_json(RESULTS / f"{stem}.json", doc)
    on = "" if rig is None else f" on the {rig} rig" + (", out-of-model" if args.fidelity == "high" else "")
    lines = [f"# Predictive study{on} ({len(rows)} validation runs, {args.draws} draws, {doc['minutes']:.0f} min)", ""]
    if rig is not None:
        lines += [
            f"`{doc['command']}`: the law-coverage calibrations (full model, robust discrepancy), a fresh 4 h "
            "validation run at 1 Hz per module on the batch's own bench; module predictions only.",
            "",
        ]
    for kind in ("module", "population"):
        if kind not in summ:
            continue
        s = summ[kind]
        lines += [
            f"## {kind} predictions ({s['n_runs']} runs)",
            "",
            "| channel | RMSE median | RMSE max | coverage 50 | coverage 90 (± se) | coverage 95 | runs with 90 % coverage in 85-95 % |",
            "|---|---|---|---|---|---|---|",
        ]
        for ch in channels:
            c = s[ch]
            u = "mV" if ch == "voltage_V" else "K"
            f = 1e3 if ch == "voltage_V" else 1.0
            lines.append(
                f"| {ch} | {f * c['rmse_median']:.4g} {u} | {f * c['rmse_max']:.4g} {u} | "
                f"{100 * c['coverage50_mean']:.1f} % | {100 * c['coverage90_mean']:.1f} ± "
                f"{100 * (c['coverage90_se'] or 0):.1f} % | {100 * c['coverage95_mean']:.1f} % | "
                f"{100 * c['coverage90_runs_in_85_95']:.0f} % |"
            )
        lines.append("")
    if summ[tkey]:
        lines += [
            f"## {'T3' if rig is None else cold} RMSE by T-bar, linear vs constant (35 degC) laws",
            "",
            "| T-bar bin | linear | constant |",
            "|---|---|---|",
        ]
    for b in summ[tkey]:
        lines.append(
            f"| {b['Tavg_C_low']:.0f}-{b['Tavg_C_low'] + 5:.0f} degC | {b['linear']:.4f} K | {b['constant']:.3f} K |"
        )
    (RESULTS / f"{stem}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
