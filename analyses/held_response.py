"""How far the laws move across a held rig value's range: first order, mode refits, full calibrations.

``--discrepancy robust`` carries the documented range of each rig value the
calibration holds fixed (the sensors' depths, the ceramic's conductance) over
to the laws to first order (:func:`tembayes.calibrate.discrepancy.held_nuisance_spread`).
This study checks that first-order response on bench modules against

- the posterior mode refitted with the value at each end of its range
  (:func:`tembayes.calibrate.module.fit_map`), and
- the whole calibration repeated at each end (posterior means);
- with ``--realised``, on a batch made by ``tembayes simulate``: the *bench*
  made again with the module's true value at each end of the range (the
  same seed, everything else the same) and calibrated at the nominal value.
  The first three say how the calibration model responds to the value; this
  one, how the laws a user gets respond to the rig's.

All as the laws' change from the range's low end to its high end, in
posterior sds of the nominal calibration (before the carried-over spread).
The first three move the *model's* value with the data fixed; ``realised``
moves the *rig's* value with the model at nominal, which acts on the
residuals the other way round: where the carry-over is faithful,
``realised`` = -``first_order``.

    python analyses/held_response.py BATCH --modules TEM1 TEM2 --held depth_T2 depth_T3 g_ceramic
    python analyses/held_response.py BATCH --held depth_T3 --realised --skip-refits

Writes analyses/results/held_response.json (one row per module and held value).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

import tembayes.calibrate.module as cm
from tembayes.bench import BenchConfig, bench, outside, simulate_batch
from tembayes.bench.hifi import SENSOR_DEPTH
from tembayes.calibrate.discrepancy import held_nuisance_spread
from tembayes.constants import MODULE_PARAMETERS
from tembayes.data import load_batch

ROOT = Path(__file__).resolve().parent.parent


def nominal_calibration(module, batch):
    """The nominal calibration's law means, core sds and first-order response per unit log of each held value."""
    seen = {}
    posterior = cm._posterior

    def keep(prob, st, levels):  # the draws before the discrepancy model widens them
        seen.update(prob=prob, st=st)
        return posterior(prob, st, levels)

    cm._posterior = keep
    try:
        cal = cm.calibrate_module(module, batch.datasheet, rig_config=batch.rig_config, seed=0)
    finally:
        cm._posterior = posterior
    prob, st = seen["prob"], seen["st"]
    space, p = prob.space, prob.model_space.ndim
    flat = st.run.chain[cm.even_indices(st.run.chain.shape[0], prob.options.keep)].reshape(-1, space.ndim)
    held = {q: prob.rig.parameter(q) for q in prob.model_space.fixed if q in prob.rig.parameter_names}
    held = {q: par for q, par in held.items() if par.high > par.low}
    centre = flat[:, :p].mean(axis=0)
    spread = held_nuisance_spread(prob.model, prob.model_space, centre, st.lin.J, prob.data.noise, held)

    def law_values(x):  # sampled coordinates -> the laws in SI units
        v = prob.model_space.values(np.atleast_2d(x))
        return np.array([float(v[k][0]) for k in MODULE_PARAMETERS])

    first = {}  # the first-order change across the whole range [SI]
    for i, q in enumerate(spread.names):
        half = 0.5 * float(np.log(held[q].high / held[q].low)) * spread.shift[:, i]
        first[q] = law_values(centre + half) - law_values(centre - half)
    draws = space.values(flat)
    sd = np.array([float(np.std(draws[k])) for k in MODULE_PARAMETERS])
    means = {k: float(np.mean(cal.draws[k])) for k in MODULE_PARAMETERS}
    return prob, means, sd, first


def mode_refits(prob, q):
    """The laws' mode at the low and the high end of ``q``'s range."""
    ms = prob.model_space
    x_map, _, _ = cm.fit_map(prob.model, ms, prob.data, cm.start_point(ms, {}))
    par = prob.rig.parameter(q)
    out = []
    for v in (par.low, par.high):
        msq = dataclasses.replace(ms, fixed={**ms.fixed, q: v})
        xe, _, _ = cm.fit_map(prob.model, msq, prob.data, x_map)
        vals = msq.values(xe[None])
        out.append(np.array([float(vals[k][0]) for k in MODULE_PARAMETERS]))
    return out[1] - out[0]


def end_calibrations(module, batch, q, par):
    """The laws' posterior means calibrated at the low and the high end of ``q``'s range."""
    out = []
    for v in (par.low, par.high):
        cfg = {**(batch.rig_config or {}), q: v}
        cal = cm.calibrate_module(module, batch.datasheet, rig_config=cfg, seed=0)
        out.append(np.array([float(np.mean(cal.draws[k])) for k in MODULE_PARAMETERS]))
    return out[1] - out[0]


