"""One experiment CSV (contract section 2): loading, validation, SI arrays.

The CSV carries degrees Celsius; everything an :class:`Experiment` hands out
is SI (kelvin, seconds, amperes, volts).  Every refusal is a
:class:`~tembayes.errors.DataError` that names the file, the line (header =
line 1) and/or the column, and says what to do.  Files are only ever read.
"""

from __future__ import annotations

import csv
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..constants import CSV_COLUMNS, KELVIN, SENSOR_CHANNELS, TEMPERATURE_COLUMNS
from ..errors import DataError

__all__ = ["Experiment", "load_experiment", "TEMP_MIN_C", "TEMP_MAX_C"]

#: Plausible temperature range of any CSV temperature column [degC].
TEMP_MIN_C = -60.0
TEMP_MAX_C = 150.0
#: A temperature column whose median is above this is taken for kelvin [degC].
_KELVIN_MEDIAN_C = 150.0
#: Without a datasheet, a current above this is taken for milliamperes [A].
_MAX_CURRENT_A = 100.0
#: ... with a datasheet, above this multiple of Imax.
_MAX_CURRENT_IMAX = 3.0
#: A voltage above this is taken for millivolts [V].
_MAX_VOLTAGE_V = 1000.0

_IN_MEMORY = Path("<in-memory>")

# Unit names for "convert the values to ..." hints on unit-variant headers.
_UNIT_NAMES = {"time_s": "s", "current_A": "A", "voltage_V": "V"}


@dataclass(frozen=True, eq=False)
class Experiment:
    """One experiment, in SI units.

    Attributes
    ----------
    path : Path
        The CSV file it came from (``<in-memory>`` for synthetic data).
    time : ndarray, shape (n,)
        Sample times [s], strictly increasing, as in the file (need not
        start at 0; sampling may be uneven).
    current : ndarray, shape (n,)
        Module current [A]; positive cools the bottom (cold-side) block.
    voltage : ndarray, shape (n,)
        Module terminal voltage [V].
    sensors : ndarray, shape (4, n)
        Block temperatures T1..T4 [K], top (water side) to bottom.
    t_water : ndarray, shape (n,)
        Cooling-water temperature [K].
    t_amb : ndarray, shape (n,)
        Ambient air temperature [K].
    extra : dict of str to ndarray
        Other numeric columns of the file, as written (unit unknown); kept,
        not used.

    Notes
    -----
    All arrays are float64 copies and read-only, so an experiment can be
    shared between threads, caches and models without defensive copies.
    """

    path: Path
    time: np.ndarray
    current: np.ndarray
    voltage: np.ndarray
    sensors: np.ndarray
    t_water: np.ndarray
    t_amb: np.ndarray
    extra: dict = field(default_factory=dict)

    def __post_init__(self):
        set_ = object.__setattr__  # frozen dataclass: the only way to normalise
        set_(self, "path", _IN_MEMORY if self.path is None else Path(self.path))
        n = None
        for name in ("time", "current", "voltage", "t_water", "t_amb"):
            arr = _frozen(getattr(self, name))
            if arr.ndim != 1:
                raise ValueError(f"Experiment.{name}: expected shape (n,), found {arr.shape}")
            if n is None:
                n = arr.shape[0]
            elif arr.shape[0] != n:
                raise ValueError(
                    f"Experiment.{name}: expected shape ({n},) like time, found {arr.shape}"
                )
            set_(self, name, arr)
        sensors = _frozen(self.sensors)
        if sensors.shape != (4, n):
            raise ValueError(f"Experiment.sensors: expected shape (4, {n}), found {sensors.shape}")
        set_(self, "sensors", sensors)
        extra = {}
        for key, value in dict(self.extra or {}).items():
            arr = _frozen(value)
            if arr.shape != (n,):
                raise ValueError(f"Experiment.extra[{key!r}]: expected shape ({n},), found {arr.shape}")
            extra[str(key)] = arr
        set_(self, "extra", extra)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.time.shape[0])

    @property
    def duration(self) -> float:
        """Time from the first to the last sample [s]."""
        return float(self.time[-1] - self.time[0]) if self.n else 0.0

    def channel(self, name: str) -> np.ndarray:
        """Return a column by its contract name, in SI units.

        Parameters
        ----------
        name : str
            A contract column name (``"time_s"``, ``"current_A"``,
            ``"voltage_V"``, ``"T1_C"`` .. ``"T4_C"``, ``"T_water_C"``,
            ``"T_amb_C"``) or the name of an extra column.

        Returns
        -------
        ndarray, shape (n,)
            Seconds, amperes, volts, or kelvin for ``*_C`` temperature
            columns (the CSV's degC converted).  Extra columns come as
            written in the file.

        Raises
        ------
        KeyError
            For an unknown name (the message lists the known ones).
        """
        if name == "time_s":
            return self.time
        if name == "current_A":
            return self.current
        if name == "voltage_V":
            return self.voltage
        if name in SENSOR_CHANNELS:
            return self.sensors[SENSOR_CHANNELS.index(name)]
        if name == "T_water_C":
            return self.t_water
        if name == "T_amb_C":
            return self.t_amb
        if name in self.extra:
            return self.extra[name]
        known = ", ".join(CSV_COLUMNS + tuple(self.extra))
        raise KeyError(f"no channel {name!r} in {self.path}; known: {known}")

    def __repr__(self):
        return (
            f"Experiment(path={str(self.path)!r}, n={self.n}, duration={self.duration:.6g} s, "
            f"extra={list(self.extra)})"
        )


