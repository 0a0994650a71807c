"""Do plate-capacity alarms follow the face sensors' contacts?  reference-faces, out-of-model null batches.

On the out-of-model bench every sensor is a body of its own in contact with
the block cell it sits in and, by a share ``v_<column>`` of that contact, with
the next cell deeper in (``tembayes.bench.anyrig``).  Two sensors with
different shares then differ in their step response (a body's time constant is
``c_sensor / (g_sensor (1 + v))``) and in the depth they read.  For every null
batch of a ``gap_benchmark.py`` work folder this prints what ``tembayes gap``
said, each plate's calibrated capacity against the bench's, both contact
shares, both sensors' response times calibrated against the bench bodies' (one
``sensor_tau_s`` for both, or the rig file's ``tau_T2`` and ``tau_T3``), and the
calibrated thermistor depths, so that the alarms can be set against the two
sensors' difference.

    python analyses/plate_vs_contact.py /work/gn_rf_rim
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def rows(folder):
    """One dict per null batch under ``folder`` (``null_sN/{batch/truth.json, run/summary.json, gap.json}``)."""
    for case in sorted(Path(folder).glob("null_s*"), key=lambda p: int(p.name[6:])):
        summary, gap = case / "run" / "summary.json", case / "gap.json"
        if not (summary.exists() and gap.exists()):
            continue
        truth = json.loads((case / "batch" / "truth.json").read_text())["modules"]
        verdict = json.loads(gap.read_text())["verdict"]
        for mid, m in json.loads(summary.read_text())["modules"].items():
            bench, post = truth[mid]["rig_bench"], m["nuisance"]
            body = [bench["c_sensor"] / (bench["g_sensor"] * (1.0 + bench[f"v_{c}"])) for c in ("T2_C", "T3_C")]
            tau = [post.get(k, post.get("sensor_tau_s"))["mean"] for k in ("tau_T2", "tau_T3")]
            yield {
                "case": case.name,
                "module": mid,
                "verdict": verdict,
                "c_plate_hot": (post["c_plate_hot"]["mean"], bench["c_plate_hot"]),
                "c_plate_cold": (post["c_plate_cold"]["mean"], bench["c_plate_cold"]),
                "v": (bench["v_T2_C"], bench["v_T3_C"]),
                "depth_mm": (1e3 * post["depth_T2"]["mean"], 1e3 * post["depth_T3"]["mean"]),
                "tau_s": (*tau, *body),
            }


def main(folder):
    """Print the table (markdown) for the work folder ``folder``."""
    print(
        "| batch | gap verdict | c_plate_hot calibrated (bench) [J/K] | c_plate_cold calibrated (bench) [J/K] "
        "| v_T2 / v_T3 (bench) | v_T2 - v_T3 | T2 / T3 response calibrated (bench body) [s] "
        "| depth_T2 / depth_T3 calibrated [mm] |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for r in rows(folder):
        (ch, th), (cc, tc), (v2, v3), (d2, d3) = r["c_plate_hot"], r["c_plate_cold"], r["v"], r["depth_mm"]
        t2, t3, b2, b3 = r["tau_s"]
        print(
            f"| {r['case']} {r['module']} | {r['verdict']} | {ch:.2f} ({th:.2f}) | {cc:.2f} ({tc:.2f}) "
            f"| {v2:.2f} / {v3:.2f} | {v2 - v3:+.2f} | {t2:.2f} ({b2:.2f}) / {t3:.2f} ({b3:.2f}) | {d2:.2f} / {d3:.2f} |"
        )


if __name__ == "__main__":
    if len(sys.argv) != 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0 if len(sys.argv) == 2 else 2)
    main(sys.argv[1])
