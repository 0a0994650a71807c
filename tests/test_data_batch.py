"""Datasheet conversions, batch.toml validation and batch-folder loading."""

from __future__ import annotations

import re
import sys
import types

import numpy as np
import pytest

from tembayes.constants import KELVIN
from tembayes.data import (
    Batch,
    Datasheet,
    Experiment,
    Module,
    load_batch,
    load_batch_toml,
    load_population_table,
    natural_key,
)
from tembayes.errors import DataError, ModelError

# ---------------------------------------------------------------- datasheet


def _tec1_12706():
    return Datasheet(name="TEC1-12706", th=25.0 + KELVIN, imax=6.4, vmax=14.4, dtmax=66.0, qmax=50.0)


def test_tec1_12706_conversions():
    ds = _tec1_12706()
    assert ds.seebeck() == pytest.approx(0.0483, abs=5e-5)
    assert ds.resistance() == pytest.approx(1.752, abs=5e-4)
    assert ds.conductance() == pytest.approx(0.5436, abs=5e-4)
    # the formulas themselves (Th in kelvin)
    th = 298.15
    assert ds.seebeck() == pytest.approx(14.4 / th, rel=1e-12)
    assert ds.resistance() == pytest.approx((th - 66) * 14.4 / (th * 6.4), rel=1e-12)
    assert ds.conductance() == pytest.approx((th - 66) * 14.4 * 6.4 / (2 * th * 66), rel=1e-12)


def test_other_datasheet_gives_other_numbers():
    # TEC1-12706 at Th = 50 degC (docs/data-format.md, '[module_type]') and a small 3 A module
    hot = Datasheet.from_table(
        {"th_C": 50.0, "imax_A": 6.4, "vmax_V": 16.4, "dtmax_K": 75.0, "qmax_W": 57.0}, "batch.toml"
    )
    small = Datasheet.from_table(
        {"name": "TEC1-12703", "th_C": 27.0, "imax_A": 3.0, "vmax_V": 15.4, "dtmax_K": 67.0, "qmax_W": 26.0},
        "batch.toml",
    )
    ref = _tec1_12706()
    assert hot.th == pytest.approx(323.15)
    assert hot.seebeck() == pytest.approx(16.4 / 323.15)
    assert small.resistance() == pytest.approx((300.15 - 67) * 15.4 / (300.15 * 3.0))
    assert small.conductance() == pytest.approx((300.15 - 67) * 15.4 * 3.0 / (2 * 300.15 * 67))
    for other in (hot, small):
        for f in ("seebeck", "resistance", "conductance"):
            assert abs(getattr(other, f)() / getattr(ref, f)() - 1) > 0.01
    assert small.resistance() > 2 * ref.resistance()  # 3 A module: higher resistance
    assert hot.name == ""


def test_datasheet_table_round_trip(data_factory):
    table = dict(data_factory.TEC1_12706)
    ds = Datasheet.from_table(table, "x/batch.toml")
    assert ds == _tec1_12706()
    assert ds.to_table() == table
    err = _ds_refusal({**table, "vendro": "Hebei"}, "b.toml")
    assert err.column == "vendro" and "unknown key 'module_type.vendro'" in err.problem


def _ds_refusal(table, path="b/batch.toml"):
    with pytest.raises(DataError) as info:
        Datasheet.from_table(table, path)
    return info.value


@pytest.mark.parametrize("key", ["th_C", "imax_A", "vmax_V", "dtmax_K", "qmax_W"])
def test_datasheet_missing_key(key, data_factory):
    table = dict(data_factory.TEC1_12706)
    del table[key]
    err = _ds_refusal(table)
    assert err.column == key
    assert re.search(rf"no '{key}'.*Add {key} = <datasheet value", str(err))
    assert "b/batch.toml" in str(err)


