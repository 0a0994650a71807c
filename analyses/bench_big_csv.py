"""Memory and time to inspect a batch whose identification run is a 300 MB CSV.

Target: ``tembayes inspect`` on a 300 MB CSV in <= 1 GB of memory.  The
baseline is the loader before block-wise parsing (commit d034f0e, which read
the whole file as text and split it into Python rows); both run side by side
in fresh processes here, on the same file, and the script prints the peak
resident memory of each and their ratio.

    python analyses/bench_big_csv.py [--mb 300] [--baseline d034f0e]

Writes analyses/results/bench_big_csv.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "data" / "example"

NEW = """
import resource, sys, time
from tembayes.cli import main
t0 = time.perf_counter()
rc = main(["inspect", sys.argv[1]])
print("RESULT", rc, time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""

OLD = """
import importlib.util, resource, sys, time
spec = importlib.util.spec_from_file_location("tembayes.data._baseline_experiment", sys.argv[2])
mod = importlib.util.module_from_spec(spec); sys.modules[spec.name] = mod; spec.loader.exec_module(mod)
t0 = time.perf_counter()
exp = mod.load_experiment(sys.argv[1] + "/TEM1/identification.csv", imax=6.4)
print("RESULT", 0, time.perf_counter() - t0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
"""


def make_batch(folder: Path, mb: float) -> Path:
    """The example's TEM1 identification run repeated (time shifted) until the CSV holds ``mb`` megabytes."""
    src = EXAMPLE / "TEM1" / "identification.csv"
    lines = src.read_text().splitlines()
    header, rows = lines[0], lines[1:]
    t = np.array([float(r.split(",", 1)[0]) for r in rows])
    span = t[-1] - t[0] + (t[1] - t[0])
    (folder / "TEM1").mkdir(parents=True)
    (folder / "batch.toml").write_text((EXAMPLE / "batch.toml").read_text())
    out = folder / "TEM1" / "identification.csv"
    with open(out, "w") as f:
        f.write(header + "\n")
        k = 0
        while f.tell() < mb * 1e6:
            shift = k * span
            f.writelines(f"{tk + shift:.3f},{r.split(',', 1)[1]}\n" for tk, r in zip(t, rows))
            k += 1
    return out


def run(code, *args):
    p = subprocess.run([sys.executable, "-c", code, *map(str, args)], capture_output=True, text=True, check=False)
    line = next((x for x in p.stdout.splitlines() if x.startswith("RESULT")), None)
    if line is None:
        raise RuntimeError(p.stderr[-2000:])
    _, rc, seconds, kb = line.split()
    return {"exit": int(rc), "seconds": float(seconds), "peak_MB": int(kb) / 1024}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mb", type=float, default=300.0)
    ap.add_argument("--baseline", default="d034f0e")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        csv = make_batch(tmp / "big", args.mb)
        size = csv.stat().st_size / 1e6
        old_src = subprocess.run(
            ["git", "show", f"{args.baseline}:tembayes/data/experiment.py"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        old = tmp / "baseline_experiment.py"
        old.write_text(old_src.replace("from ..", "from tembayes."))
        t0 = time.perf_counter()
        new = run(NEW, tmp / "big")
        base = run(OLD, tmp / "big", old)
        wall = time.perf_counter() - t0
    result = {
        "csv_MB": round(size, 1),
        "new_inspect": new,
        "baseline_load_only": base,
        "memory_ratio_baseline_over_new": base["peak_MB"] / new["peak_MB"],
        "target_peak_MB": 1024,
        "baseline": args.baseline,
        "wall_s": wall,
    }
    print(
        f"{size:.0f} MB CSV: tembayes inspect (load + preflight + summary) peak {new['peak_MB']:.0f} MB in "
        f"{new['seconds']:.1f} s (exit {new['exit']}); baseline loader ({args.baseline}, load only) peak "
        f"{base['peak_MB']:.0f} MB in {base['seconds']:.1f} s; ratio {result['memory_ratio_baseline_over_new']:.1f}x; "
        f"target <= 1024 MB: {'met' if new['peak_MB'] <= 1024 else 'MISSED'}"
    )
    out = ROOT / "analyses" / "results" / "bench_big_csv.json"
    out.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
