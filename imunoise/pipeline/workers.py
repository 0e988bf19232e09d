"""The command line's job map (:mod:`imunoise.analysis.jobs`): independent jobs that share one
large context, side by side in forked worker processes.

The diagnosis refits the model once per candidate term; each refit is a few hundred small
least-squares solves, Python-bound, so threads would only take turns on the interpreter
lock. Worker processes forked from this one inherit the context (the record, the fitted
model, the memo of solved sub-models) without copying it through a pipe; only each job's
result is pickled back. The results are those of the serial map, in the same order: a job
reads the context, and what it adds to the context's memo stays in its worker.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

from imunoise.analysis.jobs import JobMap

C = TypeVar("C")
T = TypeVar("T")
R = TypeVar("R")

# The job and its context while a pool runs: set before the workers are forked, so that
# each worker finds them in its copy of this module.
_SHARED: tuple[Callable[[Any, Any], Any], Any] | None = None


def available_cpus() -> int:
    """The CPUs this process may run on (its affinity mask where the system has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS and Windows have no affinity call
        return os.cpu_count() or 1


def can_fork() -> bool:
    """Whether forking is safe here: the platform forks, and no other thread runs in this
    process (a fork copies the locks another thread may hold, never their release)."""
    return "fork" in multiprocessing.get_all_start_methods() \
        and threading.active_count() == 1


def _run(item: Any) -> Any:
    assert _SHARED is not None  # set by forked_map before the fork
    fn, shared = _SHARED
    return fn(shared, item)


def forked_map(fn: Callable[[C, T], R], shared: C, items: Sequence[T], workers: int) -> list[R]:
    """``[fn(shared, item) for item in items]``, in up to ``workers`` forked processes.

    Serial when ``workers`` is below 2, with fewer than two items, or where forking is not
    safe (:func:`can_fork`), and also when the pool breaks (a worker killed, e.g. for
    memory): the jobs are then run here. An exception raised by ``fn`` reaches the caller
    as in the serial loop.
    """
    global _SHARED
    n = min(int(workers), len(items))
    if n < 2 or _SHARED is not None or not can_fork():
        return [fn(shared, item) for item in items]
    _SHARED = (fn, shared)
    try:
        with ProcessPoolExecutor(max_workers=n,
                                 mp_context=multiprocessing.get_context("fork")) as pool:
            return list(pool.map(_run, items))
    except BrokenProcessPool:
        return [fn(shared, item) for item in items]
    finally:
        _SHARED = None


def cpu_job_map(workers: int | None = None) -> JobMap:
    """The job map of :func:`forked_map` with ``workers`` processes (default: every CPU of
    :func:`available_cpus`)."""
    return functools.partial(forked_map, workers=available_cpus() if workers is None
                             else int(workers))
