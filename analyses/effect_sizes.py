"""How large each catalogue effect is, at its bench default, in the measured data.

For one bench module (same seed, so identical noise and drifts) the
identification and validation runs are made once without effects and once per
effect at its default magnitude; the table gives the RMS and max difference
per temperature channel [mK] and on the voltage [mV].  Compare with the
sensor noise (4 mK) and the voltage noise (1 mV): every default is meant to be
visible but realistic.

Run:  python analyses/effect_sizes.py [--seed 0] [--rate 1]
Writes analyses/results/effect_sizes.json and prints a table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from tembayes.bench import BenchConfig, draw_truth, run_experiment
from tembayes.bench.protocols import identification_staircase, validation_cycle
from tembayes.data import write_json
from tembayes.physics.effects import CATALOGUE

RESULTS = Path(__file__).parent / "results"


def runs(module, effect_params, seed, rate):
    out = []
    for kind in ("identification", "validation"):
        rng = np.random.default_rng(seed)
        proto = (
            identification_staircase()
            if kind == "identification"
            else validation_cycle(np.random.default_rng(seed + 1))
        )
        out.append(run_experiment(proto, module, dict(effect_params), rng, rate=rate))
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rate", type=float, default=1.0)
    args = ap.parse_args(argv)
    module = draw_truth(BenchConfig(n_modules=1, seed=args.seed), np.random.default_rng(args.seed))["modules"]["TEM1"]
    base = runs(module, {}, args.seed, args.rate)
    table = {}
    print(
        f"{'effect':<20s}{'run':<16s}"
        + "".join(f"{c + ' rms/max':>18s}" for c in ("T1", "T2", "T3", "T4"))
        + f"{'V rms/max [mV]':>18s}{'I rms [mA]':>12s}"
    )
    for name, effect in CATALOGUE.items():
        with_fx = runs(module, effect.defaults(), args.seed, args.rate)
        table[name] = {}
        for b, e in zip(base, with_fx):
            kind = "identification" if len(table[name]) == 0 else "validation"
            dT = 1e3 * (e.sensors - b.sensors)
            dV = 1e3 * (e.voltage - b.voltage)
            dI = 1e3 * (e.current - b.current)
            row = {
                "rms_mK": np.sqrt((dT**2).mean(axis=1)).tolist(),
                "max_mK": np.abs(dT).max(axis=1).tolist(),
                "V_rms_mV": float(np.sqrt((dV**2).mean())),
                "V_max_mV": float(np.abs(dV).max()),
                "I_rms_mA": float(np.sqrt((dI**2).mean())),
            }
            table[name][kind] = row
            cells = "".join(f"{r:9.1f}/{m:<8.1f}" for r, m in zip(row["rms_mK"], row["max_mK"]))
            print(f"{name:<20s}{kind:<16s}{cells}{row['V_rms_mV']:9.2f}/{row['V_max_mV']:<8.2f}{row['I_rms_mA']:10.2f}")
    RESULTS.mkdir(exist_ok=True)
    write_json(
        RESULTS / "effect_sizes.json",
        {
            "seed": args.seed,
            "rate_Hz": args.rate,
            "defaults": {n: e.defaults() for n, e in CATALOGUE.items()},
            "table": table,
        },
    )
    print(f"wrote {RESULTS / 'effect_sizes.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
