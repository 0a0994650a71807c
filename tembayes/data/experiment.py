"""One experiment CSV (``docs/data-format.md``, 'CSV columns'): loading, validation, SI arrays.

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
from typing import TYPE_CHECKING

import numpy as np

from ..constants import BASE_COLUMNS, KELVIN
from ..errors import DataError

if TYPE_CHECKING:  # batch.py imports this module
    from ..physics.layout import Layout
    from .batch import Datasheet

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
    sensors : ndarray, shape (ns, n)
        The rig's sensor temperatures [K], in the order of ``sensor_names``.
    boundaries : ndarray, shape (nb, n)
        The rig's measured boundary temperatures [K], in the order of
        ``boundary_names`` (the rig's boundary order).
    sensor_names, boundary_names : tuple of str
        Their CSV columns; default: the reference rig's.
    extra : dict of str to ndarray
        Other numeric columns of the file, as written (unit unknown); kept,
        not used.
    lines : ndarray of int, shape (n,), optional
        The file line of each sample (header = line 1), for messages; None
        for data made in memory.

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
    boundaries: np.ndarray
    sensor_names: tuple | None = None
    boundary_names: tuple | None = None
    extra: dict = field(default_factory=dict)
    lines: np.ndarray | None = None

    def __post_init__(self):
        set_ = object.__setattr__  # frozen dataclass: the only way to normalise
        set_(self, "path", _IN_MEMORY if self.path is None else Path(self.path))
        n = None
        for name in ("time", "current", "voltage"):
            arr = _frozen(getattr(self, name))
            if arr.ndim != 1:
                raise ValueError(f"Experiment.{name}: expected shape (n,), found {arr.shape}")
            if n is None:
                n = arr.shape[0]
            elif arr.shape[0] != n:
                raise ValueError(f"Experiment.{name}: expected shape ({n},) like time, found {arr.shape}")
            set_(self, name, arr)
        if self.sensor_names is None or self.boundary_names is None:
            layout = reference_layout()
            set_(self, "sensor_names", layout.sensors if self.sensor_names is None else self.sensor_names)
            set_(self, "boundary_names", layout.boundaries if self.boundary_names is None else self.boundary_names)
        for name, names in (("sensors", "sensor_names"), ("boundaries", "boundary_names")):
            set_(self, names, tuple(str(c) for c in getattr(self, names)))
            arr = _frozen(getattr(self, name))
            k = len(getattr(self, names))
            if arr.shape != (k, n):
                raise ValueError(f"Experiment.{name}: expected shape ({k}, {n}), found {arr.shape}")
            set_(self, name, arr)
        extra = {}
        for key, value in dict(self.extra or {}).items():
            arr = _frozen(value)
            if arr.shape != (n,):
                raise ValueError(f"Experiment.extra[{key!r}]: expected shape ({n},), found {arr.shape}")
            extra[str(key)] = arr
        set_(self, "extra", extra)
        if self.lines is not None:
            lines = np.asarray(self.lines, dtype=np.int64)
            if lines.shape != (n,):
                raise ValueError(f"Experiment.lines: expected shape ({n},), found {lines.shape}")
            lines.setflags(write=False)
            set_(self, "lines", lines)

    def where(self, i: int) -> str:
        """Sample ``i`` for a message: ``"line 1234 (t = 567.8 s)"``, or ``"sample 1232 (...)"`` in memory."""
        at = f"line {int(self.lines[i])}" if self.lines is not None else f"sample {int(i)}"
        return f"{at} (t = {self.time[i]:.6g} s)"

    def line(self, i: int) -> int | None:
        """The file line of sample ``i`` (None for data made in memory)."""
        return None if self.lines is None else int(self.lines[i])

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
            ``"voltage_V"``, a sensor or boundary column of the rig) or the
            name of an extra column.

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
        if name in self.sensor_names:
            return self.sensors[self.sensor_names.index(name)]
        if name in self.boundary_names:
            return self.boundaries[self.boundary_names.index(name)]
        if name in self.extra:
            return self.extra[name]
        known = ", ".join(self.columns + tuple(self.extra))
        raise KeyError(f"no channel {name!r} in {self.path}; known: {known}")

    @property
    def columns(self) -> tuple[str, ...]:
        """The contract columns of this experiment: time, current, voltage, then its rig's temperatures."""
        return BASE_COLUMNS + self.sensor_names + self.boundary_names

    def __repr__(self):
        return (
            f"Experiment(path={str(self.path)!r}, n={self.n}, duration={self.duration:.6g} s, extra={list(self.extra)})"
        )


