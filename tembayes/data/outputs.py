"""Where results go: checks that run before any work, so nothing a user has is lost.

Every command's output is checked up front (:func:`check_output`):

- it must not be an input, hold an input, or lie inside a batch folder;
- an existing output is replaced only with ``--overwrite``, only if it is a
  tembayes output of the same kind (:func:`output_kind`), and only if it
  holds nothing tembayes did not write there;
- a folder output must not be a file (and a file output not a folder), its
  folder must be writable and hold enough free space.

Outputs are then built beside the target and swapped in when complete
(:func:`~tembayes.data.write.atomic_directory`, or the calibration run
folder), with a marker file naming their kind.
"""

from __future__ import annotations

import contextlib
import fnmatch
import json
import os
import shutil
import socket
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from ..errors import DataError, TembayesError

if TYPE_CHECKING:
    from collections.abc import Iterable

__all__ = [
    "MARKER",
    "KINDS",
    "OutputKind",
    "output_kind",
    "check_output",
    "refuse_existing",
    "foreign_entries",
    "marker",
    "RunLock",
    "LockHeld",
]

#: The marker file every tembayes output folder holds: ``{"kind": ..., "complete": ...}``.
MARKER = ".tembayes-output.json"


@dataclass(frozen=True)
class OutputKind:
    """What one command writes.

    Attributes
    ----------
    name : str
        The command.
    signature : tuple of tuple of str
        Glob patterns that identify an output of this kind written before
        markers existed: all of one of the tuples must match.
    entries : tuple of str
        Glob patterns of the top-level entries it writes (others are foreign).
    is_file : bool
        A single file (``export``), not a folder.
    """

    name: str
    signature: tuple
    entries: tuple
    is_file: bool = False


KINDS = {
    k.name: k
    for k in (
        OutputKind(
            "calibrate",
            (("summary.json",), ("modules/*.nc",)),
            ("summary.json", "posterior.nc", "modules", "checkpoints", "figures"),
        ),
        OutputKind("identify", (("identify.json",),), ("identify.json", "*.png")),
        OutputKind("predict", (("metrics.json",),), ("metrics.json", "*.png")),
        OutputKind("gap", (("gap.json",),), ("gap.json", "*.png", "run")),
        OutputKind("report", (("report.html",),), ("report.html", "report.json")),
        OutputKind("simulate", (("truth.json", "batch.toml"),), ("truth.json", "batch.toml", "*/")),
        OutputKind("export", (), (), is_file=True),
        OutputKind("rig", (("rig.json",),), ("rig.json", "rig.png")),
        OutputKind("design", (("design.json",),), ("design.json", "protocol.csv", "design.png")),
    )
}

#: Bytes of free space a command needs at least, before any work.
MIN_FREE_BYTES = 20 << 20


def marker(kind: str, **info) -> str:
    """The marker file's text for an output of ``kind``."""
    import tembayes

    return json.dumps({"kind": kind, "tembayes_version": tembayes.__version__, **info}, indent=2) + "\n"


def output_kind(path: Path | str) -> str | None:
    """The kind of tembayes output ``path`` is (a command name), or None.

    A folder with a marker says its kind; an older folder is recognised by
    its signature files; an export file by its schema key.
    """
    path = Path(path)
    if path.is_dir():
        m = path / MARKER
        if m.is_file():
            with contextlib.suppress(OSError, ValueError):
                return json.loads(m.read_text()).get("kind")
        for k in KINDS.values():
            if any(all(any(path.glob(g)) for g in alt) for alt in k.signature):
                return k.name
        return None
    if path.is_file():
        from ..export.formats import is_export_file  # lazy: the export stage is heavier than data

        return "export" if is_export_file(path) else None
    return None


def foreign_entries(path: Path | str, kind: str) -> list:
    """Top-level entries of an output folder that its kind does not write (a user's files)."""
    k = KINDS[kind]
    out = []
    for p in sorted(Path(path).iterdir()):
        name = p.name + ("/" if p.is_dir() else "")
        if p.name == MARKER:
            continue
        if not any(fnmatch.fnmatchcase(name, pat) or fnmatch.fnmatchcase(p.name, pat) for pat in k.entries):
            out.append(p.name)
        elif kind == "simulate" and p.is_dir():
            out += [
                f"{p.name}/{q.name}"
                for q in sorted(p.iterdir())
                if not fnmatch.fnmatchcase(q.name, "identification.csv")
                and not fnmatch.fnmatchcase(q.name, "validation*.csv")
            ]
    return out


def _resolved(p) -> Path:
    return Path(os.path.abspath(os.path.expanduser(p))).resolve(strict=False)


def _refuse_overlap(out, inputs):
    o = _resolved(out)
    for path, role in inputs:
        i = _resolved(path)
        if o == i:
            raise DataError(out, f"the output is the {role} itself", "Choose another --out: inputs are never replaced")
        if o in i.parents:
            raise DataError(
                out,
                f"the output holds the {role} ({path})",
                "Choose an --out outside the inputs: replacing it would delete them",
            )
        if role == "batch folder" and i in o.parents:
            raise DataError(
                out,
                f"the output lies inside the batch folder {path}",
                "Choose an --out outside the batch folder (a batch folder holds only batch.toml and module folders)",
            )


