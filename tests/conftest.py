"""Shared fixtures.

``data_factory`` builds valid contract CSVs and batch folders under
``tmp_path`` that tests then break one way at a time.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from tembayes.physics import REFERENCE

CSV_COLUMNS = REFERENCE.layout.csv_columns

TEC1_12706 = {
    "name": "TEC1-12706",
    "th_C": 25.0,
    "imax_A": 6.4,
    "vmax_V": 14.4,
    "dtmax_K": 66.0,
    "qmax_W": 50.0,
}


def sha256(path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


class DataFactory:
    """Valid contract inputs (5 Hz, 0.2 A, ~0.5 V, temperatures 20-30 degC)."""

    TEC1_12706 = TEC1_12706
    sha256 = staticmethod(sha256)

    def __init__(self, root: Path):
        self.root = root

    @staticmethod
    def header() -> list:
        return list(CSV_COLUMNS)

    @staticmethod
    def rows(n=50, dt=0.2, t0=0.0, seed=0) -> list:
        """Rows of strings in contract column order; line number = index + 2."""
        rng = np.random.default_rng(seed)
        k = np.arange(n)
        time = t0 + dt * k
        current = 0.2 + rng.normal(0, 1e-3, n)
        voltage = 0.5 + 0.001 * k / n + rng.normal(0, 1e-3, n)
        temps = [
            21.0 + 0.02 * k / n,  # T1, next to the water cooler
            22.0 + 0.05 * k / n,  # T2
            28.0 - 0.50 * k / n,  # T3, cold side warming the other way
            29.0 - 0.40 * k / n,  # T4
            np.full(n, 20.0),  # water
            np.full(n, 23.0),  # ambient
        ]
        temps = [t + rng.normal(0, 0.004, n) for t in temps]
        cols = [time, current, voltage, *temps]
        fmts = ["{:.3f}", "{:.5f}", "{:.5f}"] + ["{:.4f}"] * 6
        return [[f.format(c[i]) for f, c in zip(fmts, cols)] for i in range(n)]

    def write_csv(self, name="experiment.csv", header=None, rows=None, *, text=None, sep=",", newline="\n") -> Path:
        path = self.root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if text is None:
            header = self.header() if header is None else header
            rows = self.rows() if rows is None else rows
            text = newline.join(sep.join(r) for r in [header, *rows]) + newline
        path.write_bytes(text.encode() if isinstance(text, str) else text)
        return path

    def batch_toml(self, module_type=None, rig=None) -> str:
        table = dict(TEC1_12706 if module_type is None else module_type)
        lines = ["[module_type]"]
        for k, v in table.items():
            lines.append(f'{k} = "{v}"' if isinstance(v, str) else f"{k} = {v!r}")
        if rig is not None:
            lines.append("[rig]")
            for k, v in rig.items():
                lines.append(f'{k} = "{v}"' if isinstance(v, str) else f"{k} = {v!r}")
        return "\n".join(lines) + "\n"

    def batch(self, name="batch", modules=("TEM1", "TEM2"), validations=("validation.csv",), toml=None) -> Path:
        """A valid batch folder; ``toml`` replaces the batch.toml text."""
        folder = self.root / name
        folder.mkdir(parents=True)
        (folder / "batch.toml").write_text(self.batch_toml() if toml is None else toml)
        for m, mod in enumerate(modules):
            self.write_csv(f"{name}/{mod}/identification.csv", rows=self.rows(seed=m))
            for v, val in enumerate(validations):
                self.write_csv(f"{name}/{mod}/{val}", rows=self.rows(t0=100.0 * v, seed=100 + v))
        return folder


@pytest.fixture
def data_factory(tmp_path) -> DataFactory:
    return DataFactory(tmp_path)


@pytest.fixture
def quick_population(monkeypatch):
    """The batch pipeline's population fits without the smallest deviation a small batch flags and
    without the leave-one-out refits.

    Both draw after the fit's own draws or from streams of their own, so the batch's draws stay the
    same; they cost most of a three-module population fit.  ``run3`` keeps them, and the tests
    that assert them use ``run3`` or fit them themselves.
    """
    from tembayes.calibrate import population

    fit = population.fit_population
    quick = {"design_reach": False, "loo_refits": False}
    monkeypatch.setattr(population, "fit_population", lambda *a, **kw: fit(*a, **{**kw, **quick}))


@pytest.fixture(scope="session")
def batch3(tmp_path_factory):
    """A 3-module bench batch (300 s holds, TEM2 an outlier), no validation runs, the paper's physics: the
    pipeline's tests run on the paper's form, the fast one (the default form is the shipped example's, the
    main job's)."""
    from tembayes.bench import BenchConfig, simulate_batch

    path = tmp_path_factory.mktemp("b3") / "batch"
    simulate_batch(
        path,
        BenchConfig(n_modules=3, seed=21, outlier="TEM2", hold=300.0, n_validations=0, physics="paper"),
        progress=lambda msg: None,
    )
    return path


@pytest.fixture(scope="session")
def batch4(tmp_path_factory):
    """Four bench modules with a short staircase (60 s holds at 1 Hz: 24 min)."""
    from tembayes.bench import BenchConfig, simulate_batch

    path = tmp_path_factory.mktemp("b4") / "batch"
    simulate_batch(
        path, BenchConfig(n_modules=4, seed=7, hold=60.0, rate=1.0, n_validations=0), progress=lambda msg: None
    )
    return path


@pytest.fixture(scope="session")
def run3(batch3, tmp_path_factory):
    """``batch3`` calibrated: ``(run folder, summary, truth)``."""
    from tembayes.calibrate import CalibrationOptions, calibrate_batch
    from tembayes.data import load_batch
    from tembayes.plots.calibrate import save_calibration_figures

    out = tmp_path_factory.mktemp("r3") / "run"
    # two worker processes: test_same_seed_same_module_result then also checks
    # that a module calibrated in a worker equals one calibrated in-process
    summ = calibrate_batch(
        load_batch(batch3), out, seed=0, workers=2, options=CalibrationOptions(model="paper", discrepancy="none")
    )
    save_calibration_figures(out)
    return out, summ, json.loads((batch3 / "truth.json").read_text())
