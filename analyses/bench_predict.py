"""Benchmark: 500 posterior-predictive draws of a 4-hour validation run, against the naive way.

- **tembayes**: :func:`tembayes.predict.simulate_predictive` -- 500 draws of
  the example module TEM2 (anchored rig, own step phase each) simulated
  through the example's 4-hour validation run with
  :class:`~tembayes.predict.runmodel.RunModel` (the integrator lands on a
  grid: every sample in the first 20 s after a step, every 5 s elsewhere;
  splines per hold fill in every sample), noise added, bands formed.
  Target: <= 20 s on 2 cores.  The whole ``predict`` (anchoring on the
  identification run included) is timed too.
- **naive**: the same 500 draws through ``tembayes.physics.simulate``
  landing on every sample (the package's own compiled integrator, so the
  ratio measures the grid, not compiled vs Python code), plus the same noise
  and bands.

Both run in this process, one after the other, on the same draws; the
agreement of the two predictive means is printed too.

    python analyses/bench_predict.py
    python analyses/bench_predict.py --draws 1000

Writes ``analyses/results/bench_predict.json``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tembayes.calibrate.run import load_run  # noqa: E402
from tembayes.data import load_batch, write_json  # noqa: E402
from tembayes.physics import Inputs, simulate  # noqa: E402
from tembayes.physics.rigread import rig_from_config  # noqa: E402
from tembayes.predict.predictive import module_draws, predict, simulate_predictive, subsample  # noqa: E402
from tembayes.predict.runmodel import RunModel  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "bench_predict.json"
TARGET_S = 20.0


def naive(exp, draws, rig, rng):
    """Every sample simulated by ``physics.simulate`` (measured inputs), the same noise and bands."""
    t0 = time.perf_counter()
    M = draws.n
    Y = np.empty((M, 5, len(exp.time)))
    inputs = Inputs.from_experiment(exp)
    for a in range(0, M, 100):
        b = min(a + 100, M)
        sim = simulate(inputs, {k: np.asarray(v)[a:b] for k, v in draws.params.items()}, rig=rig, atol=1e-4)
        Y[a:b, :4] = sim.sensors
        Y[a:b, 4] = sim.voltage
    mean = Y.mean(axis=0)
    Y += rng.standard_normal(Y.shape) * draws.noise_sd[:, :, None]
    np.quantile(Y, [0.025, 0.05, 0.25, 0.5, 0.75, 0.95, 0.975], axis=0)
    return time.perf_counter() - t0, mean


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--run",
        type=Path,
        default=Path("runs/example"),
        help="a calibration run of data/example (made by the README's main job)",
    )
    ap.add_argument("--batch", type=Path, default=Path("data/example"))
    ap.add_argument("--module", default="TEM2")
    ap.add_argument("--draws", type=int, default=500)
    args = ap.parse_args(argv)
    run, batch = load_run(args.run), load_batch(args.batch)
    exp = batch.modules[args.module].validations[0]
    rig = rig_from_config(None, 4, 3)
    d = module_draws(run, args.module, batch.modules[args.module].identification, rig)
    draws = subsample(d, np.random.default_rng(0), args.draws)
    model = RunModel(exp, rig)
    simulate_predictive(model, subsample(d, np.random.default_rng(1), 4), np.random.default_rng(1))  # warm up
    t0 = time.perf_counter()
    pred = simulate_predictive(model, draws, np.random.default_rng(2))
    t_tem = time.perf_counter() - t0
    print(
        f"tembayes: {args.draws} draws of {exp.path} ({len(exp.time)} samples, "
        f"{(exp.time[-1] - exp.time[0]) / 3600:.2f} h): {t_tem:.2f} s (target <= {TARGET_S:.0f} s)",
        flush=True,
    )
    t_naive, mean_naive = naive(exp, draws, rig, np.random.default_rng(2))
    print(f"naive (every sample, physics.simulate): {t_naive:.2f} s", flush=True)
    diff = np.abs(pred.mean - mean_naive)
    t0 = time.perf_counter()
    predict(run, exp, args.module, batch, n_draws=args.draws, seed=0, compare_constant=False)
    t_predict = time.perf_counter() - t0
    doc = {
        "command": "python analyses/bench_predict.py " + " ".join(argv or sys.argv[1:]),
        "cores": os.cpu_count(),
        "draws": args.draws,
        "samples": len(exp.time),
        "grid_points": model.n_grid,
        "tembayes_s": t_tem,
        "naive_s": t_naive,
        "ratio": t_naive / t_tem,
        "target_s": TARGET_S,
        "meets_target": t_tem <= TARGET_S,
        "predict_total_s": t_predict,
        # the naive run takes the *measured* (noisy) current and steps mid-interval; the difference is
        # dominated by that, not by the grid (see tests/test_predict.py for the grid's own error)
        "mean_abs_diff_sensors_K": float(diff[:4].max()),
        "mean_abs_diff_voltage_V": float(diff[4].max()),
        "mean_rms_diff_sensors_K": float(np.sqrt(np.mean(diff[:4] ** 2))),
    }
    print(
        f"ratio naive / tembayes: {doc['ratio']:.1f}x; whole predict (anchoring + {args.draws} draws): "
        f"{t_predict:.1f} s; predictive means differ by rms {1e3 * doc['mean_rms_diff_sensors_K']:.2f} mK"
    )
    write_json(RESULTS, doc)


if __name__ == "__main__":
    main()
