"""Atomic outputs, CSV/TOML writers and the array constructor."""

from __future__ import annotations

import json
import os
import tomllib

import numpy as np
import pytest

from tembayes.constants import KELVIN
from tembayes.data import (
    Datasheet,
    atomic_directory,
    atomic_write_bytes,
    atomic_write_text,
    experiment_from_arrays,
    load_batch,
    load_batch_toml,
    load_experiment,
    write_batch_toml,
    write_experiment_csv,
    write_json,
)
from tembayes.errors import TembayesError


def _arrays(n=200, seed=0, dt=0.2):
    rng = np.random.default_rng(seed)
    t = 12.5 + np.cumsum(rng.uniform(0.5 * dt, 1.5 * dt, n))
    cur = np.where(np.arange(n) < n // 2, 0.2, -0.4) + rng.normal(0, 1e-3, n)
    volt = 0.35 * cur + rng.normal(0, 1e-3, n)
    sensors = np.array([21.0, 22.0, 27.0, 28.0])[:, None] + KELVIN + rng.normal(0, 0.05, (4, n))
    return t, cur, volt, sensors, np.full(n, 20.0 + KELVIN), 23.0 + KELVIN + rng.normal(0, 0.01, n)


def _no_temp_files(folder):
    return [p.name for p in folder.iterdir() if p.name.startswith(".")]


# ---------------------------------------------------------------- atomic files


def test_atomic_write_text_and_bytes(tmp_path):
    p = atomic_write_text(tmp_path / "sub" / "a.txt", "héllo\n")
    assert p.read_text(encoding="utf-8") == "héllo\n"
    atomic_write_bytes(p, b"\x00\x01")
    assert p.read_bytes() == b"\x00\x01"
    assert _no_temp_files(p.parent) == []
    # ordinary permissions, not mkstemp's 0600
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "sub" / "a.txt").stat().st_mode & 0o777 == 0o666 & ~umask


def test_atomic_write_failure_keeps_old_file(tmp_path, monkeypatch):
    p = tmp_path / "out.json"
    p.write_text("old")

    def boom(src, dst):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError, match="disk full"):
        atomic_write_text(p, "new")
    assert p.read_text() == "old"
    assert _no_temp_files(tmp_path) == []


def test_write_json_numpy_and_nan(tmp_path):
    p = write_json(
        tmp_path / "x.json",
        {
            "a": np.float64(1.5),
            "b": np.arange(3),
            "c": np.int32(7),
            "d": float("nan"),
            "e": [np.inf, -np.inf, 2.0],
            "f": (True, None),
            "g": {1: np.bool_(True)},
            "p": tmp_path,
        },
    )
    text = p.read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert text.startswith("{\n  ")  # indent=2
    assert json.loads(text) == {
        "a": 1.5,
        "b": [0, 1, 2],
        "c": 7,
        "d": None,
        "e": [None, None, 2.0],
        "f": [True, None],
        "g": {"1": True},
        "p": str(tmp_path),
    }
    with pytest.raises(TypeError, match="object"):
        write_json(tmp_path / "y.json", {"x": object()})
    assert not (tmp_path / "y.json").exists()


# ---------------------------------------------------------------- atomic folders


def test_atomic_directory_success(tmp_path):
    out = tmp_path / "run"
    with atomic_directory(out) as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".run.tmp-")
        (tmp / "summary.json").write_text("{}")
        assert not out.exists()  # nothing visible until the block succeeds
    assert (out / "summary.json").read_text() == "{}"
    assert _no_temp_files(tmp_path) == []


