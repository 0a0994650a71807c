"""load_experiment: what a valid CSV gives, and every refusal of docs/data-format.md, 'CSV columns'."""

from __future__ import annotations

import os
import re

import numpy as np
import pytest

from tembayes.constants import KELVIN
from tembayes.data import Datasheet, Experiment, load_experiment
from tembayes.errors import DataError
from tembayes.physics import REFERENCE

CSV_COLUMNS = REFERENCE.layout.csv_columns

# ---------------------------------------------------------------- accepted


def test_valid_file_loads_in_si(data_factory):
    rows = data_factory.rows()
    exp = load_experiment(data_factory.write_csv(rows=rows))
    assert isinstance(exp, Experiment)
    assert exp.n == 50
    assert exp.duration == pytest.approx(49 * 0.2)
    assert exp.sensors.shape == (4, 50)
    assert exp.time.dtype == np.float64
    # degC in the file, kelvin inside
    assert exp.sensors[2, 0] == pytest.approx(float(rows[0][5]) + KELVIN)
    assert exp.channel("T_water_C")[0] == pytest.approx(float(rows[0][7]) + KELVIN)
    assert exp.channel("T_amb_C")[-1] == pytest.approx(float(rows[-1][8]) + KELVIN)
    assert exp.current[3] == float(rows[3][1])
    assert exp.voltage[4] == float(rows[4][2])
    assert exp.extra == {}


def test_channel_returns_si_by_contract_name(data_factory):
    rows = data_factory.rows()
    exp = load_experiment(data_factory.write_csv(rows=rows))
    for j, name in enumerate(CSV_COLUMNS):
        expected = np.array([float(r[j]) for r in rows])
        if name.endswith("_C"):
            expected = expected + KELVIN
        np.testing.assert_allclose(exp.channel(name), expected, rtol=0, atol=1e-9)
    with pytest.raises(KeyError, match="T5_C"):
        exp.channel("T5_C")


def test_arrays_are_read_only(data_factory):
    exp = load_experiment(data_factory.write_csv())
    for arr in (exp.time, exp.current, exp.voltage, exp.sensors, exp.channel("T_water_C"), exp.channel("T_amb_C")):
        assert not arr.flags.writeable
        with pytest.raises(ValueError):
            arr[0] = 1.0
    with pytest.raises(AttributeError):
        exp.time = np.zeros(3)


def test_uneven_sampling_and_late_start_accepted(data_factory):
    rows = data_factory.rows(n=30)
    times = 1000.0 + np.cumsum(np.r_[0.0, np.random.default_rng(1).uniform(0.05, 0.6, 29)])
    for r, t in zip(rows, times):
        r[0] = f"{t:.3f}"
    exp = load_experiment(data_factory.write_csv(rows=rows))
    assert exp.time[0] == pytest.approx(1000.0)
    assert np.all(np.diff(exp.time) > 0)
    assert np.ptp(np.diff(exp.time)) > 0.3


def test_extra_numeric_column_kept_text_column_ignored(data_factory):
    header = data_factory.header() + ["T5_C", "note", "current_mA"]
    rows = [
        r + [f"{30 + i * 0.1:.1f}", f"step {i}", f"{float(r[1]) * 1000:.2f}"] for i, r in enumerate(data_factory.rows())
    ]
    exp = load_experiment(data_factory.write_csv(header=header, rows=rows))
    assert set(exp.extra) == {"T5_C", "current_mA"}  # current_A present: the mA copy is just extra
    np.testing.assert_allclose(exp.extra["T5_C"][:3], [30.0, 30.1, 30.2])
    assert exp.channel("T5_C") is exp.extra["T5_C"]
    assert not exp.extra["T5_C"].flags.writeable


def test_columns_in_any_order_bom_crlf_blank_trailing_lines(data_factory):
    header = data_factory.header()
    rows = data_factory.rows()
    order = [8, 7, 0, 3, 1, 4, 2, 6, 5]
    text = "\ufeff" + "\r\n".join(",".join(r[j] for j in order) for r in [header, *rows]) + "\r\n\r\n\r\n"
    exp = load_experiment(data_factory.write_csv(text=text))
    ref = load_experiment(data_factory.write_csv("ref.csv", rows=rows))
    for name in CSV_COLUMNS:
        np.testing.assert_array_equal(exp.channel(name), ref.channel(name))