def _frozen(values) -> np.ndarray:
    arr = np.array(values, dtype=np.float64)  # always a private copy
    arr.setflags(write=False)
    return arr


# --------------------------------------------------------------------------
# loading


def load_experiment(path, *, imax=None) -> Experiment:
    """Load and validate one experiment CSV (contract section 2).

    Parameters
    ----------
    path : str or Path
        The CSV file: one header row, comma separators, ``.`` decimal point,
        the contract columns in any order, further columns allowed.
    imax : float, optional
        Datasheet maximum current of the module type [A].  When given, a
        current above ``3 * imax`` is refused as milliamperes; otherwise the
        limit is 100 A.

    Returns
    -------
    Experiment
        SI arrays (temperatures in kelvin).  Numeric extra columns are kept
        in ``extra``; non-numeric ones are dropped.

    Raises
    ------
    DataError
        For anything that breaks the contract; the message names the file,
        the line (header = line 1) and/or column, and what to do.
    """
    path = Path(path)
    text = _read_text(path)
    lines = text.splitlines()
    if not any(line.strip() for line in lines):
        raise DataError(path, "the file is empty",
                        "Export the experiment again: the contract needs a header row and data rows")

    reader = csv.reader(lines)
    header = next(reader)
    names = _check_header(path, header, lines[0])
    ncol = len(names)

    rows, row_lines = [], []
    for row in reader:
        line_no = reader.line_num
        if not row or (len(row) == 1 and not row[0].strip()):
            continue  # blank lines carry nothing; tolerate them
        if len(row) != ncol:
            _refuse_field_count(path, row, ncol, line_no, lines)
        rows.append(row)
        row_lines.append(line_no)

    if not rows:
        raise DataError(path, "the file has a header but no data rows",
                        "Export the experiment again with its samples", line=1)
    if len(rows) < 2:
        raise DataError(path, "the file has only 1 data row; at least 2 are needed",
                        "Export the whole experiment", line=row_lines[0])

    cols = list(zip(*rows))  # column-major tuples of strings
    index = {name: j for j, name in enumerate(names)}
    data = {c: _to_float(path, cols[index[c]], c, row_lines) for c in CSV_COLUMNS}
    for c, arr in data.items():
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            i = int(bad[0])
            raise DataError(path, f"{cols[index[c]][i].strip()!r} is not a finite number",
                            "Every contract field needs a finite number: fill the gap or delete the row",
                            line=row_lines[i], column=c)

    extra = {}
    for j, name in enumerate(names):
        if name in CSV_COLUMNS or not name:
            continue
        try:
            extra[name] = np.array(cols[j], dtype=np.float64)
        except ValueError:
            pass  # non-numeric extra column (notes, timestamps): allowed and ignored

    _check_time(path, data, row_lines)
    _check_units(path, data, row_lines, imax)

    sensors = np.stack([data[c] for c in SENSOR_CHANNELS]) + KELVIN
    return Experiment(
        path=path,
        time=data["time_s"],
        current=data["current_A"],
        voltage=data["voltage_V"],
        sensors=sensors,
        t_water=data["T_water_C"] + KELVIN,
        t_amb=data["T_amb_C"] + KELVIN,
        extra=extra,
    )


