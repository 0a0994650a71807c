"""``protocol.csv``: an identification run's current program (``docs/design.md``).

Columns ``time_s,current_A``, one row per change of level: the level of a
row holds from its time until the next row's, and the last row ends the run
(its current is not applied).  The first row is at 0 s.  On a rig whose
plates hold both module faces a third column, ``plate_C``, gives the plates'
setpoint [degC] during each hold (the last row's, like its current, is not applied).
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np

from tembayes.bench.protocols import Protocol
from tembayes.constants import KELVIN
from tembayes.data.write import atomic_write_text
from tembayes.errors import DataError

COLUMNS = ("time_s", "current_A")
#: The optional third column: the setpoint of plates that hold both faces [degC].
SETPOINT = "plate_C"
#: The shortest hold a protocol may ask for [s], as ``simulate --hold``: a step window needs its samples.
MIN_HOLD_S = 30.0


def _rows(path):
    """``[(line, {column: text})]`` of a protocol file, its header checked."""
    try:
        text = Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise DataError(path, "the file does not exist", "Check the path of the protocol file") from None
    except (IsADirectoryError, UnicodeDecodeError) as exc:
        raise DataError(path, f"cannot be read as a text CSV ({exc.__class__.__name__})", "Pass protocol.csv") from None
    reader = csv.DictReader(io.StringIO(text))
    header = tuple(h.strip() for h in (reader.fieldnames or ()))
    if header not in (COLUMNS, (*COLUMNS, SETPOINT)):
        raise DataError(
            path,
            f"the header is {','.join(header) or '(empty)'}",
            f"The header must be exactly time_s,current_A (or time_s,current_A,{SETPOINT} on plates that hold "
            "both faces)",
            line=1,
        )
    reader.fieldnames = list(header)  # "time_s, current_A" reads as the columns it names
    return [(k + 2, row) for k, row in enumerate(reader)]


def _number(path, line, column, text):
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise DataError(
            path, f"'{text}' is not a number", "Write a plain decimal number", line=line, column=column
        ) from None
    if not np.isfinite(v):
        raise DataError(path, f"'{text}' is not finite", "Write a finite number", line=line, column=column)
    return v


def read_protocol(path: Path | str, *, imax: float | None = None) -> Protocol:
    """Read ``protocol.csv`` into a :class:`~tembayes.bench.protocols.Protocol`.

    Parameters
    ----------
    path : str or Path
    imax : float, optional
        The module type's Imax [A]; a level beyond it is refused.

    Raises
    ------
    DataError
        Naming the file, the line and the column: a wrong header, fewer than
        two rows, a value that is not a finite number, a first time other
        than 0, times not increasing by at least :data:`MIN_HOLD_S`, a level
        beyond ``imax``, a plate setpoint below absolute zero.
    """
    rows = _rows(path)
    if len(rows) < 2:
        raise DataError(path, f"{len(rows)} data rows", "A protocol needs a level and the row that ends the run")
    t = np.array([_number(path, ln, "time_s", r["time_s"]) for ln, r in rows])
    i = np.array([_number(path, ln, "current_A", r["current_A"]) for ln, r in rows])
    if t[0] != 0.0:
        raise DataError(
            path, f"the first time is {t[0]:g} s", "The program starts at time_s 0", line=2, column="time_s"
        )
    short = np.flatnonzero(np.diff(t) < MIN_HOLD_S)
    if len(short):
        k = int(short[0]) + 1
        raise DataError(
            path,
            f"time_s {t[k]:g} follows {t[k - 1]:g}: a hold of {t[k] - t[k - 1]:g} s",
            f"Times must increase by at least {MIN_HOLD_S:g} s from row to row",
            line=rows[k][0],
            column="time_s",
        )
    if imax is not None:
        over = np.flatnonzero(np.abs(i[:-1]) > imax)
        if len(over):
            k = int(over[0])
            raise DataError(
                path,
                f"current_A {i[k]:g} exceeds the module type's Imax {imax:g} A",
                "Keep every level within the datasheet's Imax",
                line=rows[k][0],
                column="current_A",
            )
    setpoints = None
    if SETPOINT in rows[0][1]:
        c = np.array([_number(path, ln, SETPOINT, r[SETPOINT]) for ln, r in rows[:-1]])
        cold = np.flatnonzero(c <= -KELVIN)
        if len(cold):
            raise DataError(
                path, f"{SETPOINT} {c[cold[0]]:g} is not above absolute zero", "Write the plates' setpoint in degC",
                line=rows[int(cold[0])][0], column=SETPOINT,
            )  # fmt: skip
        setpoints = c + KELVIN
    return Protocol(levels=i[:-1], durations=np.diff(t), setpoints=setpoints)


def protocol_text(protocol: Protocol) -> str:
    """The ``protocol.csv`` text of a protocol (times to the ms, currents to the µA, setpoints to the mK)."""
    t = protocol.edges
    i = np.concatenate([protocol.levels, [0.0]])
    if protocol.setpoints is None:
        return "time_s,current_A\n" + "".join(f"{a:.3f},{b:.6f}\n" for a, b in zip(t, i))
    c = np.asarray(protocol.setpoints) - KELVIN
    c = np.concatenate([c, c[-1:]])  # the ending row's setpoint is not applied either
    return f"time_s,current_A,{SETPOINT}\n" + "".join(f"{a:.3f},{b:.6f},{v:.3f}\n" for a, b, v in zip(t, i, c))


def write_protocol(path: Path | str, protocol: Protocol) -> Path:
    """Write ``protocol.csv`` atomically; the last row (0 A) ends the run."""
    return atomic_write_text(path, protocol_text(protocol))