def reference_layout() -> Layout:
    """The reference rig's :class:`~tembayes.physics.layout.Layout`: the columns when no rig is named."""
    from ..physics.rigread import REFERENCE  # lazy: physics is heavier than data

    return REFERENCE.layout


def _frozen(values) -> np.ndarray:
    if (
        isinstance(values, np.ndarray)
        and values.dtype == np.float64
        and values.base is None
        and values.flags.c_contiguous
        and values.flags.owndata
        and not values.flags.writeable
    ):
        return values  # already private and read-only (the loader's own arrays): no second copy
    arr = np.array(values, dtype=np.float64)  # a private copy
    arr.setflags(write=False)
    return arr


# --------------------------------------------------------------------------
# loading

#: Bytes of data rows parsed at a time: memory stays bounded for any file size.
_CHUNK_BYTES = 8 << 20


def load_experiment(
    path: Path | str, *, datasheet: Datasheet | None = None, layout: Layout | None = None
) -> Experiment:
    """Load and validate one experiment CSV (``docs/data-format.md``, 'CSV columns').

    Parameters
    ----------
    path : str or Path
        The CSV file: one header row, comma separators, ``.`` decimal point,
        the contract columns in any order, further columns allowed.
    datasheet : tembayes.data.Datasheet, optional
        The module type.  When given, a current above 3 x its Imax is
        refused as milliamperes (otherwise above 100 A), and a file whose
        Seebeck voltage per kelvin is 1.8 times too small is refused as degF.
    layout : tembayes.physics.layout.Layout, optional
        The batch's rig (its sensor and boundary columns); default the
        reference rig.

    Returns
    -------
    Experiment
        SI arrays (temperatures in kelvin).  Numeric extra columns are kept
        in ``extra``; non-numeric ones are dropped.  ``lines`` holds each
        sample's line in the file.

    Raises
    ------
    DataError
        For anything that breaks the contract; the message names the file,
        the line (header = line 1) and/or column, and what to do.

    Notes
    -----
    The rows are parsed in blocks of a few megabytes, so memory is the
    arrays' size plus a constant, whatever the file's size.
    """
    path = Path(path)
    layout = layout or reference_layout()
    columns = layout.csv_columns
    _check_file(path)
    with path.open("rb") as f:
        first = f.readline()
        if b"\x00" in first:
            raise DataError(
                path, "the file is binary, not a text CSV", "Export the experiment as plain CSV text", line=1
            )
        header = _decode(first).rstrip("\r\n")
        if not header.strip():
            raise DataError(
                path,
                "line 1 is empty, but the header row must be line 1",
                f"Put the column names {', '.join(columns)} on line 1",
                line=1,
            )
        table = _Table(path, _check_header(path, next(csv.reader([header])), columns), columns)
        line_no = 1
        while block := f.readlines(_CHUNK_BYTES):
            table.add(block, line_no + 1, last=not f.peek(1))
            line_no += len(block)
    data, extra, row_lines = table.result()

    _check_time(path, data, row_lines)
    _check_units(path, data, row_lines, datasheet, layout)

    sensors = np.stack([data.pop(c) for c in layout.sensors])
    boundaries = np.stack([data.pop(c) for c in layout.boundaries])
    sensors += KELVIN
    boundaries += KELVIN
    for arr in (sensors, boundaries, *data.values(), *extra.values()):
        arr.setflags(write=False)  # handed over, not copied again
    return Experiment(
        path=path,
        time=data["time_s"],
        current=data["current_A"],
        voltage=data["voltage_V"],
        sensors=sensors,
        boundaries=boundaries,
        sensor_names=layout.sensors,
        boundary_names=layout.boundaries,
        extra=extra,
        lines=row_lines,
    )