def _read_text(path: Path) -> str:
    if not path.exists():
        raise DataError(path, "the file does not exist", "Check the path (and the batch folder layout)")
    if path.is_dir():
        raise DataError(path, "this is a folder, not a CSV file", "Pass the experiment's .csv file")
    try:
        raw = path.read_bytes()
    except OSError as e:
        raise DataError(path, f"the file cannot be read ({e.strerror or e})",
                        "Check the file's permissions") from None
    if not raw.strip():
        raise DataError(path, "the file is empty",
                        "Export the experiment again: the contract needs a header row and data rows")
    if b"\x00" in raw:
        line = raw[: raw.index(b"\x00")].count(b"\n") + 1
        raise DataError(path, "the file is binary, not a text CSV",
                        "Export the experiment as plain CSV text", line=line)
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        # Spreadsheet exports in a legacy code page (e.g. a degree sign in an
        # extra column name): the contract's own content is ASCII anyway.
        return raw.decode("cp1252", errors="replace")


def _check_header(path: Path, header: list, first_line: str) -> list:
    names = [h.strip() for h in header]
    if not any(names):
        raise DataError(path, "line 1 is empty, but the header row must be line 1",
                        f"Put the column names {', '.join(CSV_COLUMNS)} on line 1", line=1)
    if len(names) == 1:
        for sep, label in ((";", "semicolon"), ("\t", "tab")):
            if sep in names[0]:
                raise DataError(path, f"the header uses {label} separators",
                                "Use comma separators and '.' as the decimal point "
                                "(e.g. re-export as 'CSV (comma delimited)')", line=1)
    seen = {}
    for name in names:
        if name and name in seen:
            raise DataError(path, f"column {name!r} appears twice in the header",
                            "Keep one column per name", line=1, column=name)
        seen[name] = True
    missing = [c for c in CSV_COLUMNS if c not in seen]
    if missing:
        c = missing[0]
        guess = _did_you_mean(c, names)
        if guess is not None:
            other, why = guess
            raise DataError(path, f"required column {c!r} is missing, but there is {other!r} ({why})",
                            _rename_hint(c, other, why), line=1, column=c)
        found = ", ".join(repr(n) for n in names)
        raise DataError(path, f"required column{'s' if len(missing) > 1 else ''} "
                              f"{', '.join(repr(m) for m in missing)} missing; found {found}",
                        f"The header must name all of {', '.join(CSV_COLUMNS)} (units in the name)",
                        line=1, column=c)
    return names


def _did_you_mean(required: str, names: list):
    """A header name that is plainly ``required`` misspelt or in other units."""
    stem, unit = required.rsplit("_", 1)
    for name in names:
        if name.casefold() == required.casefold():
            return name, "names are case-sensitive"
    for name in names:
        if "_" not in name:
            continue
        nstem, nunit = name.rsplit("_", 1)
        if nstem.casefold() == stem.casefold() and nunit != unit:
            return name, "wrong units"
    return None


def _rename_hint(required: str, other: str, why: str) -> str:
    if why != "wrong units":
        return f"Did you mean {required!r}? Rename the column"
    if required in TEMPERATURE_COLUMNS:
        to = "degC (kelvin - 273.15)"
    else:
        to = _UNIT_NAMES[required]
    return f"Did you mean {required!r}? Convert the values to {to} and rename the column"


