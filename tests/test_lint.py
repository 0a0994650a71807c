"""The code passes ruff's lint rules and is in ruff's format (both configured in pyproject.toml)."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TREES = ("tembayes", "tests", "analyses")


def _ruff(*args):
    return subprocess.run([sys.executable, "-m", "ruff", *args, *TREES], cwd=ROOT, capture_output=True, text=True)


def test_ruff_lint_passes():
    r = _ruff("check", "--no-cache")
    assert r.returncode == 0, f"ruff check found problems (fix them, or `ruff check --fix`):\n{r.stdout}{r.stderr}"


def test_ruff_format_is_applied():
    r = _ruff("format", "--check", "--no-cache")
    assert r.returncode == 0, f"files not in ruff's format (run `ruff format`):\n{r.stdout}{r.stderr}"