def _check_file(path: Path) -> None:
    """Refuse a missing, unreadable, empty or whitespace-only file before parsing."""
    if not path.exists():
        raise DataError(path, "the file does not exist", "Check the path (and the batch folder layout)")
    if path.is_dir():
        raise DataError(path, "this is a folder, not a CSV file", "Pass the experiment's .csv file")
    try:
        with path.open("rb") as f:
            head = f.read(1 << 16)
            if b"\x00" in head:  # the rest is checked block by block while parsing
                raise DataError(
                    path,
                    "the file is binary, not a text CSV",
                    "Export the experiment as plain CSV text",
                    line=head[: head.index(b"\x00")].count(b"\n") + 1,
                )
            piece = head
            while piece:
                if piece.strip():
                    return
                piece = f.read(1 << 16)
    except OSError as e:
        raise DataError(path, f"the file cannot be read ({e.strerror or e})", "Check the file's permissions") from None
    raise DataError(
        path,
        "the file is empty",
        "Export the experiment again: a CSV needs a header row and data rows (docs/data-format.md, 'CSV columns')",
    )


def _decode(raw: bytes) -> str:
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        # Spreadsheet exports in a legacy code page (e.g. a degree sign in an
        # extra column name): the contract's own content is ASCII anyway.
        return raw.decode("cp1252", errors="replace")


class _Table:
    """The data rows of one CSV, parsed block by block into float columns.

    A block goes through numpy's C parser; a block it refuses (or that holds
    quotes or a wrong field count) is read again field by field, which finds
    the first bad row for the message.
    """

    def __init__(self, path, names, columns):
        self.path = path
        self.columns = columns
        self.ncol = len(names)
        index = {name: j for j, name in enumerate(names)}
        self.contract = [index[c] for c in columns]
        self.extra = {j: name for j, name in enumerate(names) if name and name not in columns}
        self.parts, self.line_parts = [], []
        self.extra_parts = {j: [] for j in self.extra}  # None once a column shows a non-number

    def add(self, block, first_line, *, last):
        """Parse ``block`` (raw lines, the first is file line ``first_line``; ``last``: nothing follows)."""
        lines, numbers = [], []
        for k, raw in enumerate(block):
            if b"\x00" in raw:
                raise DataError(
                    self.path,
                    "the file is binary, not a text CSV",
                    "Export the experiment as plain CSV text",
                    line=first_line + k,
                )
            text = raw.decode("utf-8", errors="replace").rstrip("\r\n")
            if text.strip():  # blank lines carry nothing; tolerate them
                lines.append(text)
                numbers.append(first_line + k)
        if not lines:
            return
        numbers = np.asarray(numbers, dtype=np.int64)
        values = self._fast(lines)
        if values is None:
            values = self._slow(lines, numbers, last)
        self._check_finite(values, lines, numbers)
        self.parts.append(values)
        self.line_parts.append(numbers)
        for j, parts in self.extra_parts.items():
            if parts is not None:
                col = self._extra_column(lines, j)
                self.extra_parts[j] = None if col is None else parts + [col]

    def _fast(self, lines):
        if any('"' in s or s.count(",") != self.ncol - 1 for s in lines):
            return None
        try:
            return np.loadtxt(lines, delimiter=",", dtype=np.float64, ndmin=2, comments=None, usecols=self.contract)
        except ValueError:
            return None

    def _slow(self, lines, numbers, last):
        rows = list(csv.reader(lines))
        for k, row in enumerate(rows):
            if len(row) != self.ncol:
                _refuse_field_count(
                    self.path, row, self.ncol, int(numbers[k]), lines[k], trailing=last and k == len(rows) - 1
                )
        cols = list(zip(*rows))
        return np.column_stack([_to_float(self.path, cols[j], c, numbers) for j, c in zip(self.contract, self.columns)])

    @staticmethod
    def _extra_column(lines, j):
        try:
            if any('"' in s for s in lines):
                return np.array([row[j] for row in csv.reader(lines)], dtype=np.float64)
            return np.loadtxt(lines, delimiter=",", dtype=np.float64, ndmin=1, comments=None, usecols=j)
        except (ValueError, IndexError):
            return None

    def _check_finite(self, values, lines, numbers):
        bad = np.argwhere(~np.isfinite(values))
        if bad.size:
            k, c = (int(x) for x in bad[0])
            field = next(csv.reader([lines[k]]))[self.contract[c]].strip()
            raise DataError(
                self.path,
                f"{field!r} is not a finite number",
                "Every field of the required columns (docs/data-format.md, 'CSV columns') needs a "
                "finite number: fill the gap or delete the row",
                line=int(numbers[k]),
                column=self.columns[c],
            )

    def result(self):
        """``(contract columns, numeric extra columns, line of each row)``; refuses fewer than 2 rows."""
        n = sum(len(p) for p in self.parts)
        if n == 0:
            raise DataError(
                self.path,
                "the file has a header but no data rows",
                "Export the experiment again with its samples",
                line=1,
            )
        row_lines = np.concatenate(self.line_parts)
        if n < 2:
            raise DataError(
                self.path,
                "the file has only 1 data row; at least 2 are needed",
                "Export the whole experiment",
                line=int(row_lines[0]),
            )
        values = np.concatenate(self.parts)
        self.parts = []
        data = {c: np.ascontiguousarray(values[:, k]) for k, c in enumerate(self.columns)}
        extra = {self.extra[j]: np.concatenate(p) for j, p in self.extra_parts.items() if p}
        return data, extra, row_lines