def _refuse_field_count(path, row, ncol, line_no, lines):
    n = len(row)
    problem = f"the row has {n} field{'s' if n != 1 else ''} but the header has {ncol}"
    text = lines[line_no - 1] if line_no - 1 < len(lines) else ""
    if n == 1 and ";" in text:
        hint = "Use comma separators and '.' as the decimal point"
    elif n > ncol:
        hint = ("A decimal comma splits numbers in two: use '.' as the decimal point; "
                "otherwise fix the row so it matches the header")
    elif line_no >= len(lines) or not any(line.strip() for line in lines[line_no:]):
        hint = "The last line looks truncated (file cut off while being written?): delete it"
    else:
        hint = "Fix or delete the row so it matches the header"
    raise DataError(path, problem, hint, line=line_no)


def _to_float(path, strings, column, row_lines) -> np.ndarray:
    try:
        return np.array(strings, dtype=np.float64)
    except ValueError:
        pass
    # Slow path only to locate the culprit for the message.
    for i, s in enumerate(strings):
        try:
            float(s)
        except ValueError:
            t = s.strip()
            if not t:
                raise DataError(path, "empty field", "Fill in a number or delete the row",
                                line=row_lines[i], column=column) from None
            if re.fullmatch(r"[+-]?\d+,\d*", t):
                hint = "Use '.' as the decimal point (and commas only between fields)"
            else:
                hint = "Every contract field must be a plain number ('.' decimal point)"
            raise DataError(path, f"{t!r} is not a number", hint,
                            line=row_lines[i], column=column) from None
    raise AssertionError("unreachable: numpy refused a column that float() accepts")


def _check_time(path, data, row_lines):
    t = data["time_s"]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if not bad.size:
        return
    i = int(bad[0]) + 1
    # A repeated sample (logger hiccup) reads better than "time not increasing".
    same_time = np.flatnonzero(t[:i] == t[i])
    for k in same_time[::-1]:
        if all(data[c][k] == data[c][i] for c in CSV_COLUMNS):
            raise DataError(path, f"duplicate row (same as line {row_lines[k]})",
                            "Delete the repeated row", line=row_lines[i], column="time_s")
    raise DataError(
        path,
        f"time is not strictly increasing: {t[i]:.10g} s on line {row_lines[i]} "
        f"after {t[i - 1]:.10g} s on line {row_lines[i - 1]}",
        "Sort the rows by time and remove repeated samples",
        line=row_lines[i], column="time_s",
    )


def _check_units(path, data, row_lines, imax):
    for c in TEMPERATURE_COLUMNS:
        med = float(np.median(data[c]))
        if med > _KELVIN_MEDIAN_C:
            raise DataError(path, f"values around {med:.2f} look like kelvin",
                            "Convert to degC (subtract 273.15)", column=c)
    for c in TEMPERATURE_COLUMNS:
        v = data[c]
        bad = np.flatnonzero((v < TEMP_MIN_C) | (v > TEMP_MAX_C))
        if bad.size:
            i = int(bad[0])
            raise DataError(path, f"{v[i]:.6g} degC is outside the plausible range "
                                  f"[{TEMP_MIN_C:g}, {TEMP_MAX_C:g}] degC",
                            "Check the sensor and the column (temperatures must be in degC); "
                            "fix or delete the row", line=row_lines[i], column=c)

    cur = np.abs(data["current_A"])
    i = int(np.argmax(cur))
    if imax is not None:
        imax = float(imax)
        if not imax > 0:
            raise ValueError(f"imax must be a positive current [A], got {imax!r}")
        limit, why = _MAX_CURRENT_IMAX * imax, f"more than {_MAX_CURRENT_IMAX:g} x Imax = {imax:g} A"
    else:
        limit, why = _MAX_CURRENT_A, f"more than {_MAX_CURRENT_A:g} A"
    if cur[i] > limit:
        raise DataError(path, f"|current| up to {cur[i]:.6g} ({why}) looks like mA",
                        "Convert to A (divide by 1000)", line=row_lines[i], column="current_A")

    volt = np.abs(data["voltage_V"])
    i = int(np.argmax(volt))
    if volt[i] > _MAX_VOLTAGE_V:
        raise DataError(path, f"|voltage| up to {volt[i]:.6g} (more than {_MAX_VOLTAGE_V:g} V) looks like mV",
                        "Convert to V (divide by 1000)", line=row_lines[i], column="voltage_V")
