"""The scheduler of the live analysis: one :class:`imunoise.live.channel.LiveChannel` per channel,
their fits and diagnoses run one at a time within a CPU budget, in a worker process.

Feeding (``update``) only runs the streaming estimators, which are vectorised and cheap. The
work that costs (fits, diagnosis) is scheduled by :meth:`RollingAnalyzer.refresh`, which the
caller invokes from its own thread: one job at a time, channels in turn (the one waiting
longest first), and after each job a pause long enough to keep the analysis CPU time under
``cpu_budget`` of one core. Jobs run in :class:`WorkerProcess`, off the interpreter lock of the
HTTP side.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol

import numpy as np

from imunoise.analysis.channel_state import DEFAULT_MODEL, check_terms
from imunoise.core.series import channel_units
from imunoise.live.channel import LiveChannel, run_inline, timed


class BlockLike(Protocol):
    """What :meth:`RollingAnalyzer.update` takes: a block of samples of one stream (e.g.
    :class:`imunoise.core.blocks.SampleBlock`)."""

    stream: str
    channels: dict[str, np.ndarray]
    fs_hz: float
    gap_before: int


PARENT_CHECK_S = 1.0
"""How often a fit worker checks that the service that started it still runs (s)."""


def _worker_init(parent_pid: int) -> None:
    """Set up a fit worker: Ctrl-C is left to the service, which stops the worker (a terminal
    sends SIGINT to every process of the foreground group); and the worker ends when the
    service is gone. A service killed with SIGKILL cannot stop it, and the worker, waiting
    on a job queue whose other end it holds itself, would never learn of it otherwise."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(PARENT_CHECK_S)
        os._exit(0)  # no job can be returned to anyone: nothing to finish

    threading.Thread(target=watch, name="imunoise-fit-parent-watch", daemon=True).start()


class WorkerClosed(RuntimeError):
    """A job was abandoned because the worker was closed (the service is stopping)."""


