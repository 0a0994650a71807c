"""The documentation's examples work: every Python snippet runs, every command parses.

Every ```python block of README.md and docs/*.md is executed, each on its own, in a
temporary folder laid out like the repository after the README's main job:

- ``data/`` -- the repository's ``data/`` (a symbolic link), so ``data/example`` is the
  shipped example batch;
- ``runs/example/`` -- a calibrated run folder.  The real main job takes minutes, so this
  one is a cheap stand-in with the same layout: a two-module bench batch (TEM1, TEM2) on a
  short staircase, the paper model, 1000 sampler steps (the modules end "not converged";
  the population is fitted with ``keep_unconverged``).  The snippets read its files
  (``summary.json``, ``posterior.nc``), so they run unchanged.  The session fixture
  ``run3`` of conftest.py is not used: it calibrates to convergence (minutes).

Every ``tembayes ...`` line of the other fenced blocks (bash, console, plain) of README.md,
docs/*.md and data/README.md is parsed with the command's own argument parser -- not run --
so a renamed flag or a wrong choice in the docs fails here.
"""

from __future__ import annotations

import re
import shlex
import warnings
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
FENCE = re.compile(r"^```([A-Za-z]*)[^\n]*\n(.*?)^```\s*$", re.S | re.M)


def _blocks(path):
    """(language, text) of every fenced block of a Markdown file."""
    return [(m.group(1).lower(), m.group(2)) for m in FENCE.finditer(path.read_text(encoding="utf-8"))]


def _python_snippets():
    out = []
    for path in DOCS:
        code = [text for lang, text in _blocks(path) if lang == "python"]
        out += [pytest.param(text, id=f"{path.relative_to(REPO)}[{i}]") for i, text in enumerate(code)]
    return out


def _commands():
    """Every ``tembayes ...`` command shown in a non-Python block, as an argument list."""
    out = []
    for path in [*DOCS, REPO / "data" / "README.md"]:
        for lang, text in _blocks(path):
            if lang in ("python", "toml", "json"):
                continue
            for line in text.splitlines():
                for part in line.split("&&"):
                    part = part.strip().removeprefix("$ ").removeprefix("time ")
                    if part.startswith("tembayes "):
                        words = shlex.split(part, comments=True)
                        out.append(pytest.param(words[1:], id=f"{path.relative_to(REPO)}: {' '.join(words)}"))
    return out


SNIPPETS = _python_snippets()
COMMANDS = _commands()


def test_the_docs_have_examples():
    assert any("README.md[" in p.id for p in SNIPPETS), "README.md has no ```python block"
    assert len(COMMANDS) >= 10


@pytest.fixture(scope="module")
def docs_workdir(tmp_path_factory):
    """A folder with ``data/`` (the repository's) and a cheap calibrated ``runs/example/``."""
    from tembayes.bench import BenchConfig, simulate_batch
    from tembayes.calibrate import CalibrationOptions, calibrate_batch
    from tembayes.data import load_batch

    root = tmp_path_factory.mktemp("docs")
    (root / "data").symlink_to(REPO / "data", target_is_directory=True)
    batch = root / "bench" / "batch"
    simulate_batch(
        batch, BenchConfig(n_modules=2, seed=7, hold=60.0, rate=1.0, n_validations=0), progress=lambda msg: None
    )
    cheap = CalibrationOptions(
        max_steps=1000,
        pilot=500,
        max_relinearise=1,
        psis_draws=100,
        leg_cells=2,
        block_split=1,
        model="paper",
        discrepancy="none",
    )
    from tembayes.calibrate import population

    fit = population.fit_population
    # the snippets read the run's files, not its numbers: the population's fit need not converge either
    quick = {"design_reach": False, "loo_refits": False, "max_steps": 4000}
    with warnings.catch_warnings(), pytest.MonkeyPatch.context() as mp:
        warnings.simplefilter("ignore", RuntimeWarning)  # "not converged": the cheap budget
        warnings.simplefilter("ignore", population.PopulationConvergenceWarning)
        mp.setattr(population, "fit_population", lambda *a, **kw: fit(*a, **{**kw, **quick}))
        calibrate_batch(
            load_batch(batch), root / "runs" / "example", seed=0, options=cheap, workers=1, keep_unconverged=True
        )
    return root


@pytest.mark.parametrize("code", SNIPPETS)
def test_python_snippet_runs(code, docs_workdir, monkeypatch, capsys):
    monkeypatch.chdir(docs_workdir)
    exec(compile(code, "<docs snippet>", "exec"), {"__name__": "__docs__"})
    assert capsys.readouterr().out.strip(), "a snippet should show the user something"


@pytest.mark.parametrize("argv", COMMANDS)
def test_shown_command_is_a_valid_invocation(argv):
    from tembayes.cli import build_parser

    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exit_:
        pytest.fail(f"`tembayes {' '.join(argv)}` does not parse (exit {exit_.code})")
    assert callable(getattr(args, "func", None))


def test_csv_examples_match_the_shipped_files():
    """A block of CSV lines after 'The first lines of `data/...csv`' is that file's start."""
    shown = 0
    for path in DOCS:
        text = path.read_text(encoding="utf-8")
        for m in re.finditer(r"first lines of `(data/[^`]+\.csv)`.*?\n```[a-z]*\n(.*?)^```", text, re.S | re.M):
            lines = m.group(2).splitlines()
            with open(REPO / m.group(1), encoding="utf-8") as f:
                head = [f.readline().rstrip("\n") for _ in lines]
            assert lines == head, f"{path.name}: the lines shown for {m.group(1)} differ from the file; copy them again"
            shown += 1
    assert shown >= 1, "docs/data-format.md no longer shows the example's first lines"