def test_spaces_around_fields_accepted(data_factory):
    header = [f" {h} " for h in data_factory.header()]
    rows = [[f" {x}" for x in r] for r in data_factory.rows()]
    assert load_experiment(data_factory.write_csv(header=header, rows=rows)).n == 50


def _sheet(imax):
    return Datasheet(name="x", th=298.15, imax=imax, vmax=14.4, dtmax=66.0, qmax=50.0 * imax / 6.4)


def test_imax_allows_large_currents_of_big_modules(data_factory):
    rows = data_factory.rows()
    rows[10][1] = "25.00000"
    path = data_factory.write_csv(rows=rows)
    assert load_experiment(path, datasheet=_sheet(12.0)).current.max() == 25.0  # 25 < 3*12
    assert load_experiment(path).current.max() == 25.0  # no datasheet: 100 A limit


def test_load_is_fast_enough(data_factory):
    # 80k rows (4.5 h at 5 Hz) is the size of a validation run.
    import time as _time

    rows = data_factory.rows(n=80_000)
    path = data_factory.write_csv(rows=rows)
    t0 = _time.perf_counter()
    exp = load_experiment(path)
    elapsed = _time.perf_counter() - t0
    assert exp.n == 80_000
    assert elapsed < 3.0  # target < 1 s; slack for slow CI machines


# ---------------------------------------------------------------- refused


def _rows_with(factory, line, col, value, n=50):
    """Rows with the field of 1-based file ``line`` in column ``col`` set to ``value``."""
    rows = factory.rows(n=n)
    rows[line - 2][CSV_COLUMNS.index(col)] = value
    return rows


def _folder(path):
    path.mkdir()
    return path


def _text(factory, header, rows, sep=","):
    return "\n".join(sep.join(r) for r in [header, *rows]) + "\n"