class WorkerProcess:
    """Runs jobs in one worker process, so a fit never holds the interpreter lock that the
    acquisition thread needs. A worker that dies is replaced and the job retried once; if
    the replacement dies too (e.g. a main module that cannot be imported twice), jobs run in
    the calling thread from then on (``fallback`` says why).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pool: ProcessPoolExecutor | None = None
        self._closed = False
        self.fallback: str | None = None

    def _executor(self) -> ProcessPoolExecutor:
        with self._lock:
            if self._closed:
                raise WorkerClosed("the analysis is shutting down")
            if self._pool is None:
                # spawn, not fork: the parent runs threads (acquisition, HTTP) holding locks
                self._pool = ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"),
                                                 initializer=_worker_init,
                                                 initargs=(os.getpid(),))
            return self._pool

    def __call__(self, fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
        for _ in (0, 1):
            if self.fallback is not None:
                break
            pool = self._executor()
            try:
                return pool.submit(timed, fn, *args).result()
            except BrokenProcessPool as exc:
                with self._lock:
                    if self._closed:
                        raise WorkerClosed("the analysis is shutting down") from None
                    if self._pool is pool:
                        self._pool = None
                last = exc
        else:
            self.fallback = f"the worker process died twice ({last}); fits run in-process"
        return timed(fn, *args)

    def close(self) -> None:
        """Stop the worker at once: a running job is abandoned (its caller gets
        :class:`WorkerClosed`), so shutting down never waits for a fit."""
        with self._lock:
            self._closed = True
            pool, self._pool = self._pool, None
        if pool is None:
            return
        # The executor has no public way to end a running job; its worker processes are
        # terminated directly (``_processes``: pid -> Process, unchanged since Python 3.8).
        processes = list(getattr(pool, "_processes", {}).values())
        manager = getattr(pool, "_executor_manager_thread", None)  # shutdown() forgets it
        pool.shutdown(wait=False, cancel_futures=True)
        for proc in processes:
            if proc.is_alive():
                proc.terminate()
        # the executor's own thread may reap a process first, which ends a join early
        deadline = time.monotonic() + 5.0
        for proc in processes:
            while proc.is_alive() and time.monotonic() < deadline:
                proc.join(0.05)
        # Let the executor's thread finish now: on Python 3.11, if it is still closing its
        # wake-up pipe when the interpreter exits, the executor's exit hook can write to the
        # closed pipe and print "OSError: Bad file descriptor" after a clean stop.
        if manager is not None:
            manager.join(max(0.0, deadline - time.monotonic()))


class RollingAnalyzer:
    """One :class:`LiveChannel` per analysable channel of the blocks fed, and the
    scheduler of their fits.

    Channels named ``gyro_*`` and ``accel_*`` are analysed; a channel name already taken by
    another stream is keyed ``STREAM:NAME``, and with ``qualified`` every channel is (as the
    MCAP readers name the channels of a file with several IMU topics: ``/razor/itg3200/
    imu:gyro_x``).

    Args:
        model: initial model of every channel.
        cpu_budget: fraction of one core the fits and diagnoses may use on average; after a
            job of ``c`` CPU seconds the next starts no sooner than ``c / cpu_budget`` after
            it began.
        workers: ``"inline"`` (jobs run in the calling thread) or ``"process"`` (in one
            worker process, off the interpreter lock of the acquisition; call :meth:`close`).
        qualified: key every channel ``STREAM:NAME`` (several devices at once).
        **analyzer_kwargs: passed to each :class:`LiveChannel`.
    """

    def __init__(self, model: Sequence[str] = DEFAULT_MODEL, cpu_budget: float = 0.3,
                 workers: str = "inline", qualified: bool = False,
                 **analyzer_kwargs: Any) -> None:
        check_terms(model)
        if not 0 < cpu_budget <= 1:
            raise ValueError(f"cpu_budget must be in (0, 1], got {cpu_budget}")
        if workers not in ("inline", "process"):
            raise ValueError(f"workers must be 'inline' or 'process', got {workers!r}")
        self._worker = WorkerProcess() if workers == "process" else None
        analyzer_kwargs.setdefault("runner", self._worker or run_inline)
        self._model = list(model)
        self.qualified = qualified
        self._kwargs = analyzer_kwargs
        self.cpu_budget = cpu_budget
        self._lock = threading.Lock()
        self._analyzers: dict[str, LiveChannel] = {}
        self._keys: dict[tuple[str, str], str] = {}
        self._next_job_t = -math.inf
        self._job_cpu = 0.0
        self._job_wall = 0.0
        self._jobs: deque[tuple[float, str, str, float]] = deque(maxlen=256)

    def update(self, block: BlockLike) -> None:
        """Route a block's channels to their analyzers (new segment after a gap)."""
        gap = getattr(block, "gap_before", 0) != 0
        for name, values in block.channels.items():
            if channel_units(name) not in ("rad/s", "m/s^2"):
                continue
            analyzer = self._analyzer(block.stream, name, block.fs_hz)
            analyzer.update(values, new_segment=gap)

    def _analyzer(self, stream: str, name: str, fs_hz: float) -> LiveChannel:
        key = self._keys.get((stream, name))
        if key is not None:
            return self._analyzers[key]
        with self._lock:
            key = (name if name not in self._analyzers and not self.qualified
                   else f"{stream}:{name}")
            self._analyzers[key] = LiveChannel(key, fs_hz, units=channel_units(name),
                                               model=self._model, **self._kwargs)
            self._keys[(stream, name)] = key
            return self._analyzers[key]

    @property
    def channels(self) -> list[str]:
        with self._lock:
            return list(self._analyzers)

    def get(self, channel: str) -> LiveChannel:
        """The analyzer of ``channel``; ``KeyError`` naming the valid channels otherwise."""
        with self._lock:
            if channel not in self._analyzers:
                valid = ", ".join(self._analyzers) or "(none yet)"
                raise KeyError(f"unknown channel {channel!r}; valid channels: {valid}")
            return self._analyzers[channel]

    def refresh(self, force: bool = False) -> bool:
        """Run the most overdue job of any channel, if the CPU budget allows one now.

        ``force``: bring every channel up to date at once, ignoring the budget (a full fit
        and a diagnosis each; used at the end of a replay). Returns whether anything
        changed."""
        with self._lock:
            analyzers = list(self._analyzers.values())
        if force:
            changed = False
            for a in analyzers:
                changed |= a.refit(full=True)
                if a.fitted:
                    changed |= a.diagnose()
            return changed
        now = time.monotonic()
        if now < self._next_job_t:
            return False
        # channels in turn: the one whose last job is oldest, then its most overdue job
        due = [(a.last_job_t, d, a) for a in analyzers if (d := a.due(now)) is not None]
        if not due:
            return False
        _, (_, kind), a = min(due, key=lambda x: (x[0], x[1]))
        t0, w0, j0 = time.thread_time(), time.monotonic(), a.job_cpu_s
        changed = a.run(kind, now)
        wall = time.monotonic() - w0
        # this thread's CPU (curve, bookkeeping) plus the job's, wherever it ran
        cpu = time.thread_time() - t0 + (a.job_cpu_s - j0 if self._worker else 0.0)
        with self._lock:
            self._next_job_t = w0 + cpu / self.cpu_budget
            self._job_cpu += cpu
            self._job_wall += wall
            self._jobs.append((time.time(), a.channel, kind, cpu))
        return changed

    def stats(self) -> dict[str, Any]:
        """What the scheduler did: CPU per job kind, jobs per minute, the refit period."""
        with self._lock:
            jobs = list(self._jobs)
            analyzers = list(self._analyzers.values())
            total_cpu = self._job_cpu
        now = time.time()
        recent = [j for j in jobs if now - j[0] <= 60.0]
        per_kind: dict[str, list[float]] = {}
        for _, _, kind, cpu in jobs:
            per_kind.setdefault(kind, []).append(cpu)
        fits = sorted(j[0] for j in jobs if j[2] in ("fit", "full"))
        period = None
        if len(fits) >= 2 and analyzers:
            period = (fits[-1] - fits[0]) / (len(fits) - 1) * len(analyzers)
        return {
            "workers": "inline" if self._worker is None else
            ("process" if self._worker.fallback is None else "inline (worker failed)"),
            "cpu_budget": self.cpu_budget,
            "cpu_s_total": total_cpu,
            "cpu_fraction_last_minute": sum(j[3] for j in recent) / 60.0,
            "jobs_last_minute": len(recent),
            "median_cpu_s": {k: float(np.median(v)) for k, v in per_kind.items()},
            "refit_period_s": period,
        }

    def close(self) -> None:
        """Stop the worker process, if any."""
        if self._worker is not None:
            self._worker.close()

    @property
    def revision(self) -> int:
        with self._lock:
            return sum(a.revision for a in self._analyzers.values())
