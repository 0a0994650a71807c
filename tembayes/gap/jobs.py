"""The diagnosis's worker pool: refits and recalibrations run at once, and the candidates' race.

A job is a picklable top-level function and its arguments; its result has
``module``, ``effect`` and ``seconds`` (the wall time it took [s]).  Results
are kept in a cache keyed like the jobs, so that a diagnosis run again on
the same run and batch with an effect withheld reuses the others'.

The race runs the recalibrations of the candidates on the module with the
largest gap first and carries a candidate on to the other modules only when
its result there asks for it.  The decisions are taken in the candidates'
order, not in the order the results arrive (:func:`in_order`), so that the
same seed gives the same diagnosis on any machine.
"""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, as_completed, wait

__all__ = ["Serial", "collect", "default_jobs", "executor", "in_order", "race", "submit_all"]


class Serial:
    """The executor interface in this process (``jobs=1``): a job runs when submitted."""

    def submit(self, fn, *args):
        """Run ``fn(*args)`` now; its result as a finished :class:`~concurrent.futures.Future`."""
        f = Future()
        f.set_result(fn(*args))
        return f

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def executor(jobs):
    """Worker processes for the refits and recalibrations (this process with ``jobs <= 1``).

    Parameters
    ----------
    jobs : int
        Worker processes.

    Returns
    -------
    ProcessPoolExecutor or Serial
    """
    if jobs <= 1:
        return Serial()
    # spawn: the compiled kernels' OpenMP runtime is not fork-safe
    return ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"))


def default_jobs():
    """Worker processes of a diagnosis by default: one more than the cores this process may use.

    The parent mostly waits, and the jobs are uneven (a recalibration takes
    2-4 min, and three modules on two workers leave one core idle for the
    last): one worker more keeps every core busy.  Measured on the 3-module
    speed case, 2 cores: 9:37 with three workers, 10:39 with two, the
    same numbers in ``gap.json`` (every job's seed is its own).
    """
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return cores + 1


def submit_all(ex, jobs, *, cache=None):
    """Submit jobs, reusing the cache's results.

    Parameters
    ----------
    ex : executor
    jobs : dict
        ``key -> (fn, args)``.
    cache : dict, optional
        ``key -> result`` of earlier calls.

    Returns
    -------
    dict
        ``key -> Future``.
    """
    out = {}
    for key, (fn, args) in jobs.items():
        if cache is not None and key in cache:
            out[key] = Future()
            out[key].set_result(cache[key])
        else:
            out[key] = ex.submit(fn, *args)
    return out


def collect(futures, *, cache=None, say, label):
    """Wait for futures as they finish, saying so.

    Parameters
    ----------
    futures : dict
        ``key -> Future``, the keys ending in ``(module_id, effect)``.
    cache : dict, optional
        Filled with the new results.
    say : callable
        Progress messages.
    label : str
        What a job did, for the messages ("refitted").

    Returns
    -------
    dict
        ``key -> result``, in the order they finished.
    """
    out = {}
    keys = {f: k for k, f in futures.items()}
    for f in as_completed(futures.values()):
        key = keys[f]
        out[key] = f.result()
        if cache is not None and key not in cache:
            cache[key] = out[key]
            say(f"  {label} {key[-2]} with {key[-1] or 'the base model'} ({out[key].seconds:.0f} s)")
    return out


def in_order(order, lead, decide):
    """A ``follow`` for :func:`race` that decides on the lead module's results in the candidates' order.

    Parameters
    ----------
    order : list of str
        The candidates, first decided first.
    lead : str
        The module whose results are decided on (the others' carry nothing).
    decide : callable
        ``decide(result)``: the ``(module_id, effect)`` jobs to carry on.  It
        runs for a candidate once it and every candidate before it are in,
        whatever order they finish in.

    Returns
    -------
    callable
        ``follow(result) -> list of (module_id, effect)``.
    """
    arrived, done = {}, set()

    def follow(r):
        if r.module != lead:
            return []
        arrived[r.effect] = r
        out = []
        for e in order:
            if e not in arrived:
                break
            if e not in done:
                done.add(e)
                out += decide(arrived[e])
        return out

    return follow


def race(first, follow, job, *, work, jobs=1, cache=None, say, ex=None):
    """Run the jobs ``first`` and, as each finishes, those ``follow(result)`` asks for (ahead of the rest).

    Parameters
    ----------
    first : list of tuple
        ``(module_id, effect)`` keys to run.
    follow : callable
        ``follow(result) -> list of (module_id, effect)``: the keys to run next.
    job : callable
        ``job(module_id, effect) -> args`` of ``work``.
    work : callable
        One job, ``work(*args)`` (a picklable top-level function with ``jobs > 1``).
    jobs : int
        Jobs at once.  Never more are submitted, so that a carried job jumps
        the queue.
    cache : dict, optional
        ``key -> result``: results already in it are not run again, new ones are added.
    say : callable
        Progress messages.
    ex : executor, optional
        Default: a new one of ``jobs`` workers.

    Returns
    -------
    dict
        ``(module_id, effect) -> result``, in the order they finished.
    """
    if ex is None:
        with executor(jobs) as pool:
            return race(first, follow, job, work=work, jobs=jobs, cache=cache, say=say, ex=pool)
    out, pending, queued = {}, list(first), set(first)

    def record(key, r):
        out[key] = r
        if cache is not None:
            cache[key] = r
        say(f"  recalibrated {key[0]} with {key[1]} ({len(out)} done, {r.seconds:.0f} s)")
        new = [k for k in follow(r) if k not in queued]
        queued.update(new)
        pending[:0] = new  # a candidate carried on goes first: it is the one likely to be reported

    running = {}
    while pending or running:
        while pending and len(running) < max(jobs, 1):
            key = pending.pop(0)
            if cache is not None and key in cache:
                record(key, cache[key])
            else:
                running[ex.submit(work, *job(*key))] = key
        if running:
            finished, _ = wait(running, return_when=FIRST_COMPLETED)
            for f in finished:
                record(running.pop(f), f.result())
    return out