def _check_header(path: Path, header: list, columns: tuple) -> list:
    names = [h.strip() for h in header]
    if not any(names):
        raise DataError(
            path,
            "line 1 is empty, but the header row must be line 1",
            f"Put the column names {', '.join(columns)} on line 1",
            line=1,
        )
    if len(names) == 1:
        for sep, label in ((";", "semicolon"), ("\t", "tab")):
            if sep in names[0]:
                raise DataError(
                    path,
                    f"the header uses {label} separators",
                    "Use comma separators and '.' as the decimal point (e.g. re-export as 'CSV (comma delimited)')",
                    line=1,
                )
    seen = {}
    for name in names:
        if name and name in seen:
            raise DataError(
                path, f"column {name!r} appears twice in the header", "Keep one column per name", line=1, column=name
            )
        seen[name] = True
    missing = [c for c in columns if c not in seen]
    if missing:
        c = missing[0]
        guess = _did_you_mean(c, names)
        if guess is not None:
            other, why = guess
            raise DataError(
                path,
                f"required column {c!r} is missing, but there is {other!r} ({why})",
                _rename_hint(c, other, why),
                line=1,
                column=c,
            )
        found = ", ".join(repr(n) for n in names)
        raise DataError(
            path,
            f"required column{'s' if len(missing) > 1 else ''} "
            f"{', '.join(repr(m) for m in missing)} missing; found {found}",
            f"The header must name all of {', '.join(columns)} (units in the name)",
            line=1,
            column=c,
        )
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
    if required.endswith("_C"):
        to = "degC (kelvin - 273.15)"
    else:
        to = _UNIT_NAMES[required]
    return f"Did you mean {required!r}? Convert the values to {to} and rename the column"


