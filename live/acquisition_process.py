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
        members: several devices at once (:mod:`imunoise.daq.device_group`): ``(spec, topic
            name, open_device keyword arguments)`` of each, read by one
            :class:`imunoise.daq.device_group.DeviceGroup` and recorded into one file; ``spec``
            and ``device_kwargs`` are then not used.
        member_processes: read each device of ``members`` in a process of its own
            (:class:`DeviceProcess`: an acquisition process without a recorder, as for a
            single device), this process merging their blocks into the recording and the
            analysis; False (the default): each on a thread of this process. On this 2-core
            host under a load average of 13 to 18 (other users), simulated ADIS16350 +
            razor under ``serve``, two 2-minute runs each, interleaved: threads lost 35 and
            25 ADIS16350 samples of 12,300 and 36 and 20 ITG-3200 samples of 24,100;
            processes 72 and 61, and 31 and 30 (four more processes at real-time priority
            on two cores wait for each other). With more cores than devices the processes
            may win; measure with bench/multi.py.
    """

    spec: str
    device_kwargs: dict[str, Any] = field(default_factory=dict)
    out: str | None = None
    record_rate_hz: float | None = None
    software: str = ""
    priority: str = "realtime"
    simulator_process: bool = True
    realtime_kernel_workers: bool = False
    members: list[tuple[str, str, dict[str, Any]]] | None = None
    member_processes: bool = False


# ----------------------------------------------------------------------------- the child


def _status(acq: Any, recorder: Any, priority: dict[str, Any], state: str | None = None,
            error: str | None = None, simulator: dict[str, Any] | None = None,
            handover_lost_by_device: dict[str, int] | None = None) -> dict[str, Any]:
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
            "lost_by_device": _by_device(getattr(rec, "lost_by_stream", None) or {}),
            "error": str(getattr(recorder, "error", "") or "") or None},
        "error": error,
        "simulator": simulator,
        "handover_lost_by_device": dict(handover_lost_by_device or {}),
        "time": time.time(),
    }


def _by_device(by_stream: dict[str, int]) -> dict[str, int]:
    from imunoise.daq.device_group import device_of_stream

    out: dict[str, int] = {}
    for stream, n in by_stream.items():
        out[device_of_stream(stream)] = out.get(device_of_stream(stream), 0) + int(n)
    return out


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


class _GroupTruth:
    """:class:`_SimulatorTruth` of each device of a group that has a simulator process."""

    def __init__(self, simulators: dict[str, Any], group: Any = None) -> None:
        self.truths = {name: _SimulatorTruth(sim) for name, sim in simulators.items()}
        self.group = group

    def first_block(self) -> None:
        for truth in self.truths.values():
            truth.first_block()

    def status(self) -> dict[str, Any] | None:
        out = {name: truth.status() for name, truth in self.truths.items()}
        for name, member in getattr(self.group, "members", []):
            sim = getattr(member, "simulator_status", None)
            if callable(sim) and sim() is not None:  # counted by the device's own process
                out[name] = sim()
        return out or None


def _open_one(spec: str, kwargs: dict[str, Any], config: AcquisitionConfig,
              clock: Any = None) -> tuple[Any, Any]:
    """One device (not yet opened) and its simulator process, if it has one."""
    from imunoise.analysis.noise_stream import stream_factory
    from imunoise.daq.devices import open_device

    kw = dict(kwargs)
    if clock is not None:
        kw["clock"] = clock
    if spec == "sim:adis16350" and config.simulator_process:
        from imunoise.live.simulator_process import SimulatorProcess

        simulator = SimulatorProcess(kw.get("rate_hz") or 102.4, kw.pop("seed", 0) or 0,
                                     config.priority, bench=kw.pop("bench", None))
        try:
            return open_device("adis16350", port=simulator.start(), **kw), simulator
        except Exception:
            simulator.stop()
            raise
    return open_device(spec, noise=stream_factory, **kw), None


def _open_group(config: AcquisitionConfig, note: str | None):
    """:func:`_open` for several devices: a DeviceGroup, one recorder, one sink."""
    from imunoise.daq.clock import RealClock
    from imunoise.daq.device_group import DeviceGroup
    from imunoise.live.recorder_process import RecorderProcess
    from imunoise.live.recorder_sink import GroupRecorderSink

    assert config.members
    clock = RealClock()  # one time base for every device
    opened: list[tuple[str, Any]] = []
    simulators: dict[str, Any] = {}
    group = recorder = sink = None
    try:
        for spec, name, kwargs in config.members:
            if config.member_processes:
                # every device's process starts at once: none polls while another one is
                # still importing and opening its device
                member = DeviceProcess(AcquisitionConfig(
                    spec, dict(kwargs), out=None, software=config.software,
                    priority=config.priority, simulator_process=config.simulator_process))
                opened.append((name, member))
                member.start()
                continue
            acq, simulator = _open_one(spec, kwargs, config, clock)
            opened.append((name, acq))
            if simulator is not None:
                simulators[name] = simulator
        group = DeviceGroup(opened, [spec for spec, _, _ in config.members])
        group.open()
        if config.out:
            recorder = RecorderProcess(
                {"out_dir": config.out, "device": "+".join(group.names),
                 "config": None, "rate_hz": None, "software": config.software,
                 "devices": {name: {"spec": spec, "config": dict(acq.config),
                                    "rate_hz": acq.rate_hz}
                             for (name, acq), (spec, _, _) in zip(opened, config.members,
                                                                  strict=True)}},
                config.priority).start()
            sink = GroupRecorderSink(recorder, group)
            if note:
                sink.note("warn", note, {"event": "acquisition_restart"})
    except Exception:
        if recorder is not None:
            recorder.close()
        for _, acq in opened:
            acq.close()
        for simulator in simulators.values():
            simulator.stop()
        raise
    return group, recorder, sink, simulators


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
                                         config.priority, bench=kw.pop("bench", None))
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


def _open_any(config: AcquisitionConfig, note: str | None):
    """(source, recorder, sink, simulators by topic name: ``""`` for a single device)."""
    if config.members:
        return _open_group(config, note)
    acq, recorder, sink, simulator = _open(config, note)
    return acq, recorder, sink, ({"": simulator} if simulator is not None else {})


def _hand_over(batch: list[Any], sink: Any, ring: BlockRing,
               lost_by_device: dict[str, int]) -> None:
    """A batch to the recorder and the analysis side's ring; blocks the ring cannot take
    are counted in ``lost_by_device`` (by topic name)."""
    # Each block is pickled once, for the analysis side's ring and the recorder's.
    payloads = [pickle.dumps(block, protocol=pickle.HIGHEST_PROTOCOL) for block in batch]
    if sink is not None:
        for block, payload in zip(batch, payloads, strict=True):
            sink.write(block, payload)
    for block, payload in zip(batch, payloads, strict=True):
        if not ring.put_bytes(payload, len(block), str(block.stream)):
            name = str(block.stream).lstrip("/").split("/", 1)[0]
            lost_by_device[name] = lost_by_device.get(name, 0) + len(block)


def _note_losses(sink: Any, acq: Any, recorder: Any, ring: BlockRing,
                 handover_by_device: dict[str, int] | None) -> None:
    """The run's losses as an event in the file (``handover_by_device``: a group's, which
    then get an event per device)."""
    counts = acq.stats.as_dict()
    if handover_by_device is None:
        sink.note("ok", "acquisition ended", {
            "event": "losses", "device_dropped": str(counts.get("dropped", 0)),
            "device_gaps": str(counts.get("gaps", 0)),
            "handover_lost": str(ring.lost_samples),
            "recording_lost": str(recorder.stats.lost_samples)})
        return
    rec_lost = _by_device(recorder.stats.lost_by_stream)
    for name, st in (counts.get("devices") or {}).items():
        sink.sinks[name].note("ok", "acquisition ended", {
            "event": "losses", "device_dropped": str(st.get("dropped", 0)),
            "device_gaps": str(st.get("gaps", 0)),
            "handover_lost": str(handover_by_device.get(name, 0)),
            "recording_lost": str(rec_lost.get(name, 0))})


def child_main(config: AcquisitionConfig, ring_name: str, stop: Any, parent_pid: int,
               note: str | None = None) -> None:
    """Entry point of the acquisition process."""
    term = TermFlag().install()  # the parent decides when to stop
    sys.setswitchinterval(GIL_SWITCH_S)
    priority = raise_priority(config.priority)
    ring = BlockRing(ring_name)
    what = (" + ".join(spec for spec, _, _ in config.members) if config.members
            else config.spec)
    try:
        acq, recorder, sink, simulators = _open_any(config, note)
    except Exception as exc:  # noqa: BLE001 - reported to the parent, which says why
        ring.publish_status(_status(None, None, priority, state="failed",
                                    error=f"cannot open {what}: {exc}"))
        ring.close()
        return

    def watch() -> None:  # stop when asked, or when the parent is gone
        while not term and not stop.wait(0.2):
            if os.getppid() != parent_pid:
                break
        acq.stop()

    threading.Thread(target=watch, name="imunoise-acq-watch", daemon=True).start()
    settle_heap()
    truth: Any = (_GroupTruth(simulators, acq) if config.members
                  else _SimulatorTruth(simulators.get("")))
    handover_lost: dict[str, int] = {}  # by device (topic name), for a group

    def status(**kw: Any) -> dict[str, Any]:
        return _status(acq, recorder, priority, simulator=truth.status(),
                       handover_lost_by_device=handover_lost, **kw)

    ring.publish_status(status())
    next_status = time.monotonic() + STATUS_EVERY_S
    error = None
    try:
        for batch in acq.batches():
            truth.first_block()
            _hand_over(batch, sink, ring, handover_lost)
            now = time.monotonic()
            if now >= next_status:
                if recorder is not None:
                    recorder.check()
                ring.publish_status(status())
                next_status = now + STATUS_EVERY_S
            if term or stop.is_set():
                break
    except Exception as exc:  # noqa: BLE001
        error = f"acquisition stopped: {type(exc).__name__}: {exc}"
    finally:
        acq.close()
        if sink is not None:
            _note_losses(sink, acq, recorder, ring, handover_lost if config.members else None)
            sink.close()
        for simulator in simulators.values():
            simulator.stop()
        ring.publish_status(status(error=error))
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
        self._gap_seen: set[str] = set()
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
        self.start()
        self.wait_opened(timeout_s)

    def start(self) -> None:
        """Start the child (:meth:`wait_opened` then waits for its device)."""
        if self.config.realtime_kernel_workers and self._kernel_workers is None:
            from imunoise.live.kernel_workers import KernelWorkerKeeper

            self._kernel_workers = KernelWorkerKeeper().start()
        self._spawn()

    def wait_opened(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Wait until the started child has opened the device (:meth:`open`)."""
        from imunoise.daq.errors import DeviceError

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
        self._gap_seen = set()
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
            if self._gap_next and self.config.members:
                # a new process: every stream of every device starts after a loss of unknown
                # length (the first block of each stream, once the child has been replaced)
                if block.stream not in self._gap_seen:
                    self._gap_seen.add(block.stream)
                    block.gap_before = -1
                    lost = 0
            elif self._gap_next:
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
        if self.config.members:
            out["handover_lost_by_device"] = dict(st.get("handover_lost_by_device") or {})
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


