"""Benchmark: ``tembayes design`` on the shipped example against its 2-minute budget.

Runs the command as a user would (default targets: the reference
staircase's R0, S0 and K widths; 2 drawn modules, 2 worker processes) and
prints its wall time, the CPU time of its processes and the ratio of the
wall time to the 120 s budget.  Other work on the machine inflates the wall
time; the CPU time says what the design itself costs.

    python analyses/bench_design.py

Writes ``analyses/results/bench_design.json``.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BUDGET_S = 120.0


def main():
    out = Path(tempfile.mkdtemp()) / "design"
    cmd = [sys.executable, "-m", "tembayes", "design", str(ROOT / "data" / "example"), "--out", str(out)]
    t0 = time.perf_counter()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = time.perf_counter() - t0
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    design = json.loads((out / "design.json").read_text())
    res = {
        "command": "tembayes design data/example --out TMP",
        "wall_s": wall,
        "cpu_s": cpu,
        "budget_s": BUDGET_S,
        "wall_over_budget": wall / BUDGET_S,
        "load_average_1min_at_end": os.getloadavg()[0],
        "design_duration_h": design["duration_s"] / 3600.0,
        "candidates": len(design["evaluated"]),
    }
    (ROOT / "analyses" / "results" / "bench_design.json").write_text(json.dumps(res, indent=2) + "\n")
    print(
        f"tembayes design (example): wall {wall:.0f} s, CPU {cpu:.0f} s over {res['candidates']} candidates; "
        f"wall / budget {res['wall_over_budget']:.2f} (load average {res['load_average_1min_at_end']:.1f})"
    )


if __name__ == "__main__":
    main()
