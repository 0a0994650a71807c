"""Benchmark: time to a converged posterior, against the naive approach, side by side.

- **tembayes**: ``calibrate_module`` on one module of the example batch, to
  convergence (50 autocorrelation times, R-hat <= 1.01, bulk ESS >= 1000 for
  every law parameter, the expansion checked by PSIS) with the default model
  (full form, robust discrepancy); target <= 60 s on 2 cores.  Then the
  whole example batch (3 modules and the population, ``calibrate_batch``
  with figures, modules in two worker processes as the CLI runs them) end to
  end; target <= 3 min.
- **naive**: emcee over a ``scipy.integrate.solve_ivp`` simulation of the
  whole identification run (75 000 samples) with the same rig model and the
  same priors, white noise at the measured level.  One log-likelihood costs
  one full BDF simulation; the benchmark times ``--naive-evals`` of them (in
  the same run) and extrapolates to the same bulk ESS: an ensemble of the same
  size needs ``ESS x tau / nwalkers`` steps after burn-in, each step
  ``nwalkers`` evaluations, spread over the 2 cores (perfect parallelism is
  granted to the naive sampler).  ``tau`` is taken from the tembayes run
  (same sampler, same parameters): running the naive sampler to convergence
  would take days, which is the point.

    python analyses/bench_calibrate.py
    python analyses/bench_calibrate.py --naive-evals 2 --module TEM1

Writes ``analyses/results/bench_calibrate.json``.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tembayes.calibrate import CalibrationOptions, calibrate_batch, calibrate_module  # noqa: E402
from tembayes.calibrate.likelihood import NOISE_PARAMETERS  # noqa: E402
from tembayes.calibrate.model import StepResponseModel  # noqa: E402
from tembayes.calibrate.module import calibration_rig, parameter_space  # noqa: E402
from tembayes.calibrate.stepdata import step_data  # noqa: E402
from tembayes.data import load_batch, write_json  # noqa: E402
from tembayes.physics.reference import simulate_reference  # noqa: E402
from tembayes.physics.simulate import Inputs  # noqa: E402
from tembayes.plots.calibrate import save_calibration_figures  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "analyses" / "results" / "bench_calibrate.json"
ESS_TARGET = 1000.0


def naive_loglike(exp, rig, params, noise):
    """The naive likelihood: solve_ivp(BDF) over the whole run, white noise on V, dT, Tmean."""
    sim = simulate_reference(Inputs.from_experiment(exp), params, rig=rig, method="BDF", rtol=1e-6, atol=1e-6)
    T2, T3 = sim.sensors[0, 1], sim.sensors[0, 2]
    pred = np.stack([sim.voltage[0], T2 - T3, 0.5 * (T2 + T3)])
    obs = np.stack([exp.voltage, exp.sensors[1] - exp.sensors[2], 0.5 * (exp.sensors[1] + exp.sensors[2])])
    r = (obs - pred) / noise[:, None]
    return -0.5 * float(np.sum(r * r))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batch", type=Path, default=ROOT / "data" / "example")
    ap.add_argument("--module", default="TEM2")
    ap.add_argument("--naive-evals", type=int, default=3, help="naive log-likelihood evaluations to time")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    batch = load_batch(args.batch)
    module = batch.modules[args.module]
    threads = os.cpu_count()

    # --- tembayes, one module (a warm-up first: numba's compiled cache) ---
    calibrate_module(
        module,
        batch.datasheet,
        rig_config=batch.rig_config,
        seed=1,
        options=CalibrationOptions(max_steps=1000, pilot=500),
    )
    t0 = time.perf_counter()
    r = calibrate_module(module, batch.datasheet, rig_config=batch.rig_config, seed=0)
    t_module = time.perf_counter() - t0
    d = r.diagnostics
    print(
        f"tembayes, {args.module}: {t_module:.1f} s to a converged posterior "
        f"(converged {d.converged}, {d.steps} steps, tau max {d.tau_max_steps:.0f}, "
        f"R-hat {d.rhat_max:.4f}, ESS {d.ess_bulk_min:.0f}, k_hat {d.psis_k:.2f}); "
        f"stages {', '.join(f'{k} {v:.1f}' for k, v in d.timings.items())}",
        flush=True,
    )

    # --- tembayes, the example batch end to end ---
    tmp = Path(tempfile.mkdtemp(prefix="tembayes-bench-"))
    try:
        t0 = time.perf_counter()
        # as `tembayes calibrate` runs it: modules in two worker processes
        summ = calibrate_batch(batch, tmp / "run", seed=0, workers=min(2, threads))
        save_calibration_figures(tmp / "run")
        t_batch = time.perf_counter() - t0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(f"tembayes, example batch end to end: {t_batch:.1f} s (converged {summ.converged})", flush=True)

    # --- naive: emcee over solve_ivp of the whole run ---
    opt = CalibrationOptions()
    rig = calibration_rig(batch.rig_config, opt)
    data = step_data(module.identification, face=rig.layout.face)
    _, space = parameter_space(rig, batch.datasheet, data, StepResponseModel(data, rig).shift_bound)
    params = {k: float(np.mean(v)) for k, v in r.draws.items() if k not in NOISE_PARAMETERS and k != "step_shift_s"}
    params.update(space.fixed)
    times = []
    for _ in range(args.naive_evals):
        t0 = time.perf_counter()
        ll = naive_loglike(module.identification, rig, params, data.noise)
        times.append(time.perf_counter() - t0)
        print(
            f"naive log-likelihood (solve_ivp BDF, {len(module.identification.time)} samples): "
            f"{times[-1]:.1f} s  (ll {ll:.0f})",
            flush=True,
        )
    t_eval = float(np.median(times))
    nw = d.nwalkers
    tau = d.tau_max_steps
    steps = ESS_TARGET * tau / nw / 0.8  # + the same 20 % burn-in
    t_naive = steps * nw * t_eval / threads
    # tembayes reached more than the target ESS; its time to the target is at most t_module
    ratio = t_naive / t_module
    print(
        f"\nnaive: {steps:.0f} steps x {nw} walkers x {t_eval:.1f} s / {threads} cores = {t_naive / 3600:.1f} h "
        f"to a bulk ESS of {ESS_TARGET:.0f} (tau {tau:.0f} steps)"
    )
    print(f"tembayes: {t_module:.1f} s to a bulk ESS of {d.ess_bulk_min:.0f} (target <= 60 s)")
    print(f"ratio of time to the same ESS (naive / tembayes): {ratio:,.0f}x")
    print(f"example batch end to end: {t_batch:.1f} s (target <= 180 s)")
    write_json(
        RESULTS,
        {
            "module": args.module,
            "cores": threads,
            "tembayes_module_seconds": t_module,
            "tembayes_stage_seconds": d.timings,
            "tembayes_steps": d.steps,
            "tembayes_tau_max_steps": tau,
            "tembayes_ess_bulk_min": d.ess_bulk_min,
            "tembayes_converged": d.converged,
            "nwalkers": nw,
            "example_batch_seconds": t_batch,
            "example_batch_converged": summ.converged,
            "naive_eval_seconds": times,
            "naive_steps_to_ess": steps,
            "naive_seconds_to_ess": t_naive,
            "ratio_time_to_same_ess": ratio,
            "targets": {"module_s": 60, "batch_s": 180},
        },
    )
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