class _MemberStats:
    """A device process's counters (the dict its child publishes) read as attributes."""

    def __init__(self, stats: dict[str, Any]) -> None:
        self._stats = stats

    def __getattr__(self, key: str) -> Any:
        try:
            return self.__dict__["_stats"][key]
        except KeyError:
            raise AttributeError(key) from None

    def as_dict(self) -> dict[str, Any]:
        return dict(self._stats)


class DeviceProcess:
    """One device of a group read by an acquisition process of its own (no recorder), as an
    :class:`imunoise.daq.acquisition.Acquisition` for
    :class:`imunoise.daq.device_group.DeviceGroup`: each device keeps a process, an
    interpreter and a scheduling slot to itself, as it has alone, and what the merging
    process does with the blocks never delays a poll.

    Blocks come one per batch; samples its hand-over ring could not take reach the recording
    as a gap (counted in ``stats.handover_lost_samples``); a child that dies is restarted as
    for a single device.
    """

    def __init__(self, config: AcquisitionConfig) -> None:
        self.process = AcquisitionProcess(config)
        self._opened = False
        self._started = False

    def start(self) -> None:
        """Start the device's process without waiting for it (:meth:`open` waits)."""
        self.process.start()
        self._started = True

    def open(self) -> None:
        if not self._opened:
            if self._started:
                self.process.wait_opened()
            else:
                self.process.open()
            self._opened = True

    @property
    def config(self) -> dict[str, str]:
        return dict(self.process.config_reported)

    @property
    def rate_hz(self) -> float:
        return float(self.config.get("rate_hz", "nan"))

    @property
    def stats(self) -> _MemberStats:
        st = dict(self.process.stats)
        st.setdefault("state", "starting")
        for key in ("samples", "dropped", "gaps", "reconnects"):
            st.setdefault(key, 0)
        st.setdefault("last_error", "")
        return _MemberStats(st)

    def simulator_status(self) -> dict[str, Any] | None:
        return (self.process.stats.get("process") or {}).get("simulator")

    def batches(self, duration_s: float | None = None):
        """The device's blocks, one per batch, until it stops (``duration_s`` is not used:
        the group stops it)."""
        for block in self.process.blocks():
            yield [block]

    def stop(self) -> None:
        self.process.stop()

    def close(self) -> None:
        self.process.stop()
        self.process.close()