# Each case: (build(factory) -> (path, load kwargs), regex on the message,
#             expected .line (int; None; or the type int = "the line of the
#             largest value"), expected .column, regex on the hint)
CASES = {
    "missing_file": (lambda f: (f.root / "nope.csv", {}), r"does not exist", None, None, r"check the path"),
    "folder_not_file": (lambda f: (_folder(f.root / "adir.csv"), {}), r"folder, not a CSV", None, None, r"\.csv"),
    "empty_file": (lambda f: (f.write_csv(text=b""), {}), r"empty", None, None, r"export the experiment again"),
    "whitespace_only": (lambda f: (f.write_csv(text="\n  \n\n"), {}), r"empty", None, None, r"header row"),
    "binary_file": (
        lambda f: (f.write_csv(text=b"time_s,current_A\n\x00\x01\x02"), {}),
        r"binary",
        2,
        None,
        r"plain CSV",
    ),
    "blank_first_line": (
        lambda f: (f.write_csv(text="\n" + _text(f, f.header(), f.rows())), {}),
        r"line 1 is empty",
        1,
        None,
        r"column names",
    ),
    "header_only": (lambda f: (f.write_csv(rows=[]), {}), r"no data rows", 1, None, r"samples"),
    "one_data_row": (lambda f: (f.write_csv(rows=f.rows(n=1)), {}), r"only 1 data row", 2, None, r"whole experiment"),
    "missing_column": (
        lambda f: (f.write_csv(header=f.header()[:-1], rows=[r[:-1] for r in f.rows()]), {}),
        r"'T_amb_C' missing; found 'time_s', 'current_A'.*'T_water_C'",
        1,
        "T_amb_C",
        r"must name all",
    ),
    "several_missing_columns": (
        lambda f: (f.write_csv(header=f.header()[:3], rows=[r[:3] for r in f.rows()]), {}),
        r"columns 'T1_C', 'T2_C', 'T3_C', 'T4_C', 'T_water_C', 'T_amb_C' missing",
        1,
        "T1_C",
        r"units",
    ),
    "duplicate_column": (
        lambda f: (f.write_csv(header=f.header() + ["T2_C"], rows=[r + ["1.0"] for r in f.rows()]), {}),
        r"'T2_C' appears twice",
        1,
        "T2_C",
        r"one column per name",
    ),
    "current_in_mA_header": (
        lambda f: (f.write_csv(header=["current_mA" if h == "current_A" else h for h in f.header()]), {}),
        r"'current_A' is missing, but there is 'current_mA' \(wrong units\)",
        1,
        "current_A",
        r"Did you mean 'current_A'\? convert the values to A",
    ),
    "temperature_in_K_header": (
        lambda f: (f.write_csv(header=["T1_K" if h == "T1_C" else h for h in f.header()]), {}),
        r"there is 'T1_K' \(wrong units\)",
        1,
        "T1_C",
        r"Did you mean 'T1_C'\? .*degC",
    ),
    "time_in_ms_header": (
        lambda f: (f.write_csv(header=["time_ms" if h == "time_s" else h for h in f.header()]), {}),
        r"there is 'time_ms' \(wrong units\)",
        1,
        "time_s",
        r"Did you mean 'time_s'\? convert the values to s",
    ),
    "water_in_K_header": (
        lambda f: (f.write_csv(header=["T_water_K" if h == "T_water_C" else h for h in f.header()]), {}),
        r"'T_water_K' \(wrong units\)",
        1,
        "T_water_C",
        r"Did you mean 'T_water_C'",
    ),
    "wrong_case_header": (
        lambda f: (f.write_csv(header=["t3_c" if h == "T3_C" else h for h in f.header()]), {}),
        r"there is 't3_c' \(names are case-sensitive\)",
        1,
        "T3_C",
        r"Did you mean 'T3_C'",
    ),
    "semicolon_separators": (
        lambda f: (
            f.write_csv(text=_text(f, f.header(), [[x.replace(".", ",") for x in r] for r in f.rows()], sep=";")),
            {},
        ),
        r"semicolon separators",
        1,
        None,
        r"use comma separators",
    ),
    "tab_separators": (
        lambda f: (f.write_csv(text=_text(f, f.header(), f.rows(), sep="\t")), {}),
        r"tab separators",
        1,
        None,
        r"use comma separators",
    ),
    "semicolon_rows_under_comma_header": (
        lambda f: (f.write_csv(text=_text(f, f.header(), []) + "\n".join(";".join(r) for r in f.rows())), {}),
        r"row has 1 field but the header has 9",
        2,
        None,
        r"use comma separators",
    ),
    "decimal_comma": (
        lambda f: (f.write_csv(rows=[[x.replace(".", ",") for x in r] for r in f.rows()]), {}),
        r"row has 18 fields but the header has 9",
        2,
        None,
        r"decimal comma.*use '\.'",
    ),
    "quoted_decimal_comma": (
        lambda f: (f.write_csv(rows=_rows_with(f, 7, "voltage_V", '"0,5"')), {}),
        r"'0,5' is not a number",
        7,
        "voltage_V",
        r"use '\.' as the decimal point",
    ),
    "short_row_middle": (
        lambda f: (f.write_csv(rows=[r if i != 10 else r[:6] for i, r in enumerate(f.rows())]), {}),
        r"row has 6 fields but the header has 9",
        12,
        None,
        r"fix or delete the row",
    ),
    "truncated_last_line": (
        lambda f: (f.write_csv(text=_text(f, f.header(), f.rows())[:-25]), {}),
        r"fields but the header has 9",
        51,
        None,
        r"last line looks truncated",
    ),
    "non_number": (
        lambda f: (f.write_csv(rows=_rows_with(f, 20, "T2_C", "23.1a")), {}),
        r"'23\.1a' is not a number",
        20,
        "T2_C",
        r"plain number",
    ),
    "empty_field": (
        lambda f: (f.write_csv(rows=_rows_with(f, 9, "current_A", "")), {}),
        r"empty field",
        9,
        "current_A",
        r"fill in a number or delete the row",
    ),
    "nan": (
        lambda f: (f.write_csv(rows=_rows_with(f, 33, "T4_C", "NaN")), {}),
        r"'NaN' is not a finite number",
        33,
        "T4_C",
        r"finite number",
    ),
    "inf": (
        lambda f: (f.write_csv(rows=_rows_with(f, 4, "voltage_V", "-inf")), {}),
        r"'-inf' is not a finite number",
        4,
        "voltage_V",
        r"fill the gap or delete the row",
    ),
    "time_not_increasing": (
        lambda f: (f.write_csv(rows=_rows_with(f, 15, "time_s", "2.000")), {}),
        r"not strictly increasing: 2 s on line 15 after 2\.4 s on line 14",
        15,
        "time_s",
        r"sort the rows",
    ),
    "time_repeated": (
        lambda f: (f.write_csv(rows=_rows_with(f, 15, "time_s", "2.400")), {}),
        r"not strictly increasing: 2\.4 s on line 15 after 2\.4 s on line 14",
        15,
        "time_s",
        r"sort",
    ),
    "duplicate_row": (
        lambda f: (f.write_csv(rows=(lambda r: r[:20] + [list(r[19])] + r[20:])(f.rows())), {}),
        r"duplicate row \(same as line 21\)",
        22,
        "time_s",
        r"delete the repeated row",
    ),
    "temperatures_in_kelvin": (
        lambda f: (
            f.write_csv(rows=[r[:3] + [f"{float(x) + 273.15:.4f}" for x in r[3:7]] + r[7:] for r in f.rows()]),
            {},
        ),
        r"values around 29[45]\.\d\d look like kelvin",
        None,
        "T1_C",
        r"convert to degC \(subtract 273\.15\)",
    ),
    "ambient_in_kelvin": (
        lambda f: (f.write_csv(rows=[r[:8] + [f"{float(r[8]) + 273.15:.4f}"] for r in f.rows()]), {}),
        r"look like kelvin",
        None,
        "T_amb_C",
        r"convert to degC",
    ),
    "temperature_out_of_range_high": (
        lambda f: (f.write_csv(rows=_rows_with(f, 40, "T3_C", "187.5")), {}),
        r"187\.5 degC is outside the plausible range \[-60, 150\] degC",
        40,
        "T3_C",
        r"fix or delete the row",
    ),
    "temperature_out_of_range_low": (
        lambda f: (f.write_csv(rows=_rows_with(f, 5, "T_water_C", "-80")), {}),
        r"-80 degC is outside",
        5,
        "T_water_C",
        r"degC",
    ),
    "current_in_mA_no_datasheet": (
        lambda f: (f.write_csv(rows=[r[:1] + [f"{float(r[1]) * 1000:.2f}"] + r[2:] for r in f.rows()]), {}),
        r"\|current\| up to 20\d\.\d+ \(more than 100 A\) looks like mA",
        int,
        "current_A",
        r"convert to A \(divide by 1000\)",
    ),
    "current_in_mA_with_imax": (
        lambda f: (f.write_csv(rows=_rows_with(f, 30, "current_A", "-25.0")), {"datasheet": _sheet(6.4)}),
        r"up to 25 \(more than 3 x Imax = 6\.4 A\) looks like mA",
        30,
        "current_A",
        r"convert to A",
    ),
    "voltage_in_mV": (
        lambda f: (f.write_csv(rows=[r[:2] + [f"{float(r[2]) * 10000:.1f}"] + r[3:] for r in f.rows()]), {}),
        r"\|voltage\| up to \d+\.?\d* \(more than 1000 V\) looks like mV",
        int,
        "voltage_V",
        r"convert to V \(divide by 1000\)",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_refusal_names_file_line_column_and_fix(case, data_factory):
    build, match, line, column, hint = CASES[case]
    path, kwargs = build(data_factory)
    before = data_factory.sha256(path) if path.is_file() else None
    with pytest.raises(DataError, match=match) as info:
        load_experiment(path, **kwargs)
    err = info.value
    assert err.path == path
    assert str(path) in str(err)
    if line is int:
        assert isinstance(err.line, int) and 2 <= err.line <= 51, str(err)
        line = err.line
    assert err.line == line, str(err)
    assert err.column == column, str(err)
    assert err.hint and re.search(hint, err.hint, re.IGNORECASE), err.hint
    assert err.hint[0].isupper(), err.hint
    if line is not None:
        assert f"line {line}" in str(err)
    if column is not None:
        assert f"column '{column}'" in str(err)
    # the input is never modified and nothing else appears next to it
    if before is not None:
        assert data_factory.sha256(path) == before
    assert sorted(p.name for p in path.parent.iterdir() if p.name.startswith(".")) == []


def test_data_error_is_a_value_error(data_factory):
    with pytest.raises(ValueError):
        load_experiment(data_factory.root / "missing.csv")


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root reads anything")
def test_unreadable_file_refused(data_factory):
    path = data_factory.write_csv()
    path.chmod(0)
    try:
        with pytest.raises(DataError, match="cannot be read.*permissions"):
            load_experiment(path)
    finally:
        path.chmod(0o644)


def test_bad_imax_is_a_programming_error(data_factory):
    with pytest.raises(ValueError, match="imax"):
        load_experiment(data_factory.write_csv(), datasheet=_sheet(0.0))
