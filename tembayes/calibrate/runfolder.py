"""The run folder's life: one writer, built beside the target, swapped in when complete.

A calibration writes into ``RUN.partial/`` next to ``RUN`` and renames it to
``RUN`` only when the run is complete, so a run that fails or is killed
leaves the previous ``RUN`` as it was, and ``--resume`` continues from
``RUN.partial/``.  One process at a time writes a run (:class:`RunLock`).
The run records its seed and the SHA-256 of every input file; a resume
with another seed or a changed batch is refused, naming what differs.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

from tembayes.calibrate.moduledigest import digest_matches
from tembayes.data.digest import batch_inputs, compare_inputs
from tembayes.data.outputs import MARKER, RunLock, check_output, foreign_entries, marker, output_kind
from tembayes.data.write import atomic_write_text
from tembayes.errors import DataError

__all__ = ["RunFolder", "partial_path", "module_usable", "module_matches", "bytes_needed"]

#: Free space a run needs per module (its posterior file and sampler checkpoints) [bytes].
BYTES_PER_MODULE = 40 << 20


def partial_path(run: Path | str) -> Path:
    """``RUN.partial``: where a run is built until it is complete."""
    run = Path(run)
    return run.with_name(run.name + ".partial")


def bytes_needed(n_modules: int, workers: int) -> int:
    """Free space a run needs before it starts [bytes] (modules at once hold checkpoints)."""
    return (20 << 20) + BYTES_PER_MODULE * min(n_modules, max(workers, 1)) + (2 << 20) * n_modules


def module_usable(nc: Path | str) -> bool:
    """Whether a module's ``.nc`` file can be read back (a resumed run recalibrates a damaged one)."""
    if digest_matches(nc):
        return True
    try:
        import h5py

        with h5py.File(nc, "r") as f:
            return "posterior" in f and "log_likelihood" in f
    except (OSError, ValueError, KeyError):
        return False


def module_matches(nc: Path | str, options) -> bool:
    """Whether a module's ``.nc`` file was calibrated with ``options``' model and discrepancy.

    A resumed run reuses its finished modules only when they are the same
    calibration: a module of another ``--model`` or ``--discrepancy``, or a
    robust one from before the runs kept each draw's held values, has other
    variables, and the batch's posterior cannot join them.
    """
    import h5py

    try:
        with h5py.File(nc, "r") as f:
            attrs = f["posterior"].attrs
            meta = json.loads(next(attrs[k] for k in attrs if k.startswith("module_")))
    except (OSError, ValueError, KeyError, StopIteration):
        return False
    recorded = meta.get("options") or {}
    same = all(recorded.get(k) == getattr(options, k) for k in ("model", "discrepancy"))
    return same and (options.discrepancy != "robust" or "held" in meta)


def _state(folder) -> dict:
    """The marker of a run folder, or what an older run's summary.json says of its seed and batch."""
    folder = Path(folder)
    with contextlib.suppress(OSError, ValueError):
        m = json.loads((folder / MARKER).read_text())
        if "seed" in m:
            return m
    with contextlib.suppress(OSError, ValueError):
        s = json.loads((folder / "summary.json").read_text())
        cal = s.get("calibration") or {}
        return {
            "seed": cal.get("seed"),
            "batch": s.get("batch") or {},
            "law_prior": (cal.get("options") or {}).get("law_prior"),
        }
    return {}


