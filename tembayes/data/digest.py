"""What a result was computed from: a SHA-256 digest of each input file of a batch.

A run records these digests; a later command that reads the run's batch
(``predict``, ``report``, ``export``, ``gap``, ``calibrate --resume``)
compares them, so a batch that moved is found and a batch that changed is
named file by file instead of silently mixing data.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from .batch import BATCH_TOML, IDENTIFICATION_CSV

if TYPE_CHECKING:
    from collections.abc import Callable

    from .batch import Batch

__all__ = ["file_sha256", "batch_inputs", "InputsCheck", "compare_inputs"]

_BLOCK = 1 << 20


def file_sha256(path: Path | str) -> str:
    """SHA-256 of a file's bytes (hex), read in blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_BLOCK):
            h.update(block)
    return h.hexdigest()


def batch_inputs(batch: Batch) -> dict:
    """``{relative path: sha256}`` of ``batch.toml`` and every experiment file of a loaded batch.

    Parameters
    ----------
    batch : tembayes.data.Batch

    Returns
    -------
    dict
        Keys are POSIX paths relative to the batch folder
        (``"batch.toml"``, ``"TEM1/identification.csv"``, ...); a rig file
        the batch names (``[rig] file``) too, by its absolute path when it
        lies outside the folder.
    """
    root = Path(batch.path)
    files = [root / BATCH_TOML]
    if "file" in batch.rig_config:
        files.append(Path(batch.rig_config["file"]))
    for m in batch.modules.values():
        files.append(Path(m.path) / IDENTIFICATION_CSV)
        files += [Path(p) for p in _validation_paths(m)]
    return {_key(f, root): file_sha256(f) for f in files}


def _key(path: Path, root: Path) -> str:
    try:
        return path.resolve().relative_to(root.resolve()).as_posix()
    except ValueError:
        return path.resolve().as_posix()


def _validation_paths(module):
    files = getattr(module, "validation_files", None)
    if files is not None:  # a lazy module: paths only
        return files
    return [e.path for e in module.validations]


@dataclass(frozen=True)
class InputsCheck:
    """How a batch on disk compares with the inputs a run recorded.

    Attributes
    ----------
    changed : tuple of str
        Files whose content differs.
    missing : tuple of str
        Recorded files that are gone.
    added : tuple of str
        Files the run did not see.
    """

    changed: tuple = ()
    missing: tuple = ()
    added: tuple = ()

    @property
    def same(self) -> bool:
        """Whether no file changed, went missing or was added."""
        return not (self.changed or self.missing or self.added)


def compare_inputs(recorded: dict, now: dict, *, only: Callable[[str], bool] | None = None) -> InputsCheck:
    """Compare two ``batch_inputs`` maps.

    Parameters
    ----------
    recorded, now : dict
        ``{relative path: sha256}``.
    only : callable, optional
        ``only(relative path) -> bool``: the files that matter (e.g. not the
        validation runs, which may be added after a calibration).

    Returns
    -------
    InputsCheck
    """
    keep = only or (lambda _: True)
    rec = {k: v for k, v in recorded.items() if keep(k)}
    cur = {k: v for k, v in now.items() if keep(k)}
    return InputsCheck(
        changed=tuple(sorted(k for k in rec if k in cur and cur[k] != rec[k])),
        missing=tuple(sorted(k for k in rec if k not in cur)),
        added=tuple(sorted(k for k in cur if k not in rec)),
    )
