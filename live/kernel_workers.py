"""Real-time priority for the kernel's unbound worker threads while a serial device is read.

Bytes from a serial adapter (a Bus Pirate on USB, or the simulator's pseudo-terminal) do not
go straight to the process that reads them: the tty layer queues them in a flip buffer and a
worker thread of the kernel's unbound workqueue (``kworker/uN:M``) moves them on. Those threads
are scheduled like any normal process. The acquisition process may run at SCHED_FIFO, but
beside CPU-bound processes a worker can wait several milliseconds for a core, and a
poll of a part without FIFO waits with it; measured with ``bench/serve.py --runs adis204
--load busy`` (3 min, the simulator's pseudo-terminal carries both directions through such
workers): 20 of 37,261 samples lost with the workers as the kernel leaves them, 0 of 37,243
with them at SCHED_FIFO 1; over 10 minutes (same load) with the workers raised, 0 of 123,195
(60 of 123,153 without, in an earlier run).

:class:`KernelWorkerBoost` puts every unbound worker at SCHED_FIFO 1, the lowest real-time
priority (below the acquisition process's), and puts back the policy and nice value of each
worker raised when the last holder stops. Several ``serve`` processes on one machine share
the workers through a :class:`WorkerLedger` (a small file under an exclusive lock): a worker
is given back only when no live holder remains, and a holder that died without stopping is
dropped by the next one that looks. :class:`KernelWorkerKeeper` holds a boost in a process of
its own: it looks for new workers every :data:`RESCAN_S`, since the kernel starts and ends
them as it likes, and gives the workers back as soon as its parent has gone, even when the
parent was killed with SIGKILL. I2C transfers run in the calling thread and do not need any
of it.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import multiprocessing as mp
import os
import re
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from imunoise.live.termination import TermFlag, end_process

WORKER_PREFIX = "kworker/u"
"""Name prefix of the kernel's unbound workqueue threads (a suffix names the work they ran
last, after ``-``, or run at the moment, after ``+``)."""
FIFO_PRIORITY = 1
"""The real-time priority given: the lowest, so that the acquisition process (20) and the
kernel's own real-time threads keep precedence."""
RESCAN_S = 0.5
"""How often new workers are looked for, and a keeper checks that its parent lives (s)."""
LEDGER_NAME = "imunoise-kernel-workers.json"
STATUS_BYTES = 512
"""Room for a keeper's status (JSON) in shared memory."""

Match = Callable[[int, str], bool]


def is_unbound_worker(pid: int, comm: str) -> bool:
    """Whether a thread named ``comm`` is one of the kernel's unbound workers."""
    return comm.startswith(WORKER_PREFIX)


def worker_name(comm: str) -> str:
    """A kernel worker's own name, without the work it ran last or runs now: the kernel
    names a worker ``kworker/u8:1-events_unbound`` when idle and ``kworker/u8:1+events_unbound``
    while it runs that work, so the part before either sign is what stays while it lives."""
    return re.split(r"[-+]", comm, maxsplit=1)[0]


def process_name(pid: int, proc: Path = Path("/proc")) -> str | None:
    """The name of process ``pid``, or None when it has ended."""
    try:
        return (proc / str(pid) / "comm").read_text().strip()
    except OSError:
        return None


def process_start(pid: int, proc: Path = Path("/proc")) -> int | None:
    """When process ``pid`` started (clock ticks since boot: with the pid, it names one
    process for good), or None when it has ended."""
    try:
        stat = (proc / str(pid) / "stat").read_text()
    except OSError:
        return None
    # the name in parentheses may hold spaces; the start time is field 22, the 20th after it
    fields = stat.rsplit(")", 1)[-1].split()
    return int(fields[19]) if len(fields) > 19 else None


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


def default_ledger() -> Path:
    """Where the machine's ledger lives: ``/run`` when this process may write there (root),
    else the temporary folder, per user."""
    run = Path("/run")
    if run.is_dir() and os.access(run, os.W_OK):
        return run / LEDGER_NAME
    return Path(tempfile.gettempdir()) / f"{LEDGER_NAME.removesuffix('.json')}-{os.getuid()}.json"


