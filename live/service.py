"""The live service behind ``imunoise serve``: acquisition, recording and rolling analysis.

Three roles, two threads:

- the *acquisition thread* pulls blocks from the source (a device, a simulator or a replayed
  file) and hands each one to the recorder and to a queue for the analyzer. It never waits on
  analysis or HTTP: for a live device the queue is large and ``put_nowait`` is used, so a stalled
  analyzer costs analysis coverage (counted in ``health()``) but never a recorded sample;
- the *analysis thread* drains the queue into a :class:`imunoise.live.scheduler.RollingAnalyzer` and
  runs its fits and diagnoses one at a time, within the analyzer's CPU budget;
- HTTP handlers only read published results (and change a model, which refits that channel).
"""

from __future__ import annotations

import dataclasses
import queue
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, Protocol

from imunoise.live.coherence import LiveCoherence
from imunoise.live.scheduler import BlockLike, RollingAnalyzer


class Sink(Protocol):
    """A consumer of blocks that must not block the acquisition thread (e.g. the recorder)."""

    def write(self, block: BlockLike) -> None: ...

    def close(self) -> None: ...


def _as_dict(obj: Any) -> dict[str, Any]:
    if obj is None:
        return {}
    if isinstance(obj, dict):
        return dict(obj)
    if callable(getattr(obj, "as_dict", None)):  # counters that say how they read
        return dict(obj.as_dict())
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    return {k: v for k, v in vars(obj).items() if not k.startswith("_")}


def _jsonable(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, str | int | float | bool) or value is None:
        return value
    if hasattr(value, "item"):
        return value.item()
    return str(value)


