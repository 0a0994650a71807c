"""Benchmark: the batched simulator against scipy's solve_ivp(BDF), side by side.

One identification run from the virtual bench (staircase, ~4.2 h at 5 Hz,
jittered sampling, noisy measured current, drifting water and ambient) is
simulated for 64 parameter sets (module laws, K and the rig's thermal
parameters drawn around their nominal values):

- tembayes: ``tembayes.physics.simulate`` (all 64 in one call, 2 threads);
- baseline: ``scipy.integrate.solve_ivp(method="BDF")`` looped over the 64
  sets, with the *same compiled* right-hand side and its analytic Jacobian,
  at the loosest tolerance that still meets the accuracy target (so the
  ratio compares integrators, not Python against compiled code);
- agreement: both against a tight-tolerance solve_ivp reference (rtol = atol
  = 1e-9) for a few sets over the whole run: max |error| per sensor [K] and
  on the voltage [V].  Targets: <= 0.01 K and <= 1 mV; speed ratio >= 50.

Run:  python analyses/bench_simulator.py            (about 6 min on 2 cores)
      python analyses/bench_simulator.py --quick    (8 sets, ~1 min; ratio is per set)
Writes analyses/results/bench_simulator.json and prints a table.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numba
import numpy as np

import tembayes
from tembayes.bench import BenchConfig, draw_truth, run_experiment
from tembayes.bench.protocols import identification_staircase
from tembayes.data import write_json
from tembayes.physics import Inputs, simulate
from tembayes.physics.reference import simulate_reference
from tembayes.physics.rigread import REFERENCE

RESULTS = Path(__file__).parent / "results"


def parameter_sets(n, rng):
    """``n`` parameter sets: module laws from the TEC1-12706 scale, rig within its documented range."""
    base = {"R0_ohm": 1.75, "R1_ohm_per_K": 0.0087, "S0_V_per_K": 0.048, "S1_V_per_K2": 1.0e-4, "K_W_per_K": 0.54}
    out = {k: v * rng.normal(1.0, 0.05, n) for k, v in base.items()}
    for p in REFERENCE.parameters:
        out[p.name] = rng.uniform(p.low, p.high, n)
    return out


def take(params, idx):
    return {k: v[idx] for k, v in params.items()}


def errors(a, b):
    return np.abs(a.sensors - b.sensors).max(axis=(0, 2)), float(np.abs(a.voltage - b.voltage).max())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sets", type=int, default=64, help="parameter sets (default 64)")
    ap.add_argument("--agreement-sets", type=int, default=2, help="sets checked against the tight reference")
    ap.add_argument("--bdf-rtol", type=float, default=1e-6, help="baseline BDF rtol (atol = rtol K)")
    ap.add_argument("--quick", action="store_true", help="8 sets, 1 agreement set")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if args.quick:
        args.sets, args.agreement_sets = 8, 1

    rng = np.random.default_rng(args.seed)
    cfg = BenchConfig(n_modules=1, seed=args.seed)
    module = draw_truth(cfg, rng)["modules"]["TEM1"]
    exp = run_experiment(identification_staircase(), module, {}, rng, rate=5.0)
    inputs = Inputs.from_experiment(exp)
    params = parameter_sets(args.sets, rng)
    print(f"identification run: {exp.n} samples, {exp.duration / 3600:.2f} h; {args.sets} parameter sets", flush=True)

    t0 = time.perf_counter()
    simulate(inputs.slice(0, 50), take(params, [0]))  # compile (or load numba's cache)
    t_compile = time.perf_counter() - t0

    t0 = time.perf_counter()
    fast = simulate(inputs, params)
    t_fast = time.perf_counter() - t0
    print(
        f"tembayes: {t_fast:.2f} s for {args.sets} sets (first-call compile/cache load {t_compile:.1f} s)", flush=True
    )
    # the same on one thread, so the ratio per core is on record too
    threads = numba.get_num_threads()
    numba.set_num_threads(1)
    t0 = time.perf_counter()
    simulate(inputs, params)
    t_fast1 = time.perf_counter() - t0
    numba.set_num_threads(threads)
    print(f"tembayes on 1 thread: {t_fast1:.2f} s", flush=True)

    t0 = time.perf_counter()
    base = simulate_reference(inputs, params, method="BDF", rtol=args.bdf_rtol, atol=args.bdf_rtol)
    t_base = time.perf_counter() - t0
    print(f"solve_ivp BDF (rtol=atol={args.bdf_rtol:g}, compiled rhs + jac) looped: {t_base:.1f} s", flush=True)

    idx = list(range(args.agreement_sets))
    t0 = time.perf_counter()
    tight = simulate_reference(inputs, take(params, idx), method="BDF", rtol=1e-9, atol=1e-9)
    t_tight = time.perf_counter() - t0
    f_sub = Simulation_take(fast, idx)
    b_sub = Simulation_take(base, idx)
    err_fast_T, err_fast_V = errors(f_sub, tight)
    err_base_T, err_base_V = errors(b_sub, tight)
    ratio = t_base / t_fast

    result = {
        "tembayes_version": tembayes.__version__,
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "samples": int(exp.n),
        "duration_h": exp.duration / 3600,
        "sets": args.sets,
        "tembayes_s": t_fast,
        "tembayes_threads": threads,
        "tembayes_1thread_s": t_fast1,
        "speed_ratio_per_thread": t_base / t_fast1,
        "tembayes_compile_s": t_compile,
        "bdf_s": t_base,
        "bdf_rtol": args.bdf_rtol,
        "speed_ratio": ratio,
        "agreement_sets": args.agreement_sets,
        "tight_reference_s": t_tight,
        "max_err_K": {ch: float(e) for ch, e in zip(fast.channels, err_fast_T)},
        "max_err_V": err_fast_V,
        "bdf_max_err_K": {ch: float(e) for ch, e in zip(fast.channels, err_base_T)},
        "bdf_max_err_V": err_base_V,
        "targets": {"speed_ratio": 50, "max_err_K": 0.01, "max_err_V": 0.001},
        "pass": bool(ratio >= 50 and err_fast_T.max() <= 0.01 and err_fast_V <= 0.001),
        "command": " ".join(["python", "analyses/bench_simulator.py", *(argv if argv is not None else sys.argv[1:])]),
    }
    print()
    print(f"{'':28s}{'tembayes':>12s}{'BDF baseline':>14s}")
    print(f"{'wall time [s]':28s}{t_fast:12.2f}{t_base:14.1f}")
    for ch, a, b in zip(fast.channels, err_fast_T, err_base_T):
        print(f"{'max |err| ' + ch + ' [K]':28s}{a:12.2e}{b:14.2e}")
    print(f"{'max |err| voltage [V]':28s}{err_fast_V:12.2e}{err_base_V:14.2e}")
    print(f"{'wall time, 1 thread [s]':28s}{t_fast1:12.2f}{t_base:14.1f}")
    print(
        f"\nspeed ratio (BDF / tembayes, {threads} threads): {ratio:.1f}x   (target >= 50x); "
        f"on 1 thread: {t_base / t_fast1:.1f}x"
    )
    print(f"agreement with tight reference: {err_fast_T.max():.2e} K, {err_fast_V:.2e} V (targets 0.01 K, 1 mV)")
    print("PASS" if result["pass"] else "FAIL")
    if not args.quick:
        RESULTS.mkdir(exist_ok=True)
        write_json(RESULTS / "bench_simulator.json", result)
        print(f"wrote {RESULTS / 'bench_simulator.json'}")
    return 0 if result["pass"] else 1


def Simulation_take(sim, idx):
    """The draws ``idx`` of a Simulation."""
    return type(sim)(
        sim.time, sim.channels, sim.sensors[idx], sim.voltage[idx], sim.t_hot[idx], sim.t_cold[idx], sim.steps[idx]
    )


if __name__ == "__main__":
    sys.exit(main())