class WorkerLedger:
    """Which processes hold the workers raised, and what each raised worker had before.

    The record is ``{"holders": [[pid, start], ...], "changed": {pid: [name, policy, nice]}}``
    in a file read and written only under an exclusive ``flock``.
    """

    def __init__(self, path: Path | None = None) -> None:
        self.path = Path(path) if path is not None else default_ledger()

    @contextlib.contextmanager
    def locked(self) -> Iterator[dict[str, Any]]:
        """The record, locked; changes made to it are written back on leaving.

        Raises:
            OSError: the file cannot be opened (a symbolic link is refused).
        """
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            with os.fdopen(os.dup(fd), "r+") as f:
                try:
                    state = json.loads(f.read() or "{}")
                except ValueError:
                    state = {}  # unreadable: what it held cannot be given back
                if not isinstance(state, dict):
                    state = {}
                state.setdefault("holders", [])
                state.setdefault("changed", {})
                yield state
                f.seek(0)
                f.truncate()
                f.write(json.dumps(state))
        finally:
            os.close(fd)  # releases the lock


def _alive(holder: list[int]) -> bool:
    pid, start = holder
    return process_start(pid) == start


class KernelWorkerBoost:
    """Hold the matching threads at SCHED_FIFO :data:`FIFO_PRIORITY` from :meth:`start` until
    :meth:`stop`; each :meth:`boost_once` raises those that appeared since (the kernel starts
    and ends workers as it likes). It has no thread of its own: :class:`KernelWorkerKeeper`
    calls it every :data:`RESCAN_S` in its process.

    Args:
        match: which (pid, name) to raise; the kernel's unbound workers by default.
        ledger: the record shared with other holders on this machine (default: the
            machine's, :func:`default_ledger`).
    """

    def __init__(self, match: Match = is_unbound_worker,
                 ledger: WorkerLedger | None = None) -> None:
        self.match = match
        self.ledger = ledger or WorkerLedger()
        self.refused: str | None = None
        self._me = [os.getpid(), process_start(os.getpid()) or 0]
        self._threads = 0
        self._holders = 0
        self._joined = False
        self._stopped = False

    def start(self) -> KernelWorkerBoost:
        """Join the holders and raise the workers now (a refusal is then in :attr:`refused`)."""
        self.boost_once()
        return self

    def boost_once(self) -> int:
        """Raise every matching thread still at SCHED_OTHER; how many were raised now."""
        if not hasattr(os, "sched_setscheduler"):
            self.refused = "real-time scheduling is not available on this system"
            return 0
        if self._stopped or self.refused is not None:
            return 0
        raised = 0
        try:
            with self.ledger.locked() as state:
                # holders that died without stopping are dropped; what they raised stays
                # recorded, for the last live holder to give back
                state["holders"] = [h for h in state["holders"]
                                    if h != self._me and _alive(h)] + [self._me]
                self._joined = True
                raised = self._raise(state)
                self._threads = len(state["changed"])
                self._holders = len(state["holders"])
        except OSError as exc:
            self.refused = f"ledger {self.ledger.path}: {exc.strerror or exc}"
        return raised

    def _raise(self, state: dict[str, Any]) -> int:
        changed: dict[str, list] = state["changed"]
        raised = 0
        seen: dict[str, str] = {}
        for pid, comm in processes():
            if not self.match(pid, comm):
                continue
            seen[str(pid)] = worker_name(comm)
            try:
                policy = os.sched_getscheduler(pid)
                if policy != os.SCHED_OTHER:
                    continue  # raised already, or real-time by the kernel or an administrator
                nice = os.getpriority(os.PRIO_PROCESS, pid)
                os.sched_setscheduler(pid, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
            except ProcessLookupError:
                continue
            except PermissionError as exc:
                self.refused = f"SCHED_FIFO for kernel workers: {exc.strerror or exc}"
                break
            changed[str(pid)] = [seen[str(pid)], policy, nice]
            raised += 1
        if self.refused is None:  # a full scan: forget the workers that have ended
            for key in [k for k, v in changed.items() if seen.get(k) != v[0]]:
                del changed[key]
        return raised

    def stop(self) -> None:
        """Leave the ledger; when no live holder remains, give every thread raised its policy
        and nice value back (a thread that has ended, or whose pid now names something else,
        is left alone)."""
        self._stopped = True
        if not self._joined:
            return
        self._joined = False
        try:
            with self.ledger.locked() as state:
                state["holders"] = [h for h in state["holders"]
                                    if h != self._me and _alive(h)]
                if not state["holders"]:
                    _restore(state["changed"])
                    state["changed"] = {}
                self._threads = 0
                self._holders = len(state["holders"])
        except OSError:
            pass  # the ledger vanished: nothing recorded to give back

    def status(self) -> dict[str, Any]:
        """For /health: the policy given, how many threads hold it (raised by any holder),
        how many processes hold them, or why none does."""
        return {"policy": f"SCHED_FIFO {FIFO_PRIORITY}", "threads": self._threads,
                "holders": self._holders, "refused": self.refused}


def _restore(changed: dict[str, list]) -> None:
    for key, (name, policy, nice) in changed.items():
        pid = int(key)
        comm = process_name(pid)
        if comm is None or worker_name(comm) != name:
            continue
        try:
            os.sched_setscheduler(pid, policy, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, pid, nice)
        except (OSError, ValueError):
            continue


def _keeper_main(prefix: str, every_s: float, ledger_path: str | None, parent_pid: int,
                 stop: Any, status: Any) -> None:
    term = TermFlag().install()  # the parent decides when to stop

    def publish(st: dict[str, Any]) -> None:
        status.value = json.dumps(st).encode()[:STATUS_BYTES - 1]

    boost = KernelWorkerBoost(match=lambda pid, comm: comm.startswith(prefix),
                              ledger=WorkerLedger(Path(ledger_path) if ledger_path else None))
    try:
        boost.start()
        publish(boost.status())
        while boost.refused is None and not term and not stop.wait(every_s):
            if os.getppid() != parent_pid:
                break  # the parent is gone, however it ended
            boost.boost_once()
            publish(boost.status())
        while boost.refused is not None and not term and not stop.wait(every_s):
            if os.getppid() != parent_pid:
                break  # refused: nothing to hold, but the parent reads the reason
    finally:
        boost.stop()
        publish(boost.status())


class KernelWorkerKeeper:
    """A :class:`KernelWorkerBoost` in a process of its own (``imunoise-kernel-workers``).

    The scan of ``/proc`` stays out of the acquisition process, and the workers are given
    back within :data:`RESCAN_S` of the parent's end, even when it was killed with SIGKILL.

    Args:
        prefix: names of the threads to raise (the kernel's unbound workers by default).
        every_s: how often to look for new workers and for the parent (s).
        ledger: the ledger's file (default: the machine's, :func:`default_ledger`).
    """

    def __init__(self, prefix: str = WORKER_PREFIX, every_s: float = RESCAN_S,
                 ledger: Path | None = None) -> None:
        self.prefix = prefix
        self.every_s = float(every_s)
        self.ledger = ledger
        self._ctx = mp.get_context("spawn")
        self._stop = self._ctx.Event()
        self._status = self._ctx.RawArray("c", STATUS_BYTES)
        self._proc: Any = None

    def start(self, timeout_s: float = 30.0) -> KernelWorkerKeeper:
        """Start the process and wait for its first pass (its status then says what was
        raised or why nothing could be)."""
        # daemonic: should the parent leave without stop(), multiprocessing's exit hook
        # sends it SIGTERM (it gives the workers back) instead of waiting for it forever
        self._proc = self._ctx.Process(
            target=_keeper_main, name="imunoise-kernel-workers", daemon=True,
            args=(self.prefix, self.every_s, str(self.ledger) if self.ledger else None,
                  os.getpid(), self._stop, self._status))
        self._proc.start()
        deadline = time.monotonic() + timeout_s
        while not self._status.value and time.monotonic() < deadline:
            if not self._proc.is_alive():
                break
            time.sleep(0.01)
        return self

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def status(self) -> dict[str, Any]:
        """The keeper's last published status (see :meth:`KernelWorkerBoost.status`)."""
        raw = self._status.value
        if raw:
            try:
                return json.loads(raw.decode())
            except ValueError:
                pass
        alive = self._proc is not None and self._proc.is_alive()
        return {"policy": f"SCHED_FIFO {FIFO_PRIORITY}", "threads": 0, "holders": 0,
                "refused": None if alive else "the kernel-worker process ended at start"}

    def stop(self, timeout_s: float = 10.0) -> None:
        """Ask the process to give the workers back and end; wait for it."""
        end_process(self._proc, self._stop, timeout_s)