def _refuse_field_count(path, row, ncol, line_no, text, *, trailing):
    n = len(row)
    problem = f"the row has {n} field{'s' if n != 1 else ''} but the header has {ncol}"
    if n == 1 and ";" in text:
        hint = "Use comma separators and '.' as the decimal point"
    elif n > ncol:
        hint = (
            "A decimal comma splits numbers in two: use '.' as the decimal point; "
            "otherwise fix the row so it matches the header"
        )
    elif trailing:
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
                raise DataError(
                    path, "empty field", "Fill in a number or delete the row", line=row_lines[i], column=column
                ) from None
            if re.fullmatch(r"[+-]?\d+,\d*", t):
                hint = "Use '.' as the decimal point (and commas only between fields)"
            else:
                hint = (
                    "Every field of the required columns must be a plain number ('.' decimal point; "
                    "docs/data-format.md, 'CSV columns')"
                )
            raise DataError(path, f"{t!r} is not a number", hint, line=row_lines[i], column=column) from None
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
        if all(v[k] == v[i] for v in data.values()):
            raise DataError(
                path,
                f"duplicate row (same as line {row_lines[k]})",
                "Delete the repeated row",
                line=row_lines[i],
                column="time_s",
            )
    raise DataError(
        path,
        f"time is not strictly increasing: {t[i]:.10g} s on line {row_lines[i]} "
        f"after {t[i - 1]:.10g} s on line {row_lines[i - 1]}",
        "Sort the rows by time and remove repeated samples",
        line=row_lines[i],
        column="time_s",
    )


def _check_units(path, data, row_lines, datasheet, layout):
    for c in layout.temperatures:
        med = float(np.median(data[c]))
        if med > _KELVIN_MEDIAN_C:
            raise DataError(
                path, f"values around {med:.2f} look like kelvin", "Convert to degC (subtract 273.15)", column=c
            )
    for c in layout.temperatures:
        v = data[c]
        bad = np.flatnonzero((v < TEMP_MIN_C) | (v > TEMP_MAX_C))
        if bad.size:
            _refuse_degf(path, data, datasheet, layout)
            i = int(bad[0])
            raise DataError(
                path,
                f"{v[i]:.6g} degC is outside the plausible range [{TEMP_MIN_C:g}, {TEMP_MAX_C:g}] degC",
                "Check the sensor and the column (temperatures must be in degC, not degF); fix or delete the row",
                line=row_lines[i],
                column=c,
            )

    cur = np.abs(data["current_A"])
    i = int(np.argmax(cur))
    if datasheet is not None:
        imax = float(datasheet.imax)
        if not imax > 0:
            raise ValueError(f"datasheet.imax must be a positive current [A], got {imax!r}")
        limit, why = _MAX_CURRENT_IMAX * imax, f"more than {_MAX_CURRENT_IMAX:g} x Imax = {imax:g} A"
    else:
        limit, why = _MAX_CURRENT_A, f"more than {_MAX_CURRENT_A:g} A"
    if cur[i] > limit:
        raise DataError(
            path,
            f"|current| up to {cur[i]:.6g} ({why}) looks like mA",
            "Convert to A (divide by 1000)",
            line=row_lines[i],
            column="current_A",
        )

    volt = np.abs(data["voltage_V"])
    i = int(np.argmax(volt))
    if volt[i] > _MAX_VOLTAGE_V:
        raise DataError(
            path,
            f"|voltage| up to {volt[i]:.6g} (more than {_MAX_VOLTAGE_V:g} V) looks like mV",
            "Convert to V (divide by 1000)",
            line=row_lines[i],
            column="voltage_V",
        )
    if datasheet is not None:
        _refuse_degf(path, data, datasheet, layout)


def _refuse_degf(path, data, datasheet, layout):
    """Refuse a file in degF when its physics says so (see :func:`tembayes.data.preflight.degf_evidence`)."""
    from .preflight import degf_evidence  # the physics of the data lives there

    why = (
        None
        if datasheet is None
        else degf_evidence(
            data["current_A"], data["voltage_V"], {c: data[c] for c in layout.temperatures}, datasheet, layout.face
        )
    )
    if why:
        raise DataError(
            path,
            f"the temperatures look like degF: {why}",
            "Convert every temperature column to degC ((F - 32) / 1.8)",
            column=layout.temperatures[0],
        )
