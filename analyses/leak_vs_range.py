"""Are the ambient_leak calls on out-of-model null batches right?  The bench's leaks against the documented range.

The out-of-model bench leaks from each module plate's edge to the room
(``leak_module``), a path the calibration model does not have: it shows up in
the neighbouring block's leak.  For every bench batch under the given work
folders this prints the bench's top and bottom leaks with the plate edge
added, the rig file's documented upper ends, what the calibration found
(each leak's posterior mean less the bench's leak, in plate edges: 1.0 is
the edge leak put on the block), and what ``tembayes gap`` said (its verdict
and the leaks it found beyond their range).

    python analyses/leak_vs_range.py /work/reststart_high2/high-paper-full-robust /work/gapnull_high2

A folder holds either ``bN/truth.json`` with ``bN.run/summary.json`` and
``bN.gap/gap.json`` (rest_start.py) or ``null_sN/batch/truth.json`` with
``null_sN/run/summary.json`` and ``null_sN/gap.json`` (gap_benchmark.py).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from tembayes.physics.rigread import rig_from_config


def cases(folder):
    """``(truth.json, summary.json, gap.json)`` of every bench batch under ``folder`` (either study's layout)."""
    folder = Path(folder)
    for t in sorted(folder.glob("b*/truth.json")):
        yield (
            t,
            t.parent.with_name(t.parent.name + ".run") / "summary.json",
            t.parent.with_name(t.parent.name + ".gap") / "gap.json",
        )
    for t in sorted(folder.glob("null_s*/batch/truth.json")):
        yield t, t.parent.parent / "run" / "summary.json", t.parent.parent / "gap.json"


def calibrated_excess(summary_file, mid, rb):
    """``"top / bottom"``: each leak's posterior mean less the bench's, in the bench's plate edges ("-" without a run)."""
    if not summary_file.exists():
        return "-"
    nuisance = json.loads(summary_file.read_text())["modules"][mid].get("nuisance", {})
    edge = rb.get("leak_module", 0.0)
    parts = [
        f"{(nuisance[k]['mean'] - rb[k]) / edge:.1f}" if k in nuisance and edge > 0 else "-"
        for k in ("leak_top", "leak_bottom")
    ]
    return " / ".join(parts)


def main(folders):
    """Print the table (markdown) for the work folders ``folders``."""
    rig = rig_from_config({"preset": "reference"}, leg_cells=0)
    high = {p.name: p.high for p in rig.parameters if p.name.startswith("leak")}
    print(
        "| batch | top + edge [W/K] | bottom + edge [W/K] | over the range | calibrated less bench, top / bottom "
        "[edges] | gap verdict | leaks beyond range |"
    )
    print("|---|---|---|---|---|---|---|")
    for truth_file, summary_file, gap_file in (c for f in folders for c in cases(f)):
        truth = json.loads(truth_file.read_text())
        for mid, m in truth["modules"].items():
            rb = m["rig_bench"]
            edge = rb.get("leak_module", 0.0)
            top, bottom = rb["leak_top"] + edge, rb["leak_bottom"] + edge
            over = [n for n, v in (("leak_top", top), ("leak_bottom", bottom)) if v > high[n]]
            verdict, beyond = "-", []
            if gap_file.exists():
                g = json.loads(gap_file.read_text())
                verdict = g["verdict"]
                beyond = [
                    f"{c['parameter']} {c['outside_sd']:.2f} sd" for c in g["conflicts"].get(mid, []) if c["conflict"]
                ]
            name = f"{truth_file.parent.parent.name}/{truth_file.parent.name}".replace("/batch", "")
            print(
                f"| {name} {mid} | {top:.4f} (≤ {high['leak_top']}) | {bottom:.4f} (≤ {high['leak_bottom']}) | "
                f"{', '.join(over) or '-'} | {calibrated_excess(summary_file, mid, rb)} | {verdict} "
                f"| {', '.join(beyond) or '-'} |"
            )


if __name__ == "__main__":
    main(sys.argv[1:])