@pytest.mark.parametrize(
    "key, value, match",
    [
        ("imax_A", "6.4", r"imax_A = '6\.4' is not a finite number"),
        ("vmax_V", True, r"vmax_V = True is not a finite number"),
        ("qmax_W", float("nan"), r"qmax_W = nan is not a finite number"),
        ("dtmax_K", float("inf"), r"not a finite number"),
        ("imax_A", 0, r"imax_A = 0 must be positive"),
        ("vmax_V", -14.4, r"vmax_V = -14\.4 must be positive"),
        ("dtmax_K", 300.0, r"dtmax_K = 300\.0 is not below Th = 298\.15 K"),
        ("th_C", -300.0, r"th_C = -300\.0 is not a plausible datasheet hot-side temperature in degC"),
        ("th_C", 298.15, r"looks like kelvin"),
        ("imax_A", 6400.0, r"disagree by a factor 1\.1\de\+03"),
        ("vmax_V", 14400.0, r"disagree by a factor"),
        ("qmax_W", 50000.0, r"disagree by a factor 0\.001"),
    ],
)
def test_datasheet_bad_value(key, value, match, data_factory):
    err = _ds_refusal({**data_factory.TEC1_12706, key: value})
    assert err.column == key
    assert re.search(match, err.problem), err.problem


def test_datasheet_name_must_be_text(data_factory):
    err = _ds_refusal({**data_factory.TEC1_12706, "name": 12706})
    assert err.column == "name"


# ---------------------------------------------------------------- batch.toml


def test_load_batch_toml_defaults_rig(data_factory):
    folder = data_factory.batch()
    ds, rig = load_batch_toml(folder / "batch.toml")
    assert ds == _tec1_12706()
    assert rig == {"preset": "reference"}
    assert load_batch_toml(folder) == (ds, rig)  # the folder works too


def test_rig_table_kept_and_preset_defaulted(data_factory, fake_rig):
    folder = data_factory.batch(toml=data_factory.batch_toml(rig={"g_cooler": 11.0}))
    _, rig = load_batch_toml(folder)
    assert rig == {"preset": "reference", "g_cooler": 11.0}
    assert fake_rig == [rig]


def test_population_table_states_known_spreads(data_factory):
    toml = (
        data_factory.batch_toml() + "\n[population]\nspread_S0_rel = 0.01\nspread_R0_rel = 0.02\nspread_log_sd = 0.5\n"
    )
    folder = data_factory.batch(toml=toml)
    assert load_population_table(folder) == {"spread_S0_rel": (0.01, 0.5), "spread_R0_rel": (0.02, 0.5)}
    assert load_batch(folder).population == {"spread_S0_rel": (0.01, 0.5), "spread_R0_rel": (0.02, 0.5)}
    # the default uncertainty of a stated spread, and no table at all
    folder2 = data_factory.batch("b2", toml=data_factory.batch_toml() + "\n[population]\nspread_K_rel = 0.03\n")
    assert load_population_table(folder2) == {"spread_K_rel": (0.03, 0.3)}
    assert load_batch(data_factory.batch("b3")).population == {}


@pytest.mark.parametrize(
    "line, key, what",
    [
        ("spread_S0 = 0.01", "spread_S0", "unknown key 'population.spread_S0' (did you mean 'spread_S0_rel'?)"),
        ("spread_S0_rel = -0.01", "spread_S0_rel", "positive number"),
        ("spread_S0_rel = 'one percent'", "spread_S0_rel", "positive number"),
    ],
)
def test_population_table_refuses_bad_keys_naming_them(data_factory, line, key, what):
    folder = data_factory.batch(toml=data_factory.batch_toml() + f"\n[population]\n{line}\n")
    with pytest.raises(DataError) as e:
        load_batch(folder)
    assert e.value.column == key and what in str(e.value) and "batch.toml" in str(e.value)


@pytest.fixture
def fake_rig(monkeypatch):
    """Stand-in for tembayes.physics.rigread that knows only the 'reference' preset."""
    from tembayes.physics.rigread import REFERENCE

    calls = []

    def rig_from_config(config):
        calls.append(dict(config))
        if config.get("preset") != "reference":
            raise ModelError(f"unknown rig preset {config.get('preset')!r}; known presets: ['reference']")
        return REFERENCE

    module = types.ModuleType("tembayes.physics.rigread")
    module.rig_from_config = rig_from_config
    monkeypatch.setitem(sys.modules, "tembayes.physics.rigread", module)
    return calls


