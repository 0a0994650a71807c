"""Where a batch's modules are calibrated: in this process, or on Dask workers.

A module's calibration depends only on its data, the options and its own
random stream (run seed and module id, :func:`~tembayes.calibrate.module.module_seed`),
so the modules can run anywhere and in any order and give the same bits.
:func:`calibrate_modules` hands them out and yields each outcome as it
arrives; :mod:`tembayes.calibrate.batch` writes it to ``RUN/modules/`` at once,
which is what makes an interrupted batch resumable module by module.

Executors:

* in this process, one module after the other (stage messages, progress bars);
* a local Dask cluster of ``workers`` processes with one thread each
  (``LocalCluster``), or an existing ``dask.distributed`` scheduler
  (``scheduler="tcp://host:8786"``).  Only a window of ``2 x workers``
  modules is in flight: the client loads a module's CSVs just before it
  submits it and drops the result once written, so memory does not grow with
  the batch.  The module's data are scattered to a worker (not put in the
  task graph) and its result comes back to the client, so workers need
  tembayes installed but no access to the batch or run folders (for resuming a module mid-way they do: the sampler
  checkpoints are written where ``RUN/checkpoints`` is, when a worker can see it).

A module that raises is an outcome with an ``error``, not the end of the
batch; a worker that dies is replaced by Dask and its modules sent again
(from their checkpoints, when the worker shares the run folder), and a module
that kills workers repeatedly (more than ``distributed.scheduler.allowed-failures``
times) is reported like one that raised.
"""

from __future__ import annotations

import contextlib
import os
import traceback
import uuid
import warnings
from dataclasses import dataclass, field
from pathlib import Path

from tembayes.calibrate.module import calibrate_module


@dataclass
class ModuleOutcome:
    """What came back for one module.

    Attributes
    ----------
    module_id : str
    result : ModuleCalibration or None
        None when the calibration failed.
    error : str or None
        One line: why it failed (exception type and message).
    detail : str
        The traceback, for the failure record.
    warnings : list of str
        RuntimeWarnings the calibration issued (re-issued by the caller).
    """

    module_id: str
    result: object = None
    error: str | None = None
    detail: str = ""
    warnings: list = field(default_factory=list)


def calibrate_one(
    module, datasheet, rig_config, seed, options, checkpoint, resume, *, progress=None, progress_bar=False, threads=None
):
    """Calibrate one module; an exception becomes the outcome's ``error``.

    Parameters
    ----------
    module : tembayes.data.Module or LazyModule
    datasheet, rig_config, seed, options, checkpoint, resume
        As :func:`~tembayes.calibrate.module.calibrate_module`; a checkpoint
        whose folder this process cannot see is not used.
    threads : int, optional
        Compiled-kernel threads (1 for a worker task of a batch that keeps
        every worker busy: the parallelism is over modules); default: leave
        them as they are.  The results do not depend on it.

    Returns
    -------
    ModuleOutcome
    """
    if threads is not None:
        import numba

        numba.set_num_threads(max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS)))
    if checkpoint is not None and not Path(checkpoint).parent.is_dir():
        checkpoint = None  # a remote worker without the run folder: no mid-module resume
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        try:
            r = calibrate_module(
                module,
                datasheet,
                rig_config=rig_config,
                seed=seed,
                options=options,
                checkpoint=checkpoint,
                resume=resume,
                progress=progress,
                progress_bar=progress_bar,
            )
        except Exception as exc:  # noqa: BLE001 -- one module's failure must not end the batch
            return ModuleOutcome(
                module.id,
                error=f"{type(exc).__name__}: {exc}",
                detail=traceback.format_exc(),
                warnings=[str(w.message) for w in caught],
            )
    return ModuleOutcome(
        module.id, result=r, warnings=[str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]
    )


def _materialise(module):
    """The module with its data in memory (a :class:`LazyModule` reads its CSVs now)."""
    load = getattr(module, "load", None)
    return load() if callable(load) else module


