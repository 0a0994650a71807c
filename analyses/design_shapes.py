"""What the staircase's span and the order of its levels do to the predicted widths.

``tembayes design``'s predictor (the standard bench's drawn modules, the same
noise streams for every program) on the example type: the spans of currents
at one hold (``--spans``, turning levels for the reference module [A]) with
the temperatures each reaches, and the reference staircase run up first
(0 -> +0.8 -> -1.6 -> 0 A) against down first (0 -> -1.6 -> +0.8 -> 0 A) at
several holds.  Spans offered by the search are in ``TURNS_A``; this script
also shows the ones withdrawn.

    python analyses/design_shapes.py                         (~2 min on 2 cores)

Writes analyses/results/design_shapes.{json,md}.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from tembayes.bench import TEC1_12706
from tembayes.bench.protocols import REFERENCE_IMAX, REFERENCE_TURNS_A, Protocol
from tembayes.constants import KELVIN, MODULE_PARAMETERS, RATE_HZ
from tembayes.data.write import write_json
from tembayes.design.search import Designer

RESULTS = Path(__file__).resolve().parent / "results"
SPANS = ((0.6, -1.2), REFERENCE_TURNS_A, (0.8, -1.8), (1.0, -2.0))


def down_first(imax, hold, step=0.2, top=REFERENCE_TURNS_A[0], bottom=REFERENCE_TURNS_A[1]):
    """The reference staircase with its legs reversed: 0 down to ``bottom``, up to ``top``, back to 0."""
    down = np.arange(0.0, bottom - 1e-9, -step)
    up = np.arange(bottom + step, top + 1e-9, step)
    back = np.arange(top - step, -1e-9, -step)
    levels = np.round(np.concatenate([down, up, back]), 6) * imax / REFERENCE_IMAX
    return Protocol(levels, np.full(len(levels), float(hold)))


class DownFirst(Designer):
    """The design's predictor on the down-first staircases (the same drawn modules and noise streams)."""

    def protocol(self, step, hold, top=REFERENCE_TURNS_A[0], bottom=REFERENCE_TURNS_A[1]):
        return down_first(self.datasheet.imax, hold, step, top, bottom)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--draws", type=int, default=2)
    ap.add_argument("--span-hold", type=float, default=100.0, help="the hold of the spans' table [s]")
    ap.add_argument("--order-holds", type=float, nargs="+", default=[120.0, 240.0, 600.0])
    args = ap.parse_args(argv)
    up, down = (cls(TEC1_12706, None, seed=0, n_draws=args.draws, jobs=1) for cls in (Designer, DownFirst))
    res = {"draws": args.draws, "spans": [], "order": []}
    for e in up.evaluate([(0.2, args.span_hold, RATE_HZ, *t) for t in SPANS]):
        res["spans"].append({"turns_A": [e.top_A, e.bottom_A], "hold_s": e.hold_s, "levels": len(e.protocol.levels),
                             "hours": e.duration_s / 3600, "sd_rel": e.sd_rel(),
                             "sensor_range_C": [t - KELVIN for t in e.sensor_range_K]})  # fmt: skip
        print(res["spans"][-1], flush=True)
    holds = [(0.2, h) for h in args.order_holds]
    for u, d in zip(up.evaluate(holds), down.evaluate(holds)):
        res["order"].append({"hold_s": u.hold_s, "up_first": u.sd_rel(), "down_first": d.sd_rel()})
        print(res["order"][-1], flush=True)
    write_json(RESULTS / "design_shapes.json", res)
    (RESULTS / "design_shapes.md").write_text(markdown(res))


def markdown(res):
    lines = [
        "# Staircase shapes: predicted widths (example type, reference rig)",
        "",
        f"`python analyses/design_shapes.py` ({res['draws']} drawn modules, the design's predictor).",
        "",
        "| turning levels [A] | hold [s] | levels | hours | R0 / S0 / K sd [%] | R1 / S1 sd [%] | sensors [°C] |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in res["spans"]:
        s = {k: 100 * v for k, v in r["sd_rel"].items()}
        lines.append(
            f"| {r['turns_A'][0]:+g} / {r['turns_A'][1]:+g} | {r['hold_s']:g} | {r['levels']} | {r['hours']:.2f} "
            f"| {s['R0_ohm']:.3f} / {s['S0_V_per_K']:.3f} / {s['K_W_per_K']:.3f} "
            f"| {s['R1_ohm_per_K']:.2f} / {s['S1_V_per_K2']:.2f} "
            f"| {r['sensor_range_C'][0]:.1f}–{r['sensor_range_C'][1]:.1f} |"
        )
    lines += ["", "| hold [s] | law | up first sd [%] | down first sd [%] | down / up |", "|---|---|---|---|---|"]
    for r in res["order"]:
        for k in MODULE_PARAMETERS:
            u, dn = 100 * r["up_first"][k], 100 * r["down_first"][k]
            lines.append(f"| {r['hold_s']:g} | {k} | {u:.3f} | {dn:.3f} | {dn / u:.3f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
