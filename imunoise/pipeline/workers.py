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


class Background:
    """``fn(*args)`` computed in a forked child process while this one goes on.

    The diagnose and analyze commands start the coherence of a record's channels this way
    before they fit: it does not depend on the fit, and the fit keeps one CPU busy for
    seconds at a time. The child inherits the arguments without copying them through a pipe
    and sends back only the result. A child still running when this process exits is ended
    with it (it is a daemon).

    :meth:`result` gives what ``fn(*args)`` returns, or raises what it raises: where the child
    cannot be used (one CPU, no fork, another thread running, the child killed or its result
    not picklable) the call is made in this process instead, when the result is asked for.
    No thread is started here, so the job map's workers can still be forked meanwhile.
    """

    def __init__(self, fn: Callable[..., R], *args: Any) -> None:
        self._fn, self._args = fn, args
        self._done: tuple[Any] | None = None
        self._process: Any = None
        self._conn: Any = None
        if available_cpus() < 2 or not can_fork():
            return
        ctx = multiprocessing.get_context("fork")
        receive, send = ctx.Pipe(duplex=False)
        self._process = ctx.Process(target=_send_result, args=(send, fn, args), daemon=True)
        try:
            self._process.start()
        except OSError:  # no process left to fork (ulimit, memory): computed here instead
            self._process = None
            receive.close()
        else:
            self._conn = receive
        finally:
            send.close()

    def result(self) -> Any:
        """The result (waits for the child; computes it here where the child failed)."""
        if self._done is not None:
            return self._done[0]
        if self._conn is not None:
            try:
                ok, value = self._conn.recv()
            except (EOFError, OSError):
                ok, value = False, None  # the child died before sending
            finally:
                self._conn.close()
                self._conn = None
                self._process.join()
            if ok:
                self._done = (value,)
                return value
        # the child's failure or exception is reproduced here, with its real traceback
        value = self._fn(*self._args)
        self._done = (value,)
        return value


def _send_result(conn: Any, fn: Callable[..., Any], args: tuple[Any, ...]) -> None:
    """The child's side of :class:`Background`: send ``(True, result)``, or ``(False, None)``
    when ``fn`` raised or the result cannot be pickled."""
    try:
        out = (True, fn(*args))
    except BaseException:  # noqa: BLE001 - the parent repeats the call and raises it there
        out = (False, None)
    try:
        conn.send(out)
    except Exception:  # noqa: BLE001 - an unpicklable result: the parent computes it itself
        conn.send((False, None))
    finally:
        conn.close()