def test_rig_model_error_becomes_data_error(data_factory, fake_rig):
    folder = data_factory.batch(toml=data_factory.batch_toml(rig={"preset": "garage"}))
    with pytest.raises(DataError, match=r"batch\.toml, column 'rig': unknown rig preset 'garage'") as info:
        load_batch(folder)
    assert info.value.column == "rig"
    assert "Fix the [rig] table" in info.value.hint


def test_rig_checked_by_real_physics(data_factory):
    folder = data_factory.batch(toml=data_factory.batch_toml(rig={"preset": "no-such-rig"}))
    with pytest.raises(DataError, match="no-such-rig") as info:
        load_batch_toml(folder)
    assert info.value.column == "rig"
    assert load_batch_toml(data_factory.batch("ok"))[1] == {"preset": "reference"}


TOML_CASES = {
    "missing_file": (None, r"batch\.toml does not exist", None, None, r"needs a batch\.toml"),
    "syntax_error": ('[module_type]\nname = "x"\nth_C = = 25\n', r"TOML syntax error", 3, None, r"Fix the TOML syntax"),
    "no_module_type": (
        '[rig]\npreset = "reference"\n',
        r"no \[module_type\] table",
        None,
        "module_type",
        r"Add \[module_type\] with name, th_C, imax_A",
    ),
    "module_type_not_table": (
        'module_type = "TEC1-12706"\n',
        r"must be a table",
        None,
        "module_type",
        r"\[module_type\] section",
    ),
    "missing_key": (
        '[module_type]\nname = "x"\nth_C = 25.0\nimax_A = 6.4\nvmax_V = 14.4\ndtmax_K = 66.0\n',
        r"no 'qmax_W'",
        None,
        "qmax_W",
        r"Add qmax_W",
    ),
    "string_value": (
        '[module_type]\nth_C = 25.0\nimax_A = "6.4 A"\nvmax_V = 14.4\ndtmax_K = 66.0\nqmax_W = 50.0\n',
        r"imax_A = '6\.4 A' is not a finite number",
        None,
        "imax_A",
        r"plain number in A",
    ),
    "rig_not_table": (
        'rig = "reference"\n[module_type]\nth_C = 25.0\nimax_A = 6.4\nvmax_V = 14.4\ndtmax_K = 66.0\nqmax_W = 50.0\n',
        r"'rig' must be a table",
        None,
        "rig",
        r"\[rig\]",
    ),
    "preset_not_text": (
        "[module_type]\nth_C = 25.0\nimax_A = 6.4\nvmax_V = 14.4\ndtmax_K = 66.0\nqmax_W = 50.0\n[rig]\npreset = 1\n",
        r"rig\.preset must be text",
        None,
        "preset",
        r"quote it",
    ),
    "not_utf8": (b'[module_type]\nname = "\xff"\n', r"not UTF-8", None, None, r"UTF-8"),
}


@pytest.mark.parametrize("case", list(TOML_CASES))
def test_batch_toml_refusals(case, data_factory):
    text, match, line, column, hint = TOML_CASES[case]
    folder = data_factory.root / "b"
    folder.mkdir()
    path = folder / "batch.toml"
    if text is not None:
        path.write_bytes(text if isinstance(text, bytes) else text.encode())
        before = data_factory.sha256(path)
    with pytest.raises(DataError, match=match) as info:
        load_batch_toml(path)
    err = info.value
    assert err.path == path and str(path) in str(err)
    assert err.line == line
    assert err.column == column
    assert re.search(hint, err.hint, re.IGNORECASE), err.hint
    if text is not None:
        assert data_factory.sha256(path) == before


# ---------------------------------------------------------------- batch folder


def test_load_batch(data_factory):
    folder = data_factory.batch(modules=("TEM1", "TEM2", "TEM3"))
    batch = load_batch(folder)
    assert isinstance(batch, Batch)
    assert batch.path == folder
    assert batch.datasheet == _tec1_12706()
    assert batch.rig_config == {"preset": "reference"}
    assert list(batch.modules) == ["TEM1", "TEM2", "TEM3"]
    m = batch.modules["TEM2"]
    assert isinstance(m, Module) and m.id == "TEM2" and m.path == folder / "TEM2"
    assert isinstance(m.identification, Experiment)
    assert m.identification.path == folder / "TEM2" / "identification.csv"
    assert len(m.validations) == 1 and m.validations[0].path.name == "validation.csv"
    assert np.all(m.identification.sensors > 250)  # kelvin inside