@contextlib.contextmanager
def dask_client(workers=None, scheduler=None):
    """A ``distributed.Client``: of a new local cluster, or of a running scheduler.

    Parameters
    ----------
    workers : int, optional
        Local worker processes (one thread each); ignored with ``scheduler``.
    scheduler : str, optional
        Address of a running ``dask scheduler`` (``tcp://host:8786``) or a
        scheduler file path.
    """
    import logging

    from distributed import Client, LocalCluster

    if scheduler:
        kw = {"scheduler_file": scheduler} if os.path.isfile(str(scheduler)) else {"address": scheduler}
        client = Client(**kw, timeout="30s")
        try:
            yield client
        finally:
            client.close()
        return
    # processes (the sampler holds the GIL), spawned (the compiled kernels'
    # OpenMP runtime is not fork-safe), quiet, no dashboard
    with (
        LocalCluster(
            n_workers=int(workers or 1),
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def calibrate_modules(
    todo,
    datasheet,
    rig_config,
    *,
    seed,
    options,
    checkpoints,
    resume,
    workers=1,
    scheduler=None,
    client=None,
    progress=None,
    progress_bar=False,
):
    """Calibrate modules and yield each :class:`ModuleOutcome` as it finishes.

    Parameters
    ----------
    todo : list of Module or LazyModule
    datasheet, rig_config, seed, options
        As :func:`~tembayes.calibrate.module.calibrate_module`.
    checkpoints : Path
        Folder of the sampler checkpoints (``<id>.json``, ...).
    resume : bool
        Continue modules from their checkpoints.
    workers : int
        1 without ``scheduler``/``client`` (or a single module): in this
        process, one after the other.  More: a local Dask cluster of that
        many processes.
    scheduler : str, optional
        A running Dask scheduler to use instead.
    client : distributed.Client, optional
        An open client to use as it is (benchmarks, notebooks).
    progress : callable, optional
        Stage messages (in-process only).
    progress_bar : bool
        Sampler progress bars (in-process only).

    Yields
    ------
    ModuleOutcome
        In order of completion.
    """
    checkpoints = Path(checkpoints)
    if client is None and scheduler is None and (workers <= 1 or len(todo) <= 1):
        # a single module gains nothing from a cluster, and here it has every core
        for module in todo:
            yield calibrate_one(
                _materialise(module),
                datasheet,
                rig_config,
                seed,
                options,
                checkpoints / module.id,
                resume,
                progress=progress,
                progress_bar=progress_bar,
            )
        return
    with contextlib.ExitStack() as stack:
        if client is None:
            client = stack.enter_context(dask_client(workers, scheduler))
        yield from _on_dask(client, todo, datasheet, rig_config, seed, options, checkpoints, resume)


def _on_dask(client, todo, datasheet, rig_config, seed, options, checkpoints, resume):
    import dask
    from distributed import CancelledError, as_completed

    n_slots = max(1, sum(client.nthreads().values()))
    window = 2 * n_slots  # in flight: every worker busy, one more queued each
    # one kernel thread per task when the modules keep every worker busy; a
    # batch of a few modules per worker ends with idle workers, so its tasks
    # keep the machine's threads (what the earlier process pool measured best)
    threads = 1 if len(todo) >= 4 * n_slots else None
    # the shared inputs go to the workers once, not with every task
    shared = client.scatter([datasheet, rig_config, options], broadcast=True)
    # a module's data go to a worker directly (scatter), not inside the task: a task
    # graph of megabytes passes through the scheduler, and Dask warns about it
    retries = int(dask.config.get("distributed.scheduler.allowed-failures"))
    pending = iter(todo)
    inflight = {}  # task key -> (module, its scattered data, resubmissions so far)

    def submit(module, tries=0):
        if module is None:
            return None
        data = client.scatter(_materialise(module), hash=False)
        key = f"calibrate-{module.id}-{uuid.uuid4().hex}"  # unique on a shared scheduler
        fut = client.submit(
            calibrate_one, data, *shared[:2], seed, shared[2], checkpoints / module.id, resume, threads=threads, key=key
        )
        inflight[fut.key] = (module, data, tries)
        return fut

    first = [f for f in (submit(next(pending, None)) for _ in range(window)) if f is not None]
    running = as_completed(first)
    for fut in running:
        module, data, tries = inflight.pop(fut.key)
        try:
            outcome = fut.result()
        except CancelledError as exc:
            # scattered data have no recipe: a worker that dies takes its modules' data along,
            # and the module is sent again (from its checkpoint, as Dask would rerun a task)
            if tries < retries:
                running.add(submit(module, tries + 1))
                continue
            outcome = ModuleOutcome(
                module.id,
                error=f"{type(exc).__name__}: its worker died {tries + 1} times",
                detail=traceback.format_exc(),
            )
        except Exception as exc:  # noqa: BLE001 -- e.g. KilledWorker: the module, not the batch
            outcome = ModuleOutcome(module.id, error=f"{type(exc).__name__}: {exc}", detail=traceback.format_exc())
        fut.release()
        data.release()
        nxt = submit(next(pending, None))
        if nxt is not None:
            running.add(nxt)
        yield outcome
