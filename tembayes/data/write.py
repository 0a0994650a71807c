"""Atomic outputs: a reader never sees a half-written file or folder.

Everything here writes to a temporary sibling first and renames it into place
(``os.replace`` is atomic within one file system), so a crash or a refused
input leaves either the old output or nothing.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..constants import KELVIN
from ..errors import TembayesError
from .batch import Datasheet
from .experiment import Experiment, reference_layout
from .outputs import MARKER, marker, refuse_existing

if TYPE_CHECKING:
    from collections.abc import Iterator, Mapping

    from numpy.typing import ArrayLike

__all__ = [
    "atomic_write_text",
    "atomic_write_bytes",
    "write_json",
    "to_jsonable",
    "atomic_directory",
    "write_experiment_csv",
    "write_batch_toml",
    "experiment_from_arrays",
    "DEFAULT_DECIMALS",
]

#: Decimals written per column kind by :func:`write_experiment_csv`.
DEFAULT_DECIMALS = {"time_s": 3, "current_A": 5, "voltage_V": 5, "temperature": 4}
_MAX_TIME_DECIMALS = 9


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write_bytes(path: Path | str, data: bytes) -> Path:
    """Write bytes to ``path`` atomically (temp file in the same folder, then rename).

    Parameters
    ----------
    path : str or Path
        Target file; missing parent folders are created.
    data : bytes

    Returns
    -------
    Path
        The written path.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # mkstemp makes 0600 files; give the result the permissions a plain open() would.
    mode = path.stat().st_mode & 0o777 if path.exists() else 0o666 & ~_umask()
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def atomic_write_text(path: Path | str, text: str, encoding: str = "utf-8") -> Path:
    """Write text to ``path`` atomically (see :func:`atomic_write_bytes`).

    Parameters
    ----------
    path : str or Path
    text : str
    encoding : str, default "utf-8"

    Returns
    -------
    Path
    """
    return atomic_write_bytes(path, text.encode(encoding))


def to_jsonable(obj):
    """Convert numpy scalars/arrays, tuples, paths to plain JSON types.

    Non-finite floats (NaN, +-inf) become ``None`` (JSON ``null``), since
    strict JSON has no spelling for them.
    """
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return to_jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, (str, int, bool)) or obj is None:
        return obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"cannot write {type(obj).__name__} to JSON: {obj!r}")


def write_json(path: Path | str, obj: dict | list) -> Path:
    """Write ``obj`` as indented JSON, atomically.

    Parameters
    ----------
    path : str or Path
    obj : dict or list
        Plain Python, numpy scalars or arrays; NaN/inf are written as null.

    Returns
    -------
    Path
    """
    text = json.dumps(to_jsonable(obj), indent=2, allow_nan=False)
    return atomic_write_text(path, text + "\n")