def refuse_existing(out: Path | str, kind: str, overwrite: bool) -> None:
    """Refuse replacing ``out`` unless allowed, of the same ``kind`` and holding only that kind's files."""
    out = Path(out)
    k = KINDS[kind]
    if out.is_symlink() and not out.exists():
        raise DataError(out, "the output is a broken symbolic link", "Remove it or choose another --out")
    if not out.exists():
        return
    if k.is_file:
        if out.is_dir():
            raise DataError(
                out,
                "the output is a folder, but this command writes a file",
                "Give a file name with --out, e.g. --out runs/x.mat",
            )
    else:
        if not out.is_dir():
            raise DataError(
                out,
                "the output is a file, but this command writes a folder",
                "Choose another --out (a folder that does not exist yet)",
            )
        if not any(out.iterdir()):
            return  # an empty folder: nothing to lose
    if not overwrite:
        raise DataError(out, "already exists", "Choose another --out, or add --overwrite to replace it")
    found = output_kind(out)
    if found != kind:
        what = f"a tembayes {found} output" if found else "not a tembayes output"
        raise DataError(
            out,
            f"--overwrite replaces only a tembayes {kind} output, and this is {what}",
            "Choose another --out; tembayes does not delete what it did not write",
        )
    if not k.is_file:
        foreign = foreign_entries(out, kind)
        if foreign:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
            raise DataError(
                out,
                f"holds files tembayes did not write there ({shown})",
                "Move them out first, or choose another --out; --overwrite replaces only its own files",
            )


def _writable_folder(out, is_file):
    """The nearest existing folder the output will be created in; refuses a file in the way or no write access."""
    target = _resolved(out)
    probe = target.parent if (is_file or target.exists()) else target
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise DataError(out, f"{probe} is a file, so no folder can be created there", "Choose another --out")
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".tembayes-probe-", dir=probe))
    except OSError as e:
        raise DataError(
            out, f"cannot write in {probe} ({e.strerror or e})", "Choose an --out in a folder you can write to"
        ) from None
    return probe


def check_output(
    out: Path | str,
    *,
    kind: str,
    inputs: Iterable[tuple[Path | str, str]] = (),
    overwrite: bool = False,
    need_bytes: int = MIN_FREE_BYTES,
) -> None:
    """Refuse an output that would lose data or fail, before any work.

    Parameters
    ----------
    out : str or Path
        The output folder (or file, for ``export``).
    kind : str
        The command (a key of :data:`KINDS`).
    inputs : iterable of (path, role)
        The command's inputs, e.g. ``[(batch_path, "batch folder")]``; a role
        of ``"batch folder"`` also refuses outputs inside it.
    overwrite : bool
        The user allowed replacing an existing output of the same kind.
    need_bytes : int
        Free space the output needs at least.

    Raises
    ------
    DataError
        Naming the output and what to do.
    """
    out = Path(out)
    _refuse_overlap(out, inputs)
    refuse_existing(out, kind, overwrite)
    folder = _writable_folder(out, KINDS[kind].is_file)
    free = shutil.disk_usage(folder).free
    if free < need_bytes:
        raise DataError(
            out,
            f"only {free / 2**20:.0f} MB are free in {folder}, and this needs about {need_bytes / 2**20:.0f} MB",
            "Free some space or choose an --out on another disk",
        )


class LockHeld(TembayesError):
    """Another process holds the lock."""


class RunLock:
    """One writer per run: an exclusive lock file beside the run folder.

    The lock is an ``flock`` on ``<parent>/.<name>.lock``, released by the
    kernel when its process ends however it ends; the file records who took
    it, so a live holder is named and a stale file (its process gone) is
    reported and taken over.

    Parameters
    ----------
    run : Path
        The run folder the lock guards (it need not exist).
    """

    def __init__(self, run):
        self.run = Path(run)
        self.path = self.run.parent / f".{self.run.name}.lock"
        self.fd = None
        self.stale = None

    def acquire(self) -> RunLock:
        """Take the lock or raise :class:`LockHeld` naming the holder; returns self."""
        import fcntl

        self.path.parent.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = _read_holder(fd)
                os.close(fd)
                raise LockHeld(
                    f"{self.run}: the run is being written by {_describe(holder)}. Wait for it to "
                    "finish, or stop that process first"
                ) from None
            # the file may have been removed by a finishing holder between open and flock: try again
            with contextlib.suppress(FileNotFoundError):
                if os.stat(self.path).st_ino == os.fstat(fd).st_ino:
                    break
            os.close(fd)
        holder = _read_holder(fd)
        self.stale = holder or None
        os.ftruncate(fd, 0)
        os.write(
            fd,
            json.dumps(
                {
                    "pid": os.getpid(),
                    "host": socket.gethostname(),
                    "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                    "command": " ".join(sys.argv),
                }
            ).encode(),
        )
        os.fsync(fd)
        self.fd = fd
        return self

    def release(self) -> None:
        """Remove the lock file and release the lock."""
        if self.fd is None:
            return
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)
        os.close(self.fd)
        self.fd = None

    def stale_note(self) -> str | None:
        """A sentence on a stale lock taken over, or None."""
        if not self.stale:
            return None
        return f"a stale lock of {_describe(self.stale)} was found on {self.run} (that process is gone) and taken over"

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()


def _read_holder(fd) -> dict:
    with contextlib.suppress(OSError, ValueError):
        os.lseek(fd, 0, os.SEEK_SET)
        text = os.read(fd, 65536).decode()
        return json.loads(text) if text.strip() else {}
    return {}


def _describe(holder: dict) -> str:
    if not holder:
        return "another process"
    return f"pid {holder.get('pid')} on {holder.get('host')} since {holder.get('started')}" + (
        f" ({holder['command']})" if holder.get("command") else ""
    )