def test_atomic_directory_exception_leaves_nothing(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(RuntimeError, match="sampler died"):
        with atomic_directory(out) as tmp:
            (tmp / "part.nc").write_text("half")
            raise RuntimeError("sampler died")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def test_atomic_directory_refuses_existing(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "keep.txt").write_text("precious")
    with pytest.raises(TembayesError, match="already exists"):
        with atomic_directory(out):
            pytest.fail("must refuse before the work starts")
    assert (out / "keep.txt").read_text() == "precious"
    assert _no_temp_files(tmp_path) == []


def test_atomic_directory_refuses_if_created_meanwhile(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(TembayesError, match="already exists"):
        with atomic_directory(out) as tmp:
            (tmp / "new.txt").write_text("new")
            out.mkdir()
    assert list(out.iterdir()) == []
    assert _no_temp_files(tmp_path) == []


def test_atomic_directory_overwrite(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    (out / "old.txt").write_text("old")
    with atomic_directory(out, overwrite=True) as tmp:
        (tmp / "new.txt").write_text("new")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]
    assert _no_temp_files(tmp_path) == []
    # a failing overwrite keeps the old output
    with pytest.raises(ValueError):
        with atomic_directory(out, overwrite=True) as tmp:
            raise ValueError("refused input")
    assert sorted(p.name for p in out.iterdir()) == ["new.txt"]


# ---------------------------------------------------------------- experiments


def test_experiment_csv_round_trip(tmp_path):
    t, cur, volt, sensors, tw, ta = _arrays()
    exp = experiment_from_arrays(t, cur, volt, sensors, [tw, ta], extra={"T5_C": np.linspace(0, 1, t.size)})
    path = write_experiment_csv(tmp_path / "TEM1" / "identification.csv", exp)
    back = load_experiment(path)
    assert path.read_text().splitlines()[0] == ("time_s,current_A,voltage_V,T1_C,T2_C,T3_C,T4_C,T_water_C,T_amb_C,T5_C")
    half = {"time_s": 5e-4, "current_A": 5e-6, "voltage_V": 5e-6}
    for name, tol in half.items():
        np.testing.assert_allclose(back.channel(name), exp.channel(name), rtol=0, atol=tol * (1 + 1e-9))
    np.testing.assert_allclose(back.sensors, exp.sensors, rtol=0, atol=5e-5 + 1e-9)
    np.testing.assert_allclose(back.channel("T_water_C"), exp.channel("T_water_C"), rtol=0, atol=5e-5 + 1e-9)
    np.testing.assert_allclose(back.channel("T_amb_C"), exp.channel("T_amb_C"), rtol=0, atol=5e-5 + 1e-9)
    np.testing.assert_array_equal(back.extra["T5_C"], exp.extra["T5_C"])  # full precision
    # writing the loaded experiment again is byte-identical (stable format)
    again = write_experiment_csv(tmp_path / "again.csv", back)
    assert again.read_text() == path.read_text()
    assert _no_temp_files(path.parent) == []


def test_experiment_csv_decimals_and_no_negative_zero(tmp_path):
    t, cur, volt, sensors, tw, ta = _arrays(n=20)
    cur = np.full(20, -1e-9)
    exp = experiment_from_arrays(t, cur, volt, sensors, [tw, ta])
    path = write_experiment_csv(tmp_path / "e.csv", exp, decimals={"temperature": 2, "voltage_V": 3})
    first = path.read_text().splitlines()[1].split(",")
    assert first[1] == "0.00000"
    assert len(first[2].split(".")[1]) == 3
    assert all(len(x.split(".")[1]) == 2 for x in first[3:])
    path = write_experiment_csv(tmp_path / "f.csv", exp, decimals=6)
    assert all(len(x.split(".")[1]) == 6 for x in path.read_text().splitlines()[1].split(","))
    with pytest.raises(ValueError, match="unknown column 'T9_C'"):
        write_experiment_csv(tmp_path / "g.csv", exp, decimals={"T9_C": 1})


def test_experiment_csv_fine_time_keeps_increasing(tmp_path):
    # 2 kHz sampling: 3 time decimals would merge samples, so more are written.
    t, cur, volt, sensors, tw, ta = _arrays(n=50)
    t = 1.0 + 5e-4 * np.arange(50)
    exp = experiment_from_arrays(t, cur, volt, sensors, [tw, ta])
    back = load_experiment(write_experiment_csv(tmp_path / "fast.csv", exp))
    np.testing.assert_allclose(back.time, t, atol=1e-9)


def test_experiment_from_arrays_shapes():
    t, cur, volt, sensors, tw, ta = _arrays(n=10)
    exp = experiment_from_arrays(t, cur, volt, sensors, [tw, ta])
    assert exp.n == 10 and str(exp.path) == "<in-memory>"
    assert not exp.sensors.flags.writeable
    sensors_copy = sensors.copy()
    exp2 = experiment_from_arrays(t, cur, volt, sensors_copy, [tw, ta], path="x.csv")
    sensors_copy[0, 0] = 0.0  # the experiment holds its own copy
    assert exp2.sensors[0, 0] == sensors[0, 0]
    with pytest.raises(
        ValueError, match=r"sensors_K: expected shape \(4, 10\) for T1_C, T2_C, T3_C, T4_C, found \(10, 4\)"
    ):
        experiment_from_arrays(t, cur, volt, sensors.T, [tw, ta])
    with pytest.raises(ValueError, match=r"current: expected shape \(10,\) like time, found \(9,\)"):
        experiment_from_arrays(t, cur[:9], volt, sensors, [tw, ta])
    with pytest.raises(ValueError, match=r"time: expected shape \(n,\), found \(2, 5\)"):
        experiment_from_arrays(t.reshape(2, 5), cur, volt, sensors, [tw, ta])
    with pytest.raises(ValueError, match="at least 2 samples"):
        experiment_from_arrays(t[:1], cur[:1], volt[:1], sensors[:, :1], [tw[:1], ta[:1]])
    with pytest.raises(ValueError, match="strictly increasing at index 3"):
        experiment_from_arrays(np.r_[t[:3], t[2], t[4:]], cur, volt, sensors, [tw, ta])
    with pytest.raises(ValueError, match="voltage: contains NaN"):
        experiment_from_arrays(t, cur, np.r_[np.nan, volt[1:]], sensors, [tw, ta])


# ---------------------------------------------------------------- batch.toml


def test_write_batch_toml_round_trip(tmp_path):
    ds = Datasheet(name='Odd "name" \\ ü', th=50.0 + KELVIN, imax=3.0, vmax=15.4, dtmax=67.0, qmax=26.0)
    rig = {"preset": "reference", "g_cooler": 11.0, "leak_top": 1e-05, "nested": {"a": 1, "b": [1.5, 2.5]}}
    path = write_batch_toml(tmp_path / "batch.toml", ds, rig)
    doc = tomllib.loads(path.read_text())
    assert doc["module_type"] == ds.to_table()
    assert doc["rig"] == rig
    # without a rig: no [rig] table, i.e. the reference rig; a folder gets batch.toml inside
    (tmp_path / "plain").mkdir()
    plain = write_batch_toml(tmp_path / "plain", ds)
    assert "[rig]" not in plain.read_text()
    assert plain == tmp_path / "plain" / "batch.toml"
    assert load_batch_toml(plain) == (ds, {"preset": "reference"})


def test_written_batch_loads(tmp_path):
    ds = Datasheet(name="X", th=25.0 + KELVIN, imax=6.4, vmax=14.4, dtmax=66.0, qmax=50.0)
    t, cur, volt, sensors, tw, ta = _arrays()
    exp = experiment_from_arrays(t, cur, volt, sensors, [tw, ta])
    with atomic_directory(tmp_path / "batch") as tmp:
        write_batch_toml(tmp / "batch.toml", ds)
        for m in ("TEM1", "TEM2", "TEM10"):
            write_experiment_csv(tmp / m / "identification.csv", exp)
        write_experiment_csv(tmp / "TEM1" / "validation.csv", exp)
    batch = load_batch(tmp_path / "batch")
    assert list(batch.modules) == ["TEM1", "TEM2", "TEM10"]
    assert batch.datasheet == ds
    assert len(batch.modules["TEM1"].validations) == 1