@contextlib.contextmanager
def atomic_directory(path: Path | str, *, overwrite: bool = False, kind: str | None = None) -> Iterator[Path]:
    """Build a folder under a temporary name and rename it into place on success.

    Parameters
    ----------
    path : str or Path
        The final folder.
    overwrite : bool, default False
        Replace an existing ``path``; otherwise an existing ``path`` is
        refused (checked before and after the work).
    kind : str, optional
        The tembayes output kind (a command name,
        :data:`tembayes.data.outputs.KINDS`): an existing ``path`` is then
        replaced only if it is an output of that kind holding nothing else,
        and the new folder gets the marker naming its kind.

    Yields
    ------
    Path
        A temporary sibling folder ``.{name}.tmp-<random>`` to write into.

    Raises
    ------
    TembayesError
        When ``path`` may not be replaced.

    Notes
    -----
    On an exception inside the block the temporary folder is removed and
    ``path`` is left as it was.
    """
    path = Path(path)
    _refuse_existing(path, overwrite, kind)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.tmp-", dir=path.parent))
    try:
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes 0700
        yield tmp
        if kind is not None:
            atomic_write_text(tmp / MARKER, marker(kind, complete=True))
        _refuse_existing(path, overwrite, kind)  # someone may have created it meanwhile
        if path.exists() or path.is_symlink():
            # Move the old output aside first so the swap window is two renames.
            old = Path(tempfile.mkdtemp(prefix=f".{path.name}.old-", dir=path.parent))
            os.rmdir(old)
            os.replace(path, old)
            os.replace(tmp, path)
            if old.is_dir() and not old.is_symlink():
                shutil.rmtree(old, ignore_errors=True)
            else:
                old.unlink(missing_ok=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _refuse_existing(path: Path, overwrite: bool, kind) -> None:
    if kind is not None:
        refuse_existing(path, kind, overwrite)
    elif not overwrite and (path.exists() or path.is_symlink()):
        raise TembayesError(f"{path}: already exists. Choose another output or allow overwriting it")


def _column_data(exp: Experiment):
    """Contract columns in CSV units (degC for temperatures)."""
    cols = {
        "time_s": exp.time,
        "current_A": exp.current,
        "voltage_V": exp.voltage,
    }
    for i, c in enumerate(exp.sensor_names):
        cols[c] = exp.sensors[i] - KELVIN
    for i, c in enumerate(exp.boundary_names):
        cols[c] = exp.boundaries[i] - KELVIN
    return cols


def write_experiment_csv(
    path: Path | str, exp: Experiment, *, decimals: int | Mapping[str, int] | None = None, include_extra: bool = True
) -> Path:
    """Write an experiment as a contract CSV (degC), atomically.

    Parameters
    ----------
    path : str or Path
    exp : Experiment
    decimals : int or dict, optional
        Decimals per column.  Default: time 3, current 5, voltage 5,
        temperatures 4.  An int applies to all; a dict overrides by column
        name (``"time_s"``, ``"T3_C"``, ...) or ``"temperature"`` for all
        temperature columns.  Time decimals are raised automatically (up to
        9) when rounding would make two sample times equal.
    include_extra : bool, default True
        Also write the extra columns (full precision) after the contract ones.

    Returns
    -------
    Path

    Notes
    -----
    The result loads back with :func:`~tembayes.data.load_experiment` equal
    to ``exp`` within half a unit of the last written decimal.
    """
    cols = _column_data(exp)
    columns = exp.columns
    dec = _decimals(decimals, columns)
    t_dec = dec["time_s"]
    # Rounding must not break "strictly increasing" or the file would be refused.
    while t_dec < _MAX_TIME_DECIMALS and np.any(np.diff(np.round(exp.time, t_dec)) <= 0):
        t_dec += 1
    dec["time_s"] = t_dec
    names = list(columns)
    fmts = [f"%.{dec[c]}f" for c in columns]
    # Round first and add +0.0 so tiny negatives print as "0.000", not "-0.000".
    arrays = [np.round(cols[c], dec[c]) + 0.0 for c in columns]
    if include_extra:
        for name, values in exp.extra.items():
            names.append(name)
            fmts.append("%.17g")
            arrays.append(values)
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack(arrays), fmt=fmts, delimiter=",", header=",".join(names), comments="")
    return atomic_write_text(path, buf.getvalue())


def _decimals(decimals, columns) -> dict:
    dec = {}
    base = dict(DEFAULT_DECIMALS)
    if isinstance(decimals, int):
        base = {k: decimals for k in base}
        decimals = {}
    decimals = dict(decimals or {})
    for k in decimals:
        if k not in columns and k != "temperature":
            raise ValueError(f"decimals: unknown column {k!r}; use a contract column name or 'temperature'")
    for c in columns:
        kind = c if c in base else "temperature"
        dec[c] = int(decimals.get(c, decimals.get(kind, base[kind])))
    return dec


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))  # 'inf'/'nan'/'1e-05' are all valid TOML floats
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a valid TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, os.PathLike):
        return json.dumps(os.fspath(v))
    raise TypeError(f"cannot write {type(v).__name__} to TOML: {v!r}")


def _toml_key(k: str) -> str:
    k = str(k)
    return k if k and all(ch.isalnum() or ch in "_-" for ch in k) and k.isascii() else json.dumps(k)


def _toml_table(lines: list, name: str, table: dict) -> None:
    lines.append(f"[{name}]")
    subtables = []
    for k, v in table.items():
        if isinstance(v, dict):
            subtables.append((k, v))
        else:
            lines.append(f"{_toml_key(k)} = {_toml_value(v)}")
    for k, v in subtables:
        lines.append("")
        _toml_table(lines, f"{name}.{_toml_key(k)}", v)


