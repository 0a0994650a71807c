"""Bad and unusual inputs made from the shipped example: one batch per case.

Each builder writes a one-module batch (the example's TEM1, its identification
and validation runs) into a new folder and breaks it one way.  The tests and
``analyses/safety_corpus.py`` (which runs them through the command line and
tabulates the outcomes) share these builders.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

EXAMPLE = Path(__file__).resolve().parent.parent / "data" / "example"
GOOD_TOML = (EXAMPLE / "batch.toml").read_text()


def read_csv(path):
    """``(header, rows as a float array)`` of a contract CSV."""
    path = Path(path)
    with open(path) as f:
        header = f.readline().strip().split(",")
    return header, np.loadtxt(path, delimiter=",", skiprows=1)


def write_csv(path, header, a):
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = ["%.3f", "%.5f", "%.5f"] + ["%.4f"] * (a.shape[1] - 3)
    np.savetxt(path, a, delimiter=",", header=",".join(header), comments="", fmt=fmt)
    return path


def good_batch(root, name="good", *, module="TEM1", toml=GOOD_TOML, validation=True):
    """A valid one-module batch (the example's TEM1)."""
    b = Path(root) / name
    (b / module).mkdir(parents=True)
    (b / "batch.toml").write_text(toml)
    shutil.copy(EXAMPLE / "TEM1" / "identification.csv", b / module / "identification.csv")
    if validation:
        shutil.copy(EXAMPLE / "TEM1" / "validation.csv", b / module / "validation.csv")
    return b


def _mutated(root, name, change, *, file="identification.csv"):
    """A one-module batch whose ``file`` went through ``change(header, a) -> a``."""
    b = good_batch(root, name)
    path = b / "TEM1" / file
    header, a = read_csv(path)
    write_csv(path, header, change({h: i for i, h in enumerate(header)}, a.copy()))
    return b


def _gap(c, a):
    t = a[:, c["time_s"]]
    return a[~((t > 7000) & (t < 7600))]  # 10 minutes of logging lost, a current step inside


def _stuck_t3(c, a):
    a[len(a) // 2 :, c["T3_C"]] = a[len(a) // 2, c["T3_C"]]
    return a


def _t4_minus_55(c, a):
    n = len(a)
    a[n // 2 :, c["T4_C"]] = -55.0 + np.random.default_rng(0).normal(0, 0.004, n - n // 2)
    return a


def _negate(*cols):
    def change(c, a):
        for col in cols:
            a[:, c[col]] *= -1
        return a

    return change


def _time_ms(c, a):
    a[:, c["time_s"]] *= 1000.0
    return a


def _short_gap_reversed(c, a):
    """Current and voltage negated, and 18 s lost in the middle of a hold (a warning only)."""
    t, i = a[:, c["time_s"]], a[:, c["current_A"]]
    mid = t[np.flatnonzero(np.abs(np.diff(i)) > 0.1)[3] + 1] + 200.0  # inside the fourth step's hold
    return _negate("current_A", "voltage_V")(c, a[~((t > mid) & (t < mid + 18.0))])


def _time_min(c, a):
    a[:, c["time_s"]] /= 60.0
    return a


def _columns(*pairs):
    """Columns read from other columns: ``("T1_C", "T2_C")`` puts T2's values in T1."""

    def change(c, a):
        b = a.copy()
        for to, frm in pairs:
            b[:, c[to]] = a[:, c[frm]]
        return b

    return change


def _logger_order_negated(c, a):
    """The sensors in a logger's order (T1 <- T2, T2 <- T3, T3 <- T1), the polarity 'fixed' by negating."""
    return _negate("current_A", "voltage_V")(c, _columns(("T1_C", "T2_C"), ("T2_C", "T3_C"), ("T3_C", "T1_C"))(c, a))


def _degf(cols, rows=None):
    def change(c, a):
        a = a if rows is None else a[:rows]
        for col in cols:
            a[:, c[col]] = a[:, c[col]] * 1.8 + 32.0
        return a

    return change


ALL_T = ("T1_C", "T2_C", "T3_C", "T4_C", "T_water_C", "T_amb_C")
#: the first 8000 s of the staircase: below 150 degF everywhere
COOL_ROWS = 40000


def _toml(text):
    def build(root, name):
        return good_batch(root, name, toml=text)

    return build


#: case -> (builder(root, name) -> batch folder, the words the refusal must hold, the file/key it must name)
DATA_CASES = {
    "time_gap_10_min": (lambda r, n: _mutated(r, n, _gap), "600.2 s gap", "line 35002"),
    "stuck_T3": (lambda r, n: _mutated(r, n, _stuck_t3), "stuck", "column 'T3_C'"),
    "T4_minus_55_half_run": (lambda r, n: _mutated(r, n, _t4_minus_55), "jumps", "column 'T4_C'"),
    "polarity_current_and_voltage": (
        lambda r, n: _mutated(r, n, _negate("current_A", "voltage_V")),
        "Negate current_A and voltage_V",
        "column 'current_A'",
    ),
    "polarity_current_only": (
        lambda r, n: _mutated(r, n, _negate("current_A")),
        "Negate current_A",
        "column 'current_A'",
    ),
    "polarity_reversed_with_a_short_gap": (
        lambda r, n: _mutated(r, n, _short_gap_reversed),
        "Negate current_A and voltage_V",
        "column 'current_A'",
    ),
    "polarity_voltage_only": (
        lambda r, n: _mutated(r, n, _negate("voltage_V")),
        "Negate voltage_V",
        "column 'voltage_V'",
    ),
    "time_in_ms": (lambda r, n: _mutated(r, n, _time_ms), "looks like milliseconds", "column 'time_s'"),
    "time_in_minutes": (lambda r, n: _mutated(r, n, _time_min), "looks like minutes", "column 'time_s'"),
    "T1_T2_swapped": (
        lambda r, n: _mutated(r, n, _columns(("T1_C", "T2_C"), ("T2_C", "T1_C"))),
        "not the order of the heat path",
        "column 'T2_C'",
    ),
    "T3_T4_swapped": (
        lambda r, n: _mutated(r, n, _columns(("T3_C", "T4_C"), ("T4_C", "T3_C"))),
        "not the order of the heat path",
        "column 'T3_C'",
    ),
    "T2_T3_swapped": (
        lambda r, n: _mutated(r, n, _columns(("T2_C", "T3_C"), ("T3_C", "T2_C"))),
        "a swap across the module",
        "column 'T3_C'",
    ),
    "sensors_in_logger_order_polarity_negated": (
        lambda r, n: _mutated(r, n, _logger_order_negated),
        "not the order of the heat path",
        "column 'T3_C'",
    ),
    "degF_whole_file": (lambda r, n: _mutated(r, n, _degf(ALL_T)), "look like degF", "identification.csv"),
    "degF_whole_file_cool_run": (
        lambda r, n: _mutated(r, n, _degf(ALL_T, COOL_ROWS)),
        "look like degF",
        "identification.csv",
    ),
    "degF_one_column_cool_run": (lambda r, n: _mutated(r, n, _degf(["T4_C"], COOL_ROWS)), "degF?", "column 'T4_C'"),
    "stuck_T3_in_validation": (
        lambda r, n: _mutated(r, n, _stuck_t3, file="validation.csv"),
        "stuck",
        "validation.csv",
    ),
    "th_C_in_kelvin": (_toml(GOOD_TOML.replace("th_C = 25.0", "th_C = 298.15")), "looks like kelvin", "column 'th_C'"),
    "imax_in_mA": (_toml(GOOD_TOML.replace("imax_A = 6.4", "imax_A = 6400")), "imax_A (mA?)", "column 'imax_A'"),
    "misspelt_population_table": (
        _toml(GOOD_TOML + "\n[populaton]\nspread_S0_rel = 0.01\n"),
        "did you mean 'population'",
        "column 'populaton'",
    ),
    "misspelt_rig_table": (_toml(GOOD_TOML.replace("[rig]", "[rigg]")), "did you mean 'rig'", "column 'rigg'"),
    "misspelt_datasheet_key": (
        _toml(GOOD_TOML.replace("qmax_W", "qmax_w")),
        "did you mean 'qmax_W'",
        "column 'qmax_w'",
    ),
    "misspelt_rig_parameter": (_toml(GOOD_TOML + "g_coolr = 11.0\n"), "did you mean 'g_cooler'", "column 'rig'"),
}


def colliding_ids(root, name):
    """Module folders 'TEM 1' and 'TEM_1': one output file name."""
    b = good_batch(root, name, module="TEM 1")
    shutil.copytree(b / "TEM 1", b / "TEM_1")
    return b