#: The out-of-model bench's neighbour cell that lies deeper below a sensor's
#: nearer face (outside.outside_rig counts the cells from the cooler: T1 and T3
#: sit near a block's first cell, T2 and T4 near its last).
DEEPER_SIDE = {"T1": 1, "T2": -1, "T3": 1, "T4": -1}


def _bench_at(truth, datasheet, q, value, out):
    """The batch of ``truth`` (its datasheet ``datasheet``) made again with every module's true ``q`` at ``value``."""
    gen = truth["generator"]
    config = BenchConfig(
        n_modules=len(truth["modules"]),
        seed=gen["seed"],
        datasheet=datasheet,
        rate=gen["rate_Hz"],
        hold=gen["hold_s"],
        n_validations=0,
        fidelity=gen["fidelity"],
        physics="full" if gen["fidelity"] == "high" else gen["physics"],
    )
    draw_truth, draw_depths = bench.draw_truth, outside.draw_sensor_depths
    s = q.removeprefix("depth_")

    def depths(rng):  # the same draws, then this sensor's offset set
        sides, shares = draw_depths(rng)
        d = value - SENSOR_DEPTH
        f = max(abs(d) / outside._DX, 1e-9)
        sides[s] = DEEPER_SIDE[s] if d >= 0 else -DEEPER_SIDE[s]
        shares[f"w_{s}"], shares[f"v_{s}"] = 1.0 - f, f
        return sides, shares

    def truth_at(cfg, rng):
        t = draw_truth(cfg, rng)
        for m in t["modules"].values():
            if q in m["rig_bench"]:
                m["rig_bench"][q] = value
        return t

    bench.draw_truth = truth_at
    if q.startswith("depth_") and gen["fidelity"] == "high":
        outside.draw_sensor_depths = depths
    try:
        simulate_batch(out, config, overwrite=True, progress=lambda msg: None)
    finally:
        bench.draw_truth, outside.draw_sensor_depths = draw_truth, draw_depths
    return load_batch(out)


def realised(batch, mid, q, par, work):
    """The laws' posterior means (nominal calibration) on the bench made with ``q`` at each end of its range."""
    truth = json.loads((Path(batch.path) / "truth.json").read_text())
    out = []
    for v in (par.low, par.high):
        b = _bench_at(truth, batch.datasheet, q, v, Path(work) / f"{Path(batch.path).name}-{q}-{v:.6g}")
        cal = cm.calibrate_module(b.modules[mid], b.datasheet, rig_config=b.rig_config, seed=0)
        out.append(np.array([float(np.mean(cal.draws[k])) for k in MODULE_PARAMETERS]))
    return out[1] - out[0]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("batch", type=Path)
    ap.add_argument("--modules", nargs="+", default=["TEM1"])
    ap.add_argument("--held", nargs="+", default=["depth_T2", "depth_T3", "g_ceramic"])
    ap.add_argument("--out", type=Path, default=ROOT / "analyses" / "results" / "held_response.json")
    ap.add_argument("--realised", action="store_true", help="also the bench made again at the range ends")
    ap.add_argument("--skip-refits", action="store_true", help="no mode refits or calibrations at the range ends")
    ap.add_argument("--work", type=Path, default=Path("held-response-work"), help="the --realised batches")
    args = ap.parse_args()
    batch = load_batch(args.batch)
    rows = json.loads(args.out.read_text()) if args.out.exists() else []
    for mid in args.modules:
        t0 = time.perf_counter()
        prob, means, sd, first = nominal_calibration(batch.modules[mid], batch)
        for q in args.held:
            par = prob.rig.parameter(q)
            row = {
                "batch": str(args.batch),
                "module": mid,
                "held": q,
                "core_sd": dict(zip(MODULE_PARAMETERS, sd.tolist())),
                "first_order": dict(zip(MODULE_PARAMETERS, (first[q] / sd).tolist())),
            }
            if not args.skip_refits:
                row["mode_refit"] = dict(zip(MODULE_PARAMETERS, (mode_refits(prob, q) / sd).tolist()))
                row["calibration"] = dict(
                    zip(MODULE_PARAMETERS, (end_calibrations(batch.modules[mid], batch, q, par) / sd).tolist())
                )
            if args.realised:
                row["realised"] = dict(zip(MODULE_PARAMETERS, (realised(batch, mid, q, par, args.work) / sd).tolist()))
            rows = [r for r in rows if (r["batch"], r["module"], r["held"]) != (row["batch"], mid, q)] + [row]
            print(
                f"{mid} {q}: low->high in core sds\n"
                + "\n".join(
                    f"  {k:14s} "
                    + "  ".join(
                        f"{c.replace('_', ' ')} {row[c][k]:+7.2f}"
                        for c in ("first_order", "mode_refit", "calibration", "realised")
                        if c in row
                    )
                    for k in MODULE_PARAMETERS
                ),
                flush=True,
            )
            args.out.write_text(json.dumps(rows, indent=1) + "\n")
        print(f"{mid}: {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
