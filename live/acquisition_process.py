"""Acquisition and recording in a process of their own, apart from analysis and HTTP.

A sensor without a FIFO (ADIS16350, ITG-3200) must be read on time; in one interpreter with
the rolling analysis, the HTTP server and the event stream, any stall there (a long numpy
call, JSON encoding of a curve, garbage collection) delays the reads, and samples are lost.
So ``serve`` runs the device driver in a child process started here, at the highest
scheduling priority the system grants, doing nothing per sample but read and stamp; the MCAP
recorder runs in a child of that one (:mod:`imunoise.live.recorder_process`), so that encoding,
compressing and fsyncing never hold up a poll. Blocks reach the analysis side through a
:class:`imunoise.live.block_ring.BlockRing` in shared memory that never makes the child wait: when
the
analysis side falls behind, the block is not handed over (a counted hand-over loss, and a gap
for the analysis), while the recording has it.

The parent's :class:`AcquisitionProcess` is the live service's source: it iterates the
blocks from the ring, reports the child's counters (``stats``) and restarts the child when it
dies (the new child writes a new file whose first event says what happened; the analysis sees
a gap). Ctrl-C and SIGTERM reach the parent, which asks the child to stop; the child ignores
SIGINT itself so that its file is always closed by its own hand, and closes it as well when
its parent disappears.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any

from imunoise.live.block_ring import DEFAULT_CAPACITY, BlockRing
from imunoise.live.process_priority import GIL_SWITCH_S, raise_priority, settle_heap
from imunoise.live.restart_pause import RestartPause, describe_exit
from imunoise.live.termination import TermFlag, end_process

STATUS_EVERY_S = 0.25
"""How often the child publishes its counters."""
START_TIMEOUT_S = 60.0
"""How long the parent waits for the child to open the device."""


@dataclass
class AcquisitionConfig:
    """What the child needs to open the device and the recorder (picklable).

    Attributes:
        spec: device name (``imunoise.daq.devices.DEVICES``).
        device_kwargs: ``port``, ``bus``, ``rate_hz``, ``seed`` for ``open_device``.
        out: folder for the MCAP files, or None (no recording).
        record_rate_hz: nominal rate written to the file's metadata (None: the device's).
        software: the writing program and its version.
        priority: ``"realtime"`` (SCHED_FIFO if permitted, else the lowest nice value
            permitted), ``"nice"`` (nice value only) or ``"normal"``.
        simulator_process: run ``sim:adis16350`` in a process of its own behind its
            pseudo-terminal (``imunoise.live.simulator_process``), opened like real hardware; the
            I2C
            simulators live under smbus2's ioctl layer and stay in the acquisition process.
        realtime_kernel_workers: while the child runs, a process of the parent's holds the
            kernel's unbound workers, which carry a serial adapter's bytes, at SCHED_FIFO 1
            (:class:`imunoise.live.kernel_workers.KernelWorkerKeeper`; changes the whole machine's
            scheduling until the parent ends, however it ends).
    """

    spec: str
    device_kwargs: dict[str, Any] = field(default_factory=dict)
    out: str | None = None
    record_rate_hz: float | None = None
    software: str = ""
    priority: str = "realtime"
    simulator_process: bool = True
    realtime_kernel_workers: bool = False


# ----------------------------------------------------------------------------- the child


def _status(acq: Any, recorder: Any, priority: dict[str, Any], state: str | None = None,
            error: str | None = None, simulator: dict[str, Any] | None = None
            ) -> dict[str, Any]:
    stats = getattr(acq, "stats", None)
    acq_stats = stats.as_dict() if stats is not None and hasattr(stats, "as_dict") else {}
    if state is not None:
        acq_stats["state"] = state
    rec = getattr(recorder, "stats", None)
    return {
        "pid": os.getpid(),
        "priority": priority,
        "acquisition": acq_stats,
        "config": {str(k): str(v) for k, v in (getattr(acq, "config", {}) or {}).items()},
        "recording": None if rec is None else {
            "file": rec.file, "files": list(rec.files), "samples": rec.samples,
            "blocks_dropped": rec.blocks_dropped, "lost_samples": rec.lost_samples,
            "pid": rec.pid, "restarts": rec.restarts, "backlog_bytes": rec.backlog_bytes,
            "error": str(getattr(recorder, "error", "") or "") or None},
        "error": error,
        "simulator": simulator,
        "time": time.time(),
    }


class _SimulatorTruth:
    """The simulator process's count of samples never read, from the first block on (the
    samples made between opening the device and the first poll are not part of the
    recording)."""

    def __init__(self, simulator: Any) -> None:
        self.simulator = simulator
        self.baseline: int | None = None

    def first_block(self) -> None:
        if self.simulator is not None and self.baseline is None:
            self.baseline = self.simulator.samples_never_read

    def status(self) -> dict[str, Any] | None:
        if self.simulator is None:
            return None
        lost = (None if self.baseline is None
                else self.simulator.samples_never_read - self.baseline)
        return {"pid": self.simulator.pid, "samples_never_read": lost}


def _open(config: AcquisitionConfig, note: str | None):
    """The device (and its simulator process), the recorder and its sink of one child."""
    from imunoise.analysis.noise_stream import stream_factory
    from imunoise.daq.devices import open_device
    from imunoise.live.recorder_process import RecorderProcess
    from imunoise.live.recorder_sink import RecorderSink

    acq = recorder = sink = simulator = None
    try:
        if config.spec == "sim:adis16350" and config.simulator_process:
            from imunoise.live.simulator_process import SimulatorProcess

            kw = dict(config.device_kwargs)
            simulator = SimulatorProcess(kw.get("rate_hz") or 102.4, kw.pop("seed", 0) or 0,
                                         config.priority)
            acq = open_device("adis16350", port=simulator.start(), **kw)
        else:
            acq = open_device(config.spec, noise=stream_factory, **config.device_kwargs)
        acq.open()
        if config.out:
            recorder = RecorderProcess(
                {"out_dir": config.out, "device": config.spec,
                 "config": getattr(acq, "config", None), "rate_hz": config.record_rate_hz,
                 "software": config.software}, config.priority).start()
            sink = RecorderSink(recorder, acq)
            if note:
                sink.note("warn", note, {"event": "acquisition_restart"})
    except Exception:
        if recorder is not None:
            recorder.close()
        if acq is not None:
            acq.close()
        if simulator is not None:
            simulator.stop()
        raise
    return acq, recorder, sink, simulator


def child_main(config: AcquisitionConfig, ring_name: str, stop: Any, parent_pid: int,
               note: str | None = None) -> None:
    """Entry point of the acquisition process."""
    term = TermFlag().install()  # the parent decides when to stop
    sys.setswitchinterval(GIL_SWITCH_S)
    priority = raise_priority(config.priority)
    ring = BlockRing(ring_name)
    try:
        acq, recorder, sink, simulator = _open(config, note)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which says why
        ring.publish_status(_status(None, None, priority, state="failed",
                                    error=f"cannot open {config.spec}: {exc}"))
        ring.close()
        return

    def watch() -> None:  # stop when asked, or when the parent is gone
        while not term and not stop.wait(0.2):
            if os.getppid() != parent_pid:
                break
        acq.stop()

    threading.Thread(target=watch, name="imunoise-acq-watch", daemon=True).start()
    settle_heap()
    truth = _SimulatorTruth(simulator)
    ring.publish_status(_status(acq, recorder, priority, simulator=truth.status()))
    next_status = time.monotonic() + STATUS_EVERY_S
    error = None
    try:
        for batch in acq.batches():
            truth.first_block()
            # Each block is pickled once, for the analysis side's ring and the recorder's.
            payloads = [pickle.dumps(block, protocol=pickle.HIGHEST_PROTOCOL)
                        for block in batch]
            if sink is not None:
                for block, payload in zip(batch, payloads, strict=True):
                    sink.write(block, payload)
            for block, payload in zip(batch, payloads, strict=True):
                ring.put_bytes(payload, len(block), str(block.stream))
            now = time.monotonic()
            if now >= next_status:
                if recorder is not None:
                    recorder.check()
                ring.publish_status(_status(acq, recorder, priority,
                                            simulator=truth.status()))
                next_status = now + STATUS_EVERY_S
            if term or stop.is_set():
                break
    except Exception as exc:  # noqa: BLE001
        error = f"acquisition stopped: {type(exc).__name__}: {exc}"
    finally:
        acq.close()
        if sink is not None:
            counts = acq.stats.as_dict()
            sink.note("ok", "acquisition ended", {
                "event": "losses", "device_dropped": str(counts.get("dropped", 0)),
                "device_gaps": str(counts.get("gaps", 0)),
                "handover_lost": str(ring.lost_samples),
                "recording_lost": str(recorder.stats.lost_samples)})
            sink.close()
        if simulator is not None:
            simulator.stop()
        ring.publish_status(_status(acq, recorder, priority, error=error,
                                    simulator=truth.status()))
        ring.close()


# ----------------------------------------------------------------------------- the parent

class AcquisitionProcess:
    """The live service's source: blocks from the acquisition process.

    Args:
        config: the device and recording to run.
        ring_bytes: capacity of the hand-over ring.
        restart: start a new child when one dies (up to ``max_restarts`` times).
    """

    def __init__(self, config: AcquisitionConfig, ring_bytes: int = DEFAULT_CAPACITY,
                 restart: bool = True, max_restarts: int = 100) -> None:
        self.config = config
        self.ring = BlockRing(create=True, capacity=ring_bytes)
        self.restart = restart
        self.max_restarts = max_restarts
        self.restarts = 0
        self.last_exit: str | None = None
        self._ctx = mp.get_context("spawn")  # never fork a process that runs threads
        self._stop = self._ctx.Event()
        self._proc: Any = None
        self._stopping = False
        self._gap_next = False
        self._files: list[str] = []
        self._lock = threading.Lock()
        self._status: dict[str, Any] = {}
        self.config_reported: dict[str, str] = {}
        self._final: dict[str, Any] | None = None  # the last status, once the ring is released
        self._respawn_at: float | None = None  # when a dead child is to be replaced
        self._pause = RestartPause()
        # imunoise.live.kernel_workers.KernelWorkerKeeper, when asked
        self._kernel_workers: Any = None

    # -- life cycle
    def _spawn(self, note: str | None = None) -> None:
        self._pause.started()
        self._stop = self._ctx.Event()
        self._proc = self._ctx.Process(
            target=child_main, name="imunoise-acquisition",
            args=(self.config, self.ring.name, self._stop, os.getpid(), note), daemon=False)
        self._proc.start()

    def open(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Start the child and wait until it has opened the device (or failed to: raises
        ``imunoise.daq.errors.DeviceError`` with its reason)."""
        from imunoise.daq.errors import DeviceError

        if self.config.realtime_kernel_workers and self._kernel_workers is None:
            from imunoise.live.kernel_workers import KernelWorkerKeeper

            self._kernel_workers = KernelWorkerKeeper().start()
        self._spawn()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            st = self.ring.status()
            if st:
                if st.get("error"):
                    self._proc.join(5)
                    self.close()
                    raise DeviceError(st["error"])
                self.config_reported = dict(st.get("config") or {})
                return
            if not self._proc.is_alive():
                code = self._proc.exitcode
                self.close()
                raise DeviceError(f"the acquisition process ended at start (exit code {code})")
            time.sleep(0.02)
        self.stop()
        self.close()
        raise DeviceError(f"the acquisition process did not open {self.config.spec} "
                          f"within {timeout_s:g} s")

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    @property
    def kernel_workers(self) -> dict[str, Any] | None:
        """The kernel-worker keeper's status (``KernelWorkerBoost.status``), or None when
        the workers are left as they are."""
        return None if self._kernel_workers is None else self._kernel_workers.status()

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def stop(self) -> None:
        """Ask the child to finish its file and end; :meth:`blocks` then ends."""
        self._stopping = True
        self._stop.set()

    def close(self, timeout_s: float = 15.0) -> None:
        """Wait for the child (terminating it if it hangs) and release the ring."""
        self._stopping = True
        end_process(self._proc, self._stop, timeout_s, grace_s=5.0)
        self._remember_files()
        if self._kernel_workers is not None:
            self._kernel_workers.stop()
        if self._final is None:
            self._final = self.ring.status() or {}
            self._final_lost = (self.ring.lost_samples, self.ring.lost_blocks)
            self.ring.close()
            self.ring.unlink()

    def _read_status(self) -> dict[str, Any]:
        return self._final if self._final is not None else (self.ring.status() or {})

    def _lost(self) -> tuple[int, int]:
        if self._final is not None:
            return self._final_lost
        return self.ring.lost_samples, self.ring.lost_blocks

    def _remember_files(self) -> None:
        rec = self._read_status().get("recording") or {}
        with self._lock:
            for f in rec.get("files") or []:
                if f not in self._files:
                    self._files.append(f)

    # -- blocks
    def _check_child(self) -> bool:
        """True while blocks may still come: restart a dead child unless stopping. A child
        that ends soon after it started (a device that cannot be opened) is restarted after a
        growing pause (1, 2, 4 ... 30 s), not at once."""
        if self._respawn_at is not None:
            if self._stopping:
                return False
            if time.monotonic() < self._respawn_at:
                return True
            self._respawn_at = None
            self._spawn(note=f"acquisition restarted: the previous acquisition process ended "
                             f"({self.last_exit}); samples between the files are lost")
            return True
        if self._proc.is_alive():
            return True
        if self._stopping:
            return False
        code = self._proc.exitcode
        self.last_exit = describe_exit(code)
        self._remember_files()
        if not self.restart or self.restarts >= self.max_restarts:
            return False
        self.restarts += 1
        self._gap_next = True
        self._respawn_at = self._pause.ended()
        return self._check_child()

    def blocks(self):
        """Blocks as the child hands them over, with ``gap_before`` set where the hand-over
        or a restart lost samples; ends when the child has stopped and the ring is empty."""
        idle = 0.0
        while True:
            got = self.ring.get()
            if got is None:
                if not self._check_child():
                    got = self.ring.get()
                    if got is None:
                        return
                else:
                    time.sleep(0.005)
                    idle += 0.005
                    continue
            block, lost = got
            if self._gap_next:
                block.gap_before = -1  # a new process: how much was lost is not known
                self._gap_next = False
            elif lost and block.gap_before >= 0:
                block.gap_before += lost
            yield block

    # -- status
    @property
    def stats(self) -> dict[str, Any]:
        """The child's acquisition counters, the hand-over losses and the process state."""
        st = self._read_status()
        out = dict(st.get("acquisition") or {})
        if not self.alive and not self._stopping and self._proc is not None:
            out["state"] = "acquisition process down" + (f" ({self.last_exit})"
                                                         if self.last_exit else "")
        out["process"] = {"pid": st.get("pid"), "alive": self.alive, "restarts": self.restarts,
                          "last_exit": self.last_exit, "priority": st.get("priority"),
                          "simulator": st.get("simulator"),
                          "kernel_workers": self.kernel_workers}
        out["handover_lost_samples"], out["handover_lost_blocks"] = self._lost()
        out["recording"] = st.get("recording")
        if st.get("error"):
            out["last_error"] = st["error"]
        return out

    def recording(self) -> dict[str, Any]:
        """The child's recorder counters (file, files, samples), files of earlier children
        included."""
        rec = dict(self._read_status().get("recording") or {})
        with self._lock:
            files = list(self._files)
        for f in rec.get("files") or []:
            if f not in files:
                files.append(f)
        rec["files"] = files
        return rec