def write_batch_toml(path: Path | str, datasheet: Datasheet, rig_config: Mapping | None = None) -> Path:
    """Write ``batch.toml`` (``docs/data-format.md``, 'batch.toml'), atomically.

    Parameters
    ----------
    path : str or Path
        The ``batch.toml`` file, or a batch folder to write it into.
    datasheet : Datasheet
        Written as ``[module_type]`` in contract units (th_C in degC).
    rig_config : dict, optional
        Written as ``[rig]`` (nested dicts become sub-tables); omitted when
        None, which means the reference rig.

    Returns
    -------
    Path
        The written file.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "batch.toml"
    lines = []
    _toml_table(lines, "module_type", datasheet.to_table())
    if rig_config is not None:
        lines.append("")
        _toml_table(lines, "rig", dict(rig_config))
    return atomic_write_text(path, "\n".join(lines) + "\n")


def experiment_from_arrays(
    time: ArrayLike,
    current: ArrayLike,
    voltage: ArrayLike,
    sensors_K: ArrayLike,
    boundaries_K: ArrayLike,
    path: Path | str | None = None,
    extra: Mapping[str, ArrayLike] | None = None,
    *,
    sensor_names: tuple | None = None,
    boundary_names: tuple | None = None,
) -> Experiment:
    """Build an :class:`Experiment` from SI arrays, checking shapes and values.

    Parameters
    ----------
    time : array_like, shape (n,)
        Sample times [s], strictly increasing.
    current : array_like, shape (n,)
        Module current [A].
    voltage : array_like, shape (n,)
        Module voltage [V].
    sensors_K : array_like, shape (ns, n)
        Sensor temperatures [K], in the order of ``sensor_names``.
    boundaries_K : array_like, shape (nb, n)
        Boundary temperatures [K], in the order of ``boundary_names``.
    path : str or Path, optional
        Where the data belongs (default ``<in-memory>``).
    extra : dict, optional
        Further columns, each shape (n,).
    sensor_names, boundary_names : tuple of str, optional
        Their CSV columns (default: the reference rig's).

    Returns
    -------
    Experiment

    Raises
    ------
    ValueError
        Wrong shapes (expected vs found), fewer than 2 samples, non-finite
        values or time not strictly increasing.
    """
    time = np.asarray(time, dtype=np.float64)
    if time.ndim != 1:
        raise ValueError(f"time: expected shape (n,), found {time.shape}")
    n = time.shape[0]
    if n < 2:
        raise ValueError(f"time: expected at least 2 samples, found {n}")
    arrays = {"current": current, "voltage": voltage}
    for name, a in arrays.items():
        shape = np.shape(a)
        if shape != (n,):
            raise ValueError(f"{name}: expected shape ({n},) like time, found {shape}")
    boundaries_K = np.atleast_2d(np.asarray(boundaries_K, dtype=np.float64))
    if sensor_names is None or boundary_names is None:
        ref = reference_layout()
        sensor_names = ref.sensors if sensor_names is None else sensor_names
        boundary_names = ref.boundaries if boundary_names is None else boundary_names
    for name, a, names in (("sensors_K", sensors_K, sensor_names), ("boundaries_K", boundaries_K, boundary_names)):
        if np.shape(a) != (len(names), n):
            raise ValueError(f"{name}: expected shape ({len(names)}, {n}) for {', '.join(names)}, found {np.shape(a)}")
    for name, a in {"time": time, "sensors_K": sensors_K, "boundaries_K": boundaries_K, **arrays}.items():
        if not np.all(np.isfinite(np.asarray(a, dtype=np.float64))):
            raise ValueError(f"{name}: contains NaN or inf")
    if np.any(np.diff(time) <= 0):
        i = int(np.flatnonzero(np.diff(time) <= 0)[0]) + 1
        raise ValueError(f"time: not strictly increasing at index {i} ({time[i]} s after {time[i - 1]} s)")
    return Experiment(
        path=path,
        time=time,
        current=current,
        voltage=voltage,
        sensors=sensors_K,
        boundaries=boundaries_K,
        sensor_names=sensor_names,
        boundary_names=boundary_names,
        extra=dict(extra or {}),
    )