class LiveService:
    """Acquisition + recording + rolling analysis, with a thread-safe view for the API.

    Args:
        source: a ``imunoise.daq.acquisition.Acquisition`` (its ``blocks()`` are iterated) or any
            iterable of sample blocks (a file reader, a generator). Its ``stats`` (a dict,
            dataclass or object), if any, are reported in ``health()``; its ``stop()`` and
            ``close()``, if any, are called on shutdown.
        analyzers: the rolling analyzers (a fresh :class:`RollingAnalyzer` by default).
        sinks: block consumers called on the acquisition thread, e.g. the recorder. Each
            ``write`` must return quickly (queue the work).
        device: description of the source for ``health()`` (spec, port, rate ...).
        realtime: True for a live device: never block the acquisition thread on a full
            analysis queue. False for a replayed file: apply back-pressure instead.
        queue_blocks: capacity of the analysis queue in blocks.
        current_file: callable returning the path of the file being written, if any.
    """

    def __init__(self, source: Iterable[BlockLike], analyzers: RollingAnalyzer | None = None,
                 sinks: Iterable[Sink] = (), device: dict[str, Any] | None = None,
                 realtime: bool = True, queue_blocks: int = 20000,
                 current_file: Callable[[], str | None] | None = None) -> None:
        self.source = source
        self.analyzers = analyzers if analyzers is not None else RollingAnalyzer()
        self.sinks = list(sinks)
        self.device = dict(device or {})
        self.realtime = realtime
        self._current_file = current_file
        self._queue: queue.Queue[BlockLike | None] = queue.Queue(maxsize=queue_blocks)
        self._stop = threading.Event()
        self._acq_done = threading.Event()
        self._abandon = False  # stopped while acquiring: running fits are abandoned
        self._threads: list[threading.Thread] = []
        # held while the threads start: a stop that arrives meanwhile (from a sink or a
        # signal) waits for both to exist, so that it joins the acquisition; reentrant for
        # a signal handler that runs on the starting thread
        self._life = threading.RLock()
        self._lock = threading.Lock()
        self.samples_received = 0
        self.blocks_received = 0
        self.samples_analysed = 0
        self.samples_not_analysed = 0
        self._not_analysed_by_stream: dict[str, int] = {}
        self.sink_errors = 0
        self.gaps_seen = 0
        self.error: str | None = None
        self.coherence = LiveCoherence()  # between each stream's channels (/coherence)
        self.started_at = time.time()
        self._last_block_t: float | None = None
        self._events = 0

    # --- life cycle ----------------------------------------------------------------------
    def start(self) -> LiveService:
        """Start the acquisition and analysis threads."""
        self.started_at = time.time()
        with self._life:
            for target, name in ((self._acquire, "imunoise-acquisition"),
                                 (self._analyse, "imunoise-analysis")):
                t = threading.Thread(target=target, name=name, daemon=True)
                t.start()
                self._threads.append(t)
        return self

    def stop_acquisition(self) -> None:
        """Ask the source to end now, as a stop signal arrives: the device is released and the
        file closed while the HTTP side still winds down (nothing else then shares the
        machine with the last samples). Cheap and safe in a signal handler; :meth:`stop`
        then finishes as for a stop while acquiring (running fits abandoned)."""
        if not self._acq_done.is_set():
            self._abandon = True
        self._stop_source()

    def _stop_source(self) -> None:
        stopper = getattr(self.source, "stop", None)
        if callable(stopper):
            try:
                stopper()
            except Exception:  # noqa: BLE001 - shutdown must go on
                pass

    def stop(self, timeout: float = 10.0) -> None:
        """Stop acquiring, close the sinks and the source. A source that ended by itself (a
        replay) has its analysis finished first (the final full fits, up to ``timeout``);
        a stop while acquiring abandons a running fit rather than wait for it."""
        self._abandon = self._abandon or not self._acq_done.is_set()
        self._stop.set()
        self._stop_source()
        with self._life:
            threads = list(self._threads)
        # the acquisition thread first: every block it took reaches the sinks
        for t in threads[:1]:
            t.join(timeout)
        closer = getattr(self.analyzers, "close", None)
        if self._abandon and callable(closer):
            closer()  # a fit running in the worker process is abandoned, not awaited
        for t in threads[1:]:
            t.join(timeout)
        if not self._abandon and callable(closer):
            closer()
        for sink in self.sinks:
            try:
                sink.close()
            except Exception as exc:  # noqa: BLE001
                self.error = f"closing {type(sink).__name__}: {exc}"
        closer = getattr(self.source, "close", None)
        if callable(closer):
            try:
                closer()
            except Exception:  # noqa: BLE001
                pass

    @property
    def running(self) -> bool:
        return not self._acq_done.is_set() and bool(self._threads)

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the source is exhausted (a replayed file) or stopped."""
        return self._acq_done.wait(timeout)

    # --- threads -------------------------------------------------------------------------
    def _acquire(self) -> None:
        # A source that can be stopped ends its blocks by itself, after handing out what it
        # has already read from the device (and counted): those blocks are still taken to
        # the sinks. Only a plain iterable is left at the stop.
        drains = callable(getattr(self.source, "stop", None))
        try:
            blocks = getattr(self.source, "blocks", None)
            for block in (blocks() if callable(blocks) else self.source):
                n = len(block.t) if hasattr(block, "t") else \
                    len(next(iter(block.channels.values()), ()))
                for sink in self.sinks:
                    try:
                        sink.write(block)
                    except Exception as exc:  # noqa: BLE001 - keep acquiring, report it
                        self.sink_errors += 1
                        self.error = f"{type(sink).__name__}: {exc}"
                with self._lock:
                    self.samples_received += n
                    self.blocks_received += 1
                    if getattr(block, "gap_before", 0) != 0 and self.blocks_received > 1:
                        self.gaps_seen += 1
                    self._last_block_t = time.time()
                if self.realtime:
                    try:
                        self._queue.put_nowait(block)
                    except queue.Full:
                        with self._lock:
                            self.samples_not_analysed += n
                            stream = str(getattr(block, "stream", ""))
                            self._not_analysed_by_stream[stream] = \
                                self._not_analysed_by_stream.get(stream, 0) + n
                else:
                    while not self._stop.is_set():
                        try:
                            self._queue.put(block, timeout=0.2)
                            break
                        except queue.Full:
                            continue
                if self._stop.is_set() and not drains:
                    break
        except Exception as exc:  # noqa: BLE001 - the service stays up and reports it
            self.error = f"acquisition stopped: {type(exc).__name__}: {exc}"
        finally:
            self._acq_done.set()
            self._queue.put(None)

    def _analyse(self) -> None:
        while True:
            try:
                block = self._queue.get(timeout=0.25)
            except queue.Empty:
                block = False
            batch = [] if block is False else [block]
            while True:  # drain what is there, then refit once
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            done = False
            for b in batch:
                if b is None:
                    done = True
                    continue
                self._update(b)
            if self._abandon:
                # stopped while acquiring: no more fits, but the blocks already handed over
                # still reach the streaming estimates (cheap), so none is left uncounted
                if not done:
                    self._update_until_end()
                return
            try:
                self.analyzers.refresh(force=done)
            except Exception as exc:  # noqa: BLE001
                if not self._abandon:
                    self.error = f"refit: {type(exc).__name__}: {exc}"
            if done:
                return

    def _update(self, block: BlockLike) -> None:
        try:
            self.analyzers.update(block)
            self.coherence.update(block)
        except Exception as exc:  # noqa: BLE001 - bad block: report, keep going
            self.error = f"analysis: {type(exc).__name__}: {exc}"
        n = len(block.t) if hasattr(block, "t") else 0
        with self._lock:
            self.samples_analysed += n

    def _update_until_end(self, wait_s: float = 2.0) -> None:
        """Take the blocks still queued up to the acquisition's end mark (waiting at most
        ``wait_s`` for each) into the streaming estimates."""
        while True:
            try:
                block = self._queue.get(timeout=wait_s)
            except queue.Empty:
                return
            if block is None:
                return
            self._update(block)

    # --- views ---------------------------------------------------------------------------
    def current_file(self) -> str | None:
        if self._current_file is None:
            return None
        try:
            path = self._current_file()
        except Exception:  # noqa: BLE001
            return None
        return str(path) if path else None

    def source_stats(self) -> dict[str, Any]:
        return _jsonable(_as_dict(getattr(self.source, "stats", None)))

    def health(self) -> dict[str, Any]:
        """Liveness, device state, counts of samples received/dropped, the file being written."""
        stats = self.source_stats()
        with self._lock:
            last = self._last_block_t
            counts = {
                "received": self.samples_received,
                "analysed": self.samples_analysed,
                "not_analysed": self.samples_not_analysed,
                "dropped": int(stats.get("dropped", 0) or 0),
            }
            gaps = max(self.gaps_seen, int(stats.get("gaps", 0) or 0))
        state = stats.get("state") or stats.get("device_state")
        if state is None:
            state = "streaming" if self.running else ("finished" if self._acq_done.is_set()
                                                      else "starting")
        now = time.time()
        process = stats.pop("process", None)
        rec_stats = stats.pop("recording", None)
        losses = {"device": counts["dropped"],
                  "handover": int(stats.get("handover_lost_samples", 0) or 0),
                  "analysis": counts["not_analysed"],
                  "recording": int((rec_stats or {}).get("lost_samples") or 0)}
        recording: dict[str, Any] = {"file": self.current_file(), "sink_errors": self.sink_errors}
        if rec_stats:
            recording.update({k: rec_stats.get(k) for k in (
                "samples", "files", "blocks_dropped", "lost_samples", "backlog_bytes", "pid",
                "restarts", "error")})
        status = "ok" if self.error is None else "degraded"
        if process is not None and not process.get("alive") and self.running:
            status = "degraded"
        out = {
            "status": status,
            "uptime_s": now - self.started_at,
            "acquiring": self.running,
            "device": dict(self.device, state=str(state), stats=stats),
            "samples": counts,
            "gaps": gaps,
            "last_block_age_s": (now - last) if last else None,
            "losses": losses,
            "acquisition_process": process,
            "recording": recording,
            "channels": self.analyzers.channels,
            "analysis": _jsonable(self.analyzers.stats()),
            "error": self.error,
        }
        if isinstance(stats.get("devices"), dict):
            out["devices"] = self._devices(stats, rec_stats or {}, out["channels"])
        return out

    def _devices(self, stats: dict[str, Any], rec_stats: dict[str, Any],
                 channels: list[str]) -> list[dict[str, Any]]:
        """Each device of a group: its state, samples, losses by stage and channels."""
        described = {d.get("name"): d for d in self.device.get("devices") or []}
        handover = stats.get("handover_lost_by_device") or {}
        recording = rec_stats.get("lost_by_device") or {}
        with self._lock:
            not_analysed: dict[str, int] = {}
            for stream, n in self._not_analysed_by_stream.items():
                name = stream.lstrip("/").split("/", 1)[0]
                not_analysed[name] = not_analysed.get(name, 0) + n
        out = []
        for name, st in stats["devices"].items():
            out.append({
                **{k: v for k, v in described.get(name, {}).items() if k != "name"},
                "name": name, "state": st.get("state"), "samples": st.get("samples", 0),
                "gaps": st.get("gaps", 0), "reconnects": st.get("reconnects", 0),
                "last_error": st.get("last_error") or None,
                "losses": {"device": int(st.get("dropped", 0) or 0),
                           "handover": int(handover.get(name, 0) or 0),
                           "analysis": int(not_analysed.get(name, 0)),
                           # a device read in a process of its own hands its blocks to the
                           # recording through a ring: what that could not take is a gap
                           "recording": int(recording.get(name, 0) or 0)
                           + int(st.get("handover_lost_samples", 0) or 0)},
                "channels": [c for c in channels if c.startswith(f"/{name}/")],
            })
        return out

    @property
    def revision(self) -> int:
        """Changes whenever anything the dashboard shows may have changed."""
        with self._lock:
            return self.analyzers.revision * 1_000_003 + self.blocks_received // 50 + self.gaps_seen