def test_natural_order_of_modules_and_validations(data_factory):
    folder = data_factory.batch(
        modules=("TEM10", "TEM2", "TEM1", "SN0042"),
        validations=("validation10.csv", "validation2.csv", "validation.csv", "validation1.csv"),
    )
    (folder / ".hidden").mkdir()
    (folder / "__pycache__").mkdir()
    (folder / "notes.txt").write_text("not a module")
    (folder / "TEM1" / "readme.csv").write_text("ignored")
    batch = load_batch(folder)
    assert list(batch.modules) == ["SN0042", "TEM1", "TEM2", "TEM10"]
    names = [e.path.name for e in batch.modules["TEM1"].validations]
    assert names == ["validation.csv", "validation1.csv", "validation2.csv", "validation10.csv"]


def test_module_without_validations(data_factory):
    batch = load_batch(data_factory.batch(validations=()))
    assert all(m.validations == () for m in batch.modules.values())


def test_natural_key():
    ids = ["TEM10", "tem3", "TEM2", "A", "TEM1", "TEM02"]
    assert sorted(ids, key=natural_key) == ["A", "TEM1", "TEM02", "TEM2", "tem3", "TEM10"]


def test_batch_uses_datasheet_imax_for_ma_check(data_factory):
    # 12 A is fine without a datasheet (< 100 A) but > 3 x Imax of a 3 A module
    small = {"name": "small", "th_C": 27.0, "imax_A": 3.0, "vmax_V": 15.4, "dtmax_K": 67.0, "qmax_W": 26.0}
    folder = data_factory.batch(toml=data_factory.batch_toml(module_type=small), validations=())
    rows = data_factory.rows()
    rows[5][1] = "12.0"
    data_factory.write_csv("batch/TEM2/identification.csv", rows=rows)
    with pytest.raises(DataError, match=r"more than 3 x Imax = 3 A\) looks like mA") as info:
        load_batch(folder)
    assert info.value.path == folder / "TEM2" / "identification.csv"
    assert info.value.line == 7


def _build_folder(f, kind):
    if kind == "missing":
        return f.root / "nothing-here"
    if kind == "file":
        return f.write_csv("a-file.csv")
    if kind == "no_toml":
        folder = f.batch()
        (folder / "batch.toml").unlink()
        return folder
    if kind == "no_modules":
        folder = f.batch(modules=())
        (folder / ".git").mkdir()
        return folder
    if kind == "no_identification":
        folder = f.batch()
        (folder / "TEM2" / "identification.csv").rename(folder / "TEM2" / "ident.csv")
        return folder
    if kind == "bad_validation":
        folder = f.batch(validations=("validation.csv", "validation2.csv"))
        rows = f.rows()
        rows[3][4] = "oops"
        f.write_csv("batch/TEM1/validation2.csv", rows=rows)
        return folder
    raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind, where, match, line, column",
    [
        ("missing", "", r"batch folder does not exist", None, None),
        ("file", "", r"not a folder.*Pass the batch folder", None, None),
        ("no_toml", "batch.toml", r"batch\.toml does not exist", None, None),
        ("no_modules", "", r"no module folders.*own sub-folder", None, None),
        (
            "no_identification",
            "TEM2",
            r"no identification\.csv.*Each module folder needs identification\.csv",
            None,
            None,
        ),
        ("bad_validation", "TEM1/validation2.csv", r"'oops' is not a number", 5, "T2_C"),
    ],
)
def test_batch_folder_refusals(kind, where, match, line, column, data_factory):
    folder = _build_folder(data_factory, kind)
    with pytest.raises(DataError, match=match) as info:
        load_batch(folder)
    err = info.value
    assert err.path == (folder / where if where else folder)
    assert err.line == line and err.column == column
