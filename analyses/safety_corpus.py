"""The bad-input corpus through the command line, before and after: a table of outcomes.

Each case builds its inputs (``tests/corpus.py``), runs one tembayes command
in a fresh process and classifies what happened:

- ``refused clearly``: exit 2, a one-line error naming the right file/line/key
  and cause, nothing written, inputs unchanged;
- ``refused, wrong reason``: refused, but the message misses the cause;
- ``accepted correctly``: exit 0 where the input is fine (a warning at most);
- ``accepted silently``: the command went on with an input it should refuse;
- ``traceback``: a Python traceback instead of a message;
- ``data loss``: an input, a user's file or an earlier result was deleted or
  changed.

Run it against this checkout and against an earlier commit (checked out as a
git worktree) side by side:

    python analyses/safety_corpus.py --baseline d034f0e

Commands that would start a long calibration are stopped after ``--budget``
seconds (what counts happens in the first seconds: a refusal or a deletion).
Writes analyses/results/safety_corpus.{json,md}.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests"))

from corpus import DATA_CASES, EXAMPLE, colliding_ids, good_batch  # noqa: E402


def tree(folder):
    folder = Path(folder)
    if not folder.exists():
        return None
    if folder.is_file():
        return {"": hashlib.sha256(folder.read_bytes()).hexdigest()}
    return {
        p.relative_to(folder).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


def fake_run(folder):
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text('{"modules": {}}')
    (folder / "posterior.nc").write_bytes(b"earlier result")
    return folder


# A case: build(tmp) -> dict(argv, keep=[paths that must not change], expect="refuse"|"accept", needles=[...])
def _data_case(name):
    build, words, where = DATA_CASES[name]

    def make(tmp):
        b = build(tmp, "b")
        return {"argv": ["inspect", b], "keep": [b], "needles": [words, where]}

    return make


def _overwrite_user_folder(tmp):
    b = good_batch(tmp, "b", validation=False)
    mine = tmp / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("mine")
    return {
        "argv": ["calibrate", b, "--out", mine, "--overwrite"],
        "keep": [b, mine],
        "needles": ["not a tembayes output"],
    }


def _overwrite_is_batch(tmp):
    b = good_batch(tmp, "b", validation=False)
    return {"argv": ["calibrate", b, "--out", b, "--overwrite"], "keep": [b], "needles": ["batch folder itself"]}


def _overwrite_parent_of_batch(tmp):
    b = good_batch(tmp / "data", "b", validation=False)
    return {
        "argv": ["calibrate", b, "--out", tmp / "data", "--overwrite"],
        "keep": [b],
        "needles": ["holds the batch folder"],
    }


def _out_inside_batch(tmp):
    b = good_batch(tmp, "b", validation=False)
    return {"argv": ["calibrate", b, "--out", b / "run"], "keep": [b], "needles": ["inside the batch folder"]}


def _overwrite_earlier_run_killed(tmp):
    b = good_batch(tmp, "b", validation=False)
    run = fake_run(tmp / "run")
    return {
        "argv": ["calibrate", b, "--out", run, "--overwrite"],
        "keep": [b, run],
        "expect": "accept",
        "budget": 15.0,
    }  # stopped mid-run: the earlier run must survive


def _out_is_a_file(command):
    def make(tmp):
        b = good_batch(tmp, "b", validation=False)
        f = tmp / "afile"
        f.write_text("x")
        argv = [command, f] if command == "simulate" else [command, b, "--out", f]
        return {"argv": argv, "keep": [b, f], "needles": ["is a file"]}

    return make


def _colliding(tmp):
    b = colliding_ids(tmp, "b")
    return {"argv": ["inspect", b], "keep": [b], "needles": ["share output file names"]}


def _short_gap_warning(tmp):
    from corpus import read_csv, write_csv

    b = good_batch(tmp, "b", validation=False)
    path = b / "TEM1" / "identification.csv"
    header, a = read_csv(path)
    t = a[:, 0]
    write_csv(path, header, a[~((t > 1000) & (t < 1005))])
    return {"argv": ["inspect", b], "keep": [b], "expect": "accept"}


def _clean_example(tmp):
    return {"argv": ["inspect", EXAMPLE], "keep": [EXAMPLE], "expect": "accept"}


CASES = {f"data: {k}": _data_case(k) for k in sorted(DATA_CASES)}
CASES.update(
    {
        "data: colliding module ids": _colliding,
        "data: a 5 s gap inside a hold (fine)": _short_gap_warning,
        "data: the shipped example (fine)": _clean_example,
        "out: --overwrite on a folder of the user's": _overwrite_user_folder,
        "out: --out = the batch, --overwrite": _overwrite_is_batch,
        "out: --out = the batch's parent, --overwrite": _overwrite_parent_of_batch,
        "out: --out inside the batch": _out_inside_batch,
        "out: --overwrite, run killed: earlier run kept": _overwrite_earlier_run_killed,
        "out: calibrate --out is a file": _out_is_a_file("calibrate"),
        "out: identify --out is a file": _out_is_a_file("identify"),
        "out: simulate OUT is a file": _out_is_a_file("simulate"),
    }
)


def run_case(make, pythonpath, budget):
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        case = make(tmp)
        keep = {str(p): tree(p) for p in case["keep"]}
        env = dict(os.environ, PYTHONPATH=str(pythonpath))
        argv = [sys.executable, "-m", "tembayes", *map(str, case["argv"])]
        t0 = time.perf_counter()
        p = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp, start_new_session=True
        )
        try:
            out, err = p.communicate(timeout=case.get("budget", budget))
            rc = p.returncode
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, 9)
            out, err = p.communicate()
            rc = None
        seconds = time.perf_counter() - t0
        lost = [k for k, v in keep.items() if tree(k) != v]
    last = (err.strip().splitlines() or [""])[-1]
    expect = case.get("expect", "refuse")
    if lost:
        outcome = "data loss"
    elif "Traceback" in err:
        outcome = "traceback"
    elif rc in (0, None):
        outcome = "accepted correctly" if expect == "accept" else "accepted silently"
    elif expect == "accept":
        outcome = "refused, wrong reason"
    elif all(n in last for n in case.get("needles", [])):
        outcome = "refused clearly"
    else:
        outcome = "refused, wrong reason"
    return {"outcome": outcome, "exit": rc, "seconds": round(seconds, 1), "message": last[:300], "lost": lost}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", default="d034f0e", help="commit to compare with (default d034f0e)")
    ap.add_argument("--budget", type=float, default=30.0, help="seconds before a command is stopped")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp(prefix="tembayes-baseline-"))
    subprocess.run(
        ["git", "worktree", "add", "--detach", str(work), args.baseline], cwd=ROOT, check=True, capture_output=True
    )
    try:
        rows = {}
        for name, make in CASES.items():
            rows[name] = {"before": run_case(make, work, args.budget), "after": run_case(make, ROOT, args.budget)}
            print(f"{name:55s} {rows[name]['before']['outcome']:22s} -> {rows[name]['after']['outcome']}", flush=True)
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(work)], cwd=ROOT, check=False)
    kinds = [
        "refused clearly",
        "accepted correctly",
        "refused, wrong reason",
        "accepted silently",
        "traceback",
        "data loss",
    ]
    count = {w: {k: sum(r[w]["outcome"] == k for r in rows.values()) for k in kinds} for w in ("before", "after")}
    res = ROOT / "analyses" / "results"
    (res / "safety_corpus.json").write_text(
        json.dumps({"baseline": args.baseline, "cases": rows, "counts": count}, indent=2) + "\n"
    )
    lines = [
        f"# The bad-input corpus: {args.baseline} against this checkout",
        "",
        "`python analyses/safety_corpus.py --baseline " + args.baseline + "`",
        "",
        "| outcome | before | after |",
        "|---|---|---|",
    ]
    lines += [f"| {k} | {count['before'][k]} | {count['after'][k]} |" for k in kinds]
    lines += ["", "| case | before | after | message after |", "|---|---|---|---|"]
    for name, r in rows.items():
        msg = r["after"]["message"].replace("|", "/")
        lines.append(f"| {name} | {r['before']['outcome']} | {r['after']['outcome']} | {msg[:160]} |")
    (res / "safety_corpus.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines[:12]))


if __name__ == "__main__":
    main()
