"""Scale-out benchmark: a 200-module batch calibrated on 1 and on 2 Dask workers.

Usage::

    python analyses/scaleout_benchmark.py                   # 200 modules, ~30 min on 2 cores
    python analyses/scaleout_benchmark.py --modules 40      # a quick look

What it does, side by side in one run:

1. simulates a bench batch of ``--modules`` modules with a short staircase
   (60 s holds at 1 Hz: 24 steps, 24 min), once (kept in ``--work``);
2. calibrates it with ``tembayes.calibrate.calibrate_batch`` on a local Dask
   cluster of 1 worker, then of 2 workers (one thread each), with a cheap
   per-module budget (paper-sized rig model, 1000 sampler steps: ~5 s a
   module, so that both arms fit in half an hour; the modules end "not
   converged" by the 1000-ESS target and the population is fitted with
   ``keep_unconverged``).  The scale-out machinery (dispatch, transfer,
   writing, the batch stage) is what is measured; its overhead per module is
   the same at any budget, so a short module is the harder test of the
   parallel efficiency;
3. reports modules per hour, the parallel efficiency ``T1 / (2 T2)`` of the
   module stage, the peak memory of the client and of each worker (sampled
   every 0.2 s) and the client's memory as the batch progresses (bounded:
   flat in the number of modules done), the batch stage's time
   (population + ``posterior.nc`` + figures), and the agreement of the 2-worker run with the
   1-worker (serial) run: every number of ``summary.json`` and every array of
   ``posterior.nc``;
4. times ``--probe`` modules at the default (production) budget on one
   thread, for the extrapolation to 10^4 modules in docs/benchmarks.md.

Results: ``analyses/results/scaleout_benchmark.{json,md}``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parent / "results"
CHEAP = dict(max_steps=1000, pilot=500, max_relinearise=1, psis_draws=100, leg_cells=2, block_split=1)


class MemoryWatch:
    """Peak RSS of this process and of its child processes (the local workers), sampled."""

    def __init__(self, every=0.2):
        import psutil

        self.me = psutil.Process()
        self.every = every
        self.client_peak = 0
        self.worker_peak = 0
        self.total_peak = 0
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def sample(self):
        rss = self.me.memory_info().rss
        kids = []
        for c in self.me.children(recursive=True):
            try:
                if "resource_tracker" not in " ".join(c.cmdline()):
                    kids.append(c.memory_info().rss)
            except Exception:  # noqa: BLE001 -- a worker may exit between listing and reading
                pass
        self.client_peak = max(self.client_peak, rss)
        self.worker_peak = max([self.worker_peak] + kids)
        self.total_peak = max(self.total_peak, rss + sum(kids))
        return rss

    def _run(self):
        while not self._stop.is_set():
            self.sample()
            time.sleep(self.every)

    def __enter__(self):
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()


def simulate(path, n, seed):
    from tembayes.bench import BenchConfig, simulate_batch

    if (path / "batch.toml").exists() and len([p for p in path.iterdir() if p.is_dir()]) == n:
        return 0.0
    if path.exists():
        shutil.rmtree(path)
    t = time.perf_counter()
    simulate_batch(
        path, BenchConfig(n_modules=n, seed=seed, hold=60.0, rate=1.0, n_validations=0), progress=lambda m: None
    )
    return time.perf_counter() - t


def run_arm(batch_dir, out, workers, seed, log):
    from tembayes.calibrate import calibrate_batch
    from tembayes.calibrate.module import CalibrationOptions
    from tembayes.calibrate.scaleout import dask_client
    from tembayes.data import load_batch
    from tembayes.plots.calibrate import save_calibration_figures

    if out.exists():
        shutil.rmtree(out)
    batch = load_batch(batch_dir, lazy=True)
    n = len(batch.modules)
    marks = {}
    rss_trace = []
    done = [0]
    with MemoryWatch() as mem:
        t0 = time.perf_counter()
        with dask_client(workers) as client:
            t_up = time.perf_counter()

            def progress(msg):
                now = time.perf_counter()
                if " done (" in msg:
                    marks["last_module"] = now  # the module stage ends with the last module written
                    done[0] += 1
                    rss_trace.append((done[0], mem.sample()))
                    if done[0] % 20 == 0 or done[0] == n:
                        log(
                            f"  {workers} worker(s): {done[0]}/{n} modules, {now - t_up:.0f} s, "
                            f"client RSS {rss_trace[-1][1] / 2**20:.0f} MiB"
                        )
                if msg.startswith(("population", "posterior.nc")):  # the batch stage has read the modules
                    marks.setdefault("read", now)

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # "not converged": the cheap budget
                calibrate_batch(
                    batch,
                    out,
                    seed=seed,
                    options=CalibrationOptions(**CHEAP),
                    client=client,
                    keep_unconverged=True,
                    progress=progress,
                )
                save_calibration_figures(out)
            t_end = time.perf_counter()
    t_modules = marks["last_module"] - t_up
    trace = np.array(rss_trace, dtype=float)
    q = {
        f"{int(100 * f)}%": float(trace[min(len(trace) - 1, int(f * len(trace)) - 1), 1] / 2**20)
        for f in (0.25, 0.5, 0.75, 1.0)
    }
    slope = (
        float(np.polyfit(trace[len(trace) // 4 :, 0], trace[len(trace) // 4 :, 1], 1)[0]) if len(trace) > 8 else None
    )
    return {
        "workers": workers,
        "modules": n,
        "cluster_start_s": t_up - t0,
        "module_stage_s": t_modules,
        "batch_stage_s": t_end - marks["last_module"],
        "batch_stage_reading_modules_s": marks["read"] - marks["last_module"],
        "total_s": t_end - t0,
        "modules_per_hour": 3600.0 * n / t_modules,
        "peak_rss_client_MiB": mem.client_peak / 2**20,
        "peak_rss_worker_MiB": mem.worker_peak / 2**20,
        "peak_rss_total_MiB": mem.total_peak / 2**20,
        "client_rss_MiB_at_done": q,
        "client_rss_slope_kiB_per_module": None if slope is None else slope / 1024,
        "posterior_nc_MiB": (out / "posterior.nc").stat().st_size / 2**20,
        "module_seconds_mean": float(
            np.mean(
                [
                    m["diagnostics"]["seconds"]
                    for m in json.loads((out / "summary.json").read_text())["modules"].values()
                ]
            )
        ),
    }


def compare(a, b):
    """Largest differences between two runs: summary numbers and posterior.nc arrays."""
    import arviz as az

    sa, sb = (json.loads((Path(r) / "summary.json").read_text()) for r in (a, b))
    worst = {"summary_max_abs_diff": 0.0, "summary_numbers": 0, "posterior_arrays": 0, "posterior_max_abs_diff": 0.0}
    skip = {"seconds", "sampling_s", "elapsed_s", "command", "executor", "path"}

    def walk(x, y):
        if isinstance(x, dict):
            for k in x:
                if k not in skip:
                    walk(x[k], y.get(k) if isinstance(y, dict) else None)
        elif isinstance(x, list):
            for u, v in zip(x, y or []):
                walk(u, v)
        elif isinstance(x, (int, float)) and not isinstance(x, bool) and x is not None:
            worst["summary_numbers"] += 1
            d = abs(float(x) - float(y)) if y is not None else float("inf")
            if np.isfinite(d) or not (np.isnan(float(x)) and y is not None and np.isnan(float(y))):
                worst["summary_max_abs_diff"] = max(worst["summary_max_abs_diff"], 0.0 if x == y else d)

    walk(sa, sb)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ia = az.from_netcdf(Path(a) / "posterior.nc", engine="h5netcdf")
        ib = az.from_netcdf(Path(b) / "posterior.nc", engine="h5netcdf")
    for g in ia.groups():
        for k in getattr(ia, g).data_vars:
            u, v = getattr(ia, g)[k].values, getattr(ib, g)[k].values
            worst["posterior_arrays"] += 1
            same = np.array_equal(u, v, equal_nan=True)
            if not same:
                worst["posterior_max_abs_diff"] = max(worst["posterior_max_abs_diff"], float(np.nanmax(np.abs(u - v))))
    worst["identical"] = worst["summary_max_abs_diff"] == 0.0 and worst["posterior_max_abs_diff"] == 0.0
    pa, pb = sa["population"], sb["population"]
    worst["population_R0_mean"] = [pa["R0_ohm"]["mean"], pb["R0_ohm"]["mean"]]
    return worst


def probe_production(batch_dir, n, log):
    """Seconds per module at the default budget on one thread (for the extrapolation)."""
    import numba

    from tembayes.calibrate.module import calibrate_module
    from tembayes.data import load_batch

    numba.set_num_threads(1)
    b = load_batch(batch_dir)
    out = []
    for mid in list(b.modules)[:n]:
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            r = calibrate_module(b.modules[mid], b.datasheet, rig_config=b.rig_config, seed=0)
        out.append(
            {
                "module": mid,
                "seconds": time.perf_counter() - t,
                "steps": r.diagnostics["steps"],
                "converged": bool(r.diagnostics["converged"]),
            }
        )
        log(
            f"  production budget, 1 thread: {mid} {out[-1]['seconds']:.0f} s, {out[-1]['steps']} steps, "
            f"converged {out[-1]['converged']}"
        )
    return out


def population_scaling(sizes, seed, log):
    """The population stage alone on synthetic module posteriors of growing batches.

    Each module: 1000 draws from a Gaussian of the size a calibrated module's
    posterior has (0.1-1 % of the datasheet levels) around a member of a
    population with 2 % spreads.  Reports emcee steps, seconds, seconds per
    step and module, and the peak traced memory of the stage.
    """
    import tracemalloc

    from tembayes.calibrate.population import fit_population
    from tembayes.data import load_batch

    ds = load_batch(Path(__file__).resolve().parents[1] / "data" / "example").datasheet
    rng = np.random.default_rng(seed)
    level = np.array([ds.resistance(), 0.0, ds.seebeck(), 0.0, ds.conductance()])
    slope = np.array([0.0, 0.005 * ds.resistance(), 0.0, 0.002 * ds.seebeck(), 0.0])
    sd_rel = np.array([0.002, 0.0, 0.002, 0.0, 0.01])
    out = []
    for n in sizes:
        draws = {}
        for i in range(n):
            centre = level * (1 + 0.02 * rng.standard_normal(5)) + slope * (1 + 0.1 * rng.standard_normal(5))
            sd = np.where(sd_rel > 0, sd_rel * np.abs(centre), 0.05 * np.abs(slope) + 1e-12)
            draws[f"M{i:05d}"] = centre + sd * rng.standard_normal((1000, 5))
        tracemalloc.start()
        t = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            pop = fit_population(draws, ds, rng=np.random.default_rng(seed))
        dt = time.perf_counter() - t
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        d = pop.diagnostics
        steps = int(d.get("n_steps") or 0)
        out.append(
            {
                "modules": n,
                "seconds": dt,
                "steps": steps,
                "converged": bool(d.get("converged")),
                "method": d.get("method"),
                "us_per_step_and_module": 1e6 * d.get("sampling_s", dt) / max(1, steps) / n,
                "peak_traced_MiB": peak / 2**20,
            }
        )
        log(
            f"  population of {n} synthetic modules: {dt:.0f} s, {steps} steps, converged {out[-1]['converged']}, "
            f"{out[-1]['us_per_step_and_module']:.2f} us per step and module, peak {peak / 2**20:.0f} MiB"
        )
        del draws
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0],
        epilog="example: python analyses/scaleout_benchmark.py --modules 200 --work /tmp/scaleout",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--modules", type=int, default=200)
    ap.add_argument("--work", type=Path, default=Path("/tmp/tembayes_scaleout"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--probe", type=int, default=2, help="modules timed at the production budget (0: skip)")
    ap.add_argument(
        "--population-scaling",
        type=int,
        nargs="*",
        metavar="N",
        help="only time the population stage on synthetic batches of N modules (e.g. 200 1000 2000) "
        "and add it to the recorded results",
    )
    args = ap.parse_args(argv)
    if args.population_scaling:

        def say(msg):
            print(msg, flush=True)

        rows = population_scaling(args.population_scaling, args.seed, say)
        f = RESULTS / "scaleout_benchmark.json"
        doc = json.loads(f.read_text()) if f.exists() else {}
        doc["population_scaling"] = rows
        f.write_text(json.dumps(doc, indent=1) + "\n")
        md = RESULTS / "scaleout_benchmark.md"
        lines = [
            "",
            "Population stage alone (`--population-scaling`), synthetic module posteriors:",
            "",
            "| modules | seconds | emcee steps | converged | us per step and module | peak traced MiB |",
            "|---|---|---|---|---|---|",
        ]
        lines += [
            f"| {r['modules']} | {r['seconds']:.0f} | {r['steps']} | {r['converged']} | "
            f"{r['us_per_step_and_module']:.2f} | {r['peak_traced_MiB']:.0f} |"
            for r in rows
        ]
        with open(md, "a") as fh:
            fh.write("\n".join(lines) + "\n")
        return 0
    args.work.mkdir(parents=True, exist_ok=True)

    def log(msg):
        print(msg, flush=True)

    import os

    log(f"cores: {os.cpu_count()}; simulating {args.modules} bench modules (60 s holds, 1 Hz) ...")
    batch_dir = args.work / f"batch{args.modules}"
    t_sim = simulate(batch_dir, args.modules, args.seed)
    arms = {}
    for w in (1, 2):
        log(f"calibrating on {w} Dask worker(s) ...")
        arms[w] = run_arm(batch_dir, args.work / f"run_w{w}", w, args.seed, log)
        log(json.dumps(arms[w], indent=1))
    eff = arms[1]["module_stage_s"] / (2 * arms[2]["module_stage_s"])
    agree = compare(args.work / "run_w1", args.work / "run_w2")
    probe = probe_production(batch_dir, args.probe, log) if args.probe else []
    out = {
        "command": "python analyses/scaleout_benchmark.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "cores": os.cpu_count(),
        "modules": args.modules,
        "simulate_s": t_sim,
        "options": CHEAP,
        "arms": {str(k): v for k, v in arms.items()},
        "parallel_efficiency": eff,
        "speedup": arms[1]["module_stage_s"] / arms[2]["module_stage_s"],
        "agreement_2_vs_1_worker": agree,
        "production_probe": probe,
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "scaleout_benchmark.json").write_text(json.dumps(out, indent=1) + "\n")
    a1, a2 = arms[1], arms[2]
    md = [
        f"# Scale-out benchmark ({args.modules} modules, {os.cpu_count()} cores)",
        "",
        f"`{out['command']}`",
        "",
        "| | 1 worker | 2 workers |",
        "|---|---|---|",
        f"| module stage [s] | {a1['module_stage_s']:.0f} | {a2['module_stage_s']:.0f} |",
        f"| modules per hour | {a1['modules_per_hour']:.0f} | {a2['modules_per_hour']:.0f} |",
        f"| mean module calibration [s] | {a1['module_seconds_mean']:.1f} | {a2['module_seconds_mean']:.1f} |",
        f"| cluster start [s] | {a1['cluster_start_s']:.1f} | {a2['cluster_start_s']:.1f} |",
        f"| batch stage (population, posterior.nc, figures) [s] | {a1['batch_stage_s']:.0f} | {a2['batch_stage_s']:.0f} |",
        f"| peak RSS client / one worker / all [MiB] | {a1['peak_rss_client_MiB']:.0f} / {a1['peak_rss_worker_MiB']:.0f}"
        f" / {a1['peak_rss_total_MiB']:.0f} | {a2['peak_rss_client_MiB']:.0f} / {a2['peak_rss_worker_MiB']:.0f} / "
        f"{a2['peak_rss_total_MiB']:.0f} |",
        "| client RSS at 25/50/75/100 % of modules [MiB] | "
        + " / ".join(f"{v:.0f}" for v in a1["client_rss_MiB_at_done"].values())
        + " | "
        + " / ".join(f"{v:.0f}" for v in a2["client_rss_MiB_at_done"].values())
        + " |",
        "| client RSS growth after the first quarter [kiB per module] | "
        + " | ".join(
            "-" if a["client_rss_slope_kiB_per_module"] is None else f"{a['client_rss_slope_kiB_per_module']:.0f}"
            for a in (a1, a2)
        )
        + " |",
        f"| posterior.nc [MiB] | {a1['posterior_nc_MiB']:.0f} | {a2['posterior_nc_MiB']:.0f} |",
        "",
        f"**Parallel efficiency** T1 / (2 T2) = **{eff:.2f}** (speed-up {out['speedup']:.2f}x; target >= 0.80).",
        "",
        f"**Agreement, 2 workers vs 1 (serial):** {agree['summary_numbers']} numbers of summary.json, largest "
        f"difference {agree['summary_max_abs_diff']:.3g}; {agree['posterior_arrays']} arrays of posterior.nc, largest "
        f"difference {agree['posterior_max_abs_diff']:.3g}; identical: {agree['identical']}.",
        "",
    ]
    if probe:
        md.append(
            "Production budget (default options, 4 x 6 rig model, to convergence), one thread, this batch's "
            "modules: " + ", ".join(f"{p['module']} {p['seconds']:.0f} s ({p['steps']} steps)" for p in probe) + "."
        )
    (RESULTS / "scaleout_benchmark.md").write_text("\n".join(md) + "\n")
    log("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
