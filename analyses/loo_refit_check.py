"""How far a module's leave-one-out deviation by reweighting (PSIS) is from the exact one, against its Pareto k.

``deviation`` leaves a module out by reweighting the batch's hyper draws
(PSIS); above a Pareto k of 0.7 the population stage refits the other
modules instead.  This check fits each batch twice with the same seed: once
reweighting every module, once refitting every module (the exact leave-one-out
answer, up to Monte Carlo error), and compares their ``rel``, ``spreads`` and
``p_loo`` per module against the module's k.  It tells whether the threshold
is where the reweighting stops being good enough, and what the refit changes.

Synthetic batches of the outlier study's design (``population_checks.draw_batch``:
the bench's truths and spreads, Gaussian module posteriors): 3 and 8
modules, no outlier or one parameter of one module shifted by 6 unit
spreads.

Run:  python analyses/loo_refit_check.py [--batches 6]      (~30 min on 1 core)
      python analyses/loo_refit_check.py --summarise        (from the cached rows)
Writes analyses/results/loo_refit_check.{json,md} and loo_refit_check_rows.jsonl.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from population_checks import DS, draw_batch, read_jsonl  # noqa: E402

from tembayes.calibrate.population import deviation as deviation_module  # noqa: E402
from tembayes.calibrate.population import fit_population  # noqa: E402
from tembayes.constants import MODULE_PARAMETERS  # noqa: E402
from tembayes.data import write_json  # noqa: E402

RESULTS = Path(__file__).parent / "results"
ROWS = RESULTS / "loo_refit_check_rows.jsonl"
CELLS = ((3, 0), (3, 6), (8, 0), (8, 6))
QUANTITIES = ("rel", "spreads", "p_loo")


def _fit(batch, seed, refit_above):
    """The batch's population fit with modules refitted above Pareto k ``refit_above``."""
    saved = deviation_module.K_HAT_MAX
    deviation_module.K_HAT_MAX = refit_above
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return fit_population(batch["draws"], DS, rng=np.random.default_rng(seed), design_reach=False)
    finally:
        deviation_module.K_HAT_MAX = saved


def batch_rows(seed, n, shift):
    """One row per module: its k, and its deviation by reweighting and by refitting."""
    batch = draw_batch(np.random.default_rng(seed), n, "spreads" if shift else "none", spreads=shift)
    psis, exact = _fit(batch, seed, np.inf), _fit(batch, seed, -np.inf)
    out = []
    for i, mid in enumerate(batch["ids"]):
        out.append(
            {
                "seed": seed,
                "n": n,
                "shift": shift,
                "outlier": i == batch["outlier"],
                "k_hat": psis.diagnostics["deviation_k_hat"][mid],
                "psis": {q: [psis.deviation[mid][p][q] for p in MODULE_PARAMETERS] for q in QUANTITIES},
                "exact": {q: [exact.deviation[mid][p][q] for p in MODULE_PARAMETERS] for q in QUANTITIES},
            }
        )
    return out


#: Levels (R0, S0, K) and slopes (R1, S1): slopes' ``rel`` is relative to a centre near zero.
GROUPS = {"levels": [0, 2, 4], "slopes": [1, 3]}


def _differences(rows):
    """Per quantity and group: the median, 90th percentile and largest |PSIS - exact| over modules and parameters."""
    out = {"modules": len(rows)}
    for q in QUANTITIES:
        for g, idx in GROUPS.items():
            d = np.abs(np.array([r["psis"][q] for r in rows])[:, idx] - np.array([r["exact"][q] for r in rows])[:, idx])
            d = d.ravel() * (100.0 if q == "rel" else 1.0)  # rel in percent points
            out[f"{q}_{g}"] = {"median": float(np.median(d)), "p90": float(np.quantile(d, 0.9)), "max": float(d.max())}
    return out


def summarise(rows):
    res = {"k_hat_max": deviation_module.K_HAT_MAX, "cells": {}}
    for n in sorted({r["n"] for r in rows}):
        for label, sel in (
            ("k <= 0.7", lambda r: r["k_hat"] <= deviation_module.K_HAT_MAX),
            ("k > 0.7", lambda r: r["k_hat"] > deviation_module.K_HAT_MAX),
        ):
            part = [r for r in rows if r["n"] == n and sel(r)]
            if part:
                res["cells"][f"{n} modules, {label}"] = _differences(part)
    write_json(RESULTS / "loo_refit_check.json", res)
    cols = [f"{q}_{g}" for q in QUANTITIES for g in GROUPS]
    lines = [
        "# Leave-one-out deviation: reweighting (PSIS) against refitting\n",
        "|PSIS - exact|, median / 90th percentile / largest; rel in % points.\n",
        "| batch, modules | modules | " + " | ".join(cols) + " |",
        "|---|---|" + "---|" * len(cols),
    ]
    for c, v in res["cells"].items():
        cells = " | ".join(f"{v[k]['median']:.2g} / {v[k]['p90']:.2g} / {v[k]['max']:.2g}" for k in cols)
        lines.append(f"| {c} | {v['modules']} | {cells} |")
    text = "\n".join(lines) + "\n"
    (RESULTS / "loo_refit_check.md").write_text(text)
    print(text)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", type=int, default=6, help="batches per size and shift (default 6)")
    ap.add_argument("--seed", type=int, default=2811)
    ap.add_argument("--summarise", action="store_true")
    args = ap.parse_args(argv)
    if not args.summarise:
        done = {(r["seed"], r["n"], r["shift"]) for r in read_jsonl(ROWS)} if ROWS.exists() else set()
        seeds = np.random.SeedSequence(args.seed).generate_state(args.batches * len(CELLS))
        for k, (seed, (n, shift)) in enumerate(zip(seeds, CELLS * args.batches)):
            if (int(seed), n, shift) in done:
                continue
            with open(ROWS, "a") as f:
                for row in batch_rows(int(seed), n, shift):
                    f.write(json.dumps(row) + "\n")
            print(f"  {k + 1}/{len(seeds)}: {n} modules, shift {shift}", flush=True)
    summarise(read_jsonl(ROWS))


if __name__ == "__main__":
    main()
