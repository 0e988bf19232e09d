"""Real-time priority for the kernel's unbound worker threads while a device is read.

Bytes from a serial adapter (a Bus Pirate on USB, or the simulator's pseudo-terminal) do not
go straight to the process that reads them: the tty layer queues them in a flip buffer and a
worker thread of the kernel's unbound workqueue (``kworker/uN:M``) moves them on. Those threads
are scheduled like any normal process. The acquisition process may run at SCHED_FIFO, but
beside CPU-bound processes a worker can wait several milliseconds for a core, and a
poll of a part without FIFO waits with it; measured with ``bench/serve.py --runs adis204
--load busy`` (3 min, the simulator's pseudo-terminal carries both directions through such
workers): 20 of 37,261 samples lost with the workers as the kernel leaves them, 0 of 37,243
with them at SCHED_FIFO 1; over 10 minutes (same load) with ``serve
--realtime-kernel-workers``, 0 of 123,195 (60 of 123,153 without, in an earlier run).

:class:`KernelWorkerBoost` puts every unbound worker at SCHED_FIFO 1, the lowest real-time
priority (below the acquisition process's), looks again every :data:`RESCAN_S` since the
kernel starts and ends workers as it likes, and puts back the policy and nice value of each
worker it changed when stopped. It changes the whole machine's scheduling while it runs, so
it is off unless asked for (``serve --realtime-kernel-workers``). I2C transfers run in the
calling thread and do not need it.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

WORKER_PREFIX = "kworker/u"
"""Name prefix of the kernel's unbound workqueue threads (the suffix after ``-`` names the
work they run at the moment)."""
FIFO_PRIORITY = 1
"""The real-time priority given: the lowest, so that the acquisition process (20) and the
kernel's own real-time threads keep precedence."""
RESCAN_S = 0.5
"""How often new workers are looked for (s)."""

Match = Callable[[int, str], bool]


def is_unbound_worker(pid: int, comm: str) -> bool:
    """Whether a thread named ``comm`` is one of the kernel's unbound workers."""
    return comm.startswith(WORKER_PREFIX)


def process_name(pid: int, proc: Path = Path("/proc")) -> str | None:
    """The name of process ``pid``, or None when it has ended."""
    try:
        return (proc / str(pid) / "comm").read_text().strip()
    except OSError:
        return None


def processes(proc: Path = Path("/proc")) -> Iterator[tuple[int, str]]:
    """(pid, name) of every process visible in ``proc``; kernel workers are single-thread
    processes, so their pid is their thread id."""
    try:
        pids = [int(e.name) for e in os.scandir(proc) if e.name.isdigit()]
    except OSError:
        return
    for pid in pids:
        comm = process_name(pid, proc)
        if comm is not None:  # else ended meanwhile
            yield pid, comm


class KernelWorkerBoost:
    """Hold the matching threads at SCHED_FIFO :data:`FIFO_PRIORITY` until :meth:`stop`.

    Args:
        match: which (pid, name) to raise; the kernel's unbound workers by default.
        every_s: how often to look for new ones (s).
    """

    def __init__(self, match: Match = is_unbound_worker, every_s: float = RESCAN_S) -> None:
        self.match = match
        self.every_s = float(every_s)
        self.refused: str | None = None
        self._changed: dict[int, tuple[str, int, int]] = {}  # pid -> (name, policy, nice)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> KernelWorkerBoost:
        """Raise the workers now (so that a refusal is known at once), then keep watching."""
        self.boost_once()
        if self.refused is None:
            self._thread = threading.Thread(target=self._run, name="imunoise-kworker-boost",
                                            daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            self.boost_once()
            if self.refused is not None:
                return

    def boost_once(self) -> int:
        """Raise every matching thread still at SCHED_OTHER; how many were raised now."""
        if not hasattr(os, "sched_setscheduler"):
            self.refused = "real-time scheduling is not available on this system"
            return 0
        raised = 0
        for pid, comm in processes():
            if not self.match(pid, comm):
                continue
            with self._lock:
                if self._stop.is_set() or pid in self._changed:
                    continue
                try:
                    policy = os.sched_getscheduler(pid)
                    if policy != os.SCHED_OTHER:
                        continue  # already real-time (by the kernel or an administrator)
                    nice = os.getpriority(os.PRIO_PROCESS, pid)
                    os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
                except ProcessLookupError:
                    continue
                except PermissionError as exc:
                    self.refused = f"SCHED_FIFO for kernel workers: {exc.strerror or exc}"
                    return raised
                self._changed[pid] = (comm.split("-", 1)[0], policy, nice)
                raised += 1
        return raised

    def stop(self) -> None:
        """Stop watching and give every thread raised here its policy and nice value back
        (a thread that has ended, or whose pid now names something else, is left alone)."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5)
        with self._lock:
            changed, self._changed = self._changed, {}
        for pid, (name, policy, nice) in changed.items():
            comm = process_name(pid)
            if comm is None or comm.split("-", 1)[0] != name:
                continue
            try:
                os.sched_setscheduler(pid, policy, os.sched_param(0))
                os.setpriority(os.PRIO_PROCESS, pid, nice)
            except (OSError, ValueError):
                continue

    def status(self) -> dict[str, Any]:
        """For /health: the policy given, how many threads hold it, or why none does."""
        with self._lock:
            n = len(self._changed)
        return {"policy": f"SCHED_FIFO {FIFO_PRIORITY}", "threads": n, "refused": self.refused}