@dataclass
class RunFolder:
    """A calibration run folder being written (a context manager).

    Parameters
    ----------
    run : Path
        The run folder the user asked for.
    batch : tembayes.data.Batch
        The loaded batch.
    seed : int
    resume : bool
        Continue ``RUN.partial`` (or a finished ``RUN``: retry its failed
        modules, rebuild its summary) instead of starting afresh.
    overwrite : bool
        Replace an existing ``RUN`` (a calibration run holding nothing else)
        or an interrupted ``RUN.partial`` when done.
    workers : int
        Modules calibrated at once (the free-space check).
    progress : callable, optional
    """

    run: Path
    batch: object
    seed: int
    resume: bool = False
    overwrite: bool = False
    workers: int = 1
    progress: object = None
    law_prior: dict | None = None

    def __post_init__(self):
        self.run = Path(self.run)
        self.partial = partial_path(self.run)
        self.lock = RunLock(self.run)
        self.inputs = None

    def __enter__(self) -> Path:
        say = self.progress or (lambda msg: None)
        check_output(
            self.run,
            kind="calibrate",
            inputs=[(self.batch.path, "batch folder")],
            overwrite=self.overwrite or self.resume,
            need_bytes=bytes_needed(len(self.batch.modules), self.workers),
        )
        self.lock.acquire()
        try:
            if self.lock.stale_note():
                say(self.lock.stale_note())
            self.inputs = batch_inputs(self.batch)
            self._prepare(say)
        except BaseException:
            self.lock.release()
            raise
        return self.partial

    def _prepare(self, say):
        if self.partial.exists():
            if output_kind(self.partial) != "calibrate" or foreign_entries(self.partial, "calibrate"):
                raise DataError(
                    self.partial,
                    "is in the way of the run and is not an interrupted tembayes run",
                    "Move it away or choose another --out",
                )
            if self.resume:
                self._check_same(self.partial, say)
                say(f"resuming the interrupted run in {self.partial}")
                return
            if not self.overwrite:
                raise DataError(
                    self.partial,
                    "holds an interrupted run of this --out",
                    "Continue it with --resume, or start afresh with --overwrite",
                )
            shutil.rmtree(self.partial)
        self.partial.mkdir(parents=True)
        if self.resume and self.run.is_dir() and any(self.run.iterdir()):
            self._check_same(self.run, say)
            _link_modules(self.run, self.partial)
            say(f"resuming from the finished run {self.run} (its modules reused; it is replaced when done)")
        self._write_marker(complete=False)

    def _check_same(self, folder, say):
        state = _state(folder)
        if state.get("seed") is not None and int(state["seed"]) != int(self.seed):
            raise DataError(
                folder,
                f"the run was started with --seed {state['seed']}, not {self.seed}",
                f"Resume it with --seed {state['seed']}, or start afresh with --overwrite",
            )
        if state.get("law_prior") != self.law_prior:
            # the reused modules were sampled under the recorded prior; the population divides out the new one
            was, now = (
                ("the datasheet's" if x is None else x["source"]) for x in (state.get("law_prior"), self.law_prior)
            )
            raise DataError(
                folder,
                f"the run's laws were calibrated under the prior of {was}, not {now}",
                "Resume it with the same --unit-prior (or none), or start afresh with --overwrite",
            )
        recorded = (state.get("batch") or {}).get("inputs")
        if recorded is None:
            say(
                f"note: {folder} records no digest of its batch: make sure {self.batch.path} is the batch it was "
                "started on"
            )
            return
        diff = compare_inputs(recorded, self.inputs)
        if not diff.same:
            what = "; ".join(
                f"{label}: {', '.join(files[:3])}"
                for label, files in (("changed", diff.changed), ("missing", diff.missing), ("new", diff.added))
                if files
            )
            raise DataError(
                folder,
                f"the batch {self.batch.path} differs from the one the run was started on ({what})",
                "Resume it on the same batch, or start afresh with --overwrite",
            )

    def record(self) -> dict:
        """What ``summary.json`` records of the batch: absolute path, digests of its files."""
        return {"path": str(Path(os.path.abspath(self.batch.path))), "inputs": self.inputs}

    def _write_marker(self, *, complete):
        atomic_write_text(
            self.partial / MARKER,
            marker("calibrate", complete=complete, seed=int(self.seed), batch=self.record(), law_prior=self.law_prior),
        )

    def commit(self) -> None:
        """Swap the finished ``RUN.partial`` into place as ``RUN`` (the old ``RUN`` is removed after)."""
        self._write_marker(complete=True)
        shutil.rmtree(self.partial / "checkpoints", ignore_errors=True)
        if self.run.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{self.run.name}.old-", dir=self.run.parent))
            os.rmdir(old)
            os.replace(self.run, old)
            os.replace(self.partial, self.run)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(self.partial, self.run)

    def __exit__(self, exc_type, exc, tb):
        self.lock.release()
        return False


def _link_modules(run, partial):
    """The finished modules of ``run`` in ``partial`` (hard links where possible: nothing is copied twice)."""
    src = Path(run) / "modules"
    if not src.is_dir():
        return
    dst = Path(partial) / "modules"
    dst.mkdir(exist_ok=True)
    for f in src.iterdir():
        if f.is_file():
            try:
                os.link(f, dst / f.name)
            except OSError:
                shutil.copy2(f, dst / f.name)
