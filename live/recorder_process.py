"""The MCAP recorder in a process of its own, fed by the acquisition process through a ring.

In the acquisition process, the recorder's writer thread (encoding a block of a 1 kHz ITG-3200
took 0.6 ms, and once a second a chunk is compressed and fsynced) shared the interpreter with
the polls of a device that has no FIFO, and the polls it held up lost samples. Here the
recorder runs in a child of the acquisition process; the acquisition process only pickles each
block (once, for both rings) and copies it into shared memory.

Two :class:`imunoise.live.block_ring.BlockRing` segments, both made by the acquisition process:

- the *feed* carries pickled records ``("block", wall, pickled SampleBlock)``,
  ``("event", wall, (level, message, fields, t))`` and ``("close", wall, None)`` in order. It
  never makes the acquisition process wait and holds :data:`FEED_BYTES` (minutes of any
  device), so a disk that stalls for a while loses nothing; a block that still does not fit is
  a loss of the recording, counted (``lost_samples``) and marked in the file as a gap before
  the next block of its stream.
- the *back* ring carries only the recorder's status (file, files, samples, error), which the
  acquisition process puts into its own.

A recorder process that dies is replaced by :meth:`RecorderProcess.check`: the new one attaches
to the same feed and goes on from the dead one's read position in a new file that starts with
an event saying what happened; what the dead one had read but not yet written is lost (at most
a flush interval, as when the acquisition process itself is killed). When the acquisition
process dies, its recorder writes what is left in the feed and closes its file.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import pickle
import signal
import time
from types import SimpleNamespace
from typing import Any

from imunoise.live.block_ring import BlockRing
from imunoise.live.restart_pause import RestartPause, describe_exit

FEED_BYTES = 64 * 1024 * 1024
"""Data area of the feed ring: about 2.5 min of an ADIS16350 at 819 Hz and 10 min of a 1 kHz
razor (113 kB/s of records, measured), before a recorder that cannot keep up loses blocks."""
START_TIMEOUT_S = 60.0
IDLE_SLEEP_S = 0.005
"""How long the recorder process sleeps when the feed is empty (seconds)."""
STATUS_EVERY_S = 0.25
PRIORITY_OF = {"realtime": "nice", "nice": "nice", "normal": "normal"}
"""The recorder's priority for the acquisition's: never SCHED_FIFO, whose compression and
fsync would take a core from the analysis side without need; the feed absorbs its delays."""


def _recorder_main(feed_name: str, back_name: str, recorder_args: dict[str, Any],
                   priority: str, parent_pid: int, note: str | None) -> None:
    """Entry point of the recorder process."""
    from imunoise.daq import ros2_msgs
    from imunoise.daq.recorder import McapRecorder
    from imunoise.live.process_priority import raise_priority, settle_heap

    # The acquisition process closes the file (a "close" record) after its last block and
    # event; a signal to the whole process group must not end the recorder before those.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise_priority(priority)
    feed, back = BlockRing(feed_name), BlockRing(back_name)
    try:
        recorder = McapRecorder(threaded=False, **recorder_args)
    except OSError as exc:
        back.publish_status({"state": "failed", "pid": os.getpid(), "error": str(exc)})
        return
    if note:
        recorder.event(ros2_msgs.WARN, note, {"event": "recorder_restart"})

    def publish(state: str) -> None:
        st = recorder.stats
        back.publish_status({"state": state, "pid": os.getpid(), "file": st.file,
                             "files": list(st.files), "samples": st.samples,
                             "blocks_dropped": st.blocks_dropped, "error": recorder.error})

    publish("recording")
    settle_heap()
    next_status = time.monotonic() + STATUS_EVERY_S
    orphaned = False
    try:
        while True:
            now = time.monotonic()
            if now >= next_status:  # also while catching up, so that a lag shows
                publish("recording")
                next_status = now + STATUS_EVERY_S
            got = feed.get_bytes()
            if got is None:
                if orphaned:
                    break  # the feed is drained
                if os.getppid() != parent_pid:
                    orphaned = True
                    continue  # one more pass: anything put before the acquisition died
                recorder.flush_if_due()
                time.sleep(IDLE_SLEEP_S)
                continue
            record, lost = got
            kind, wall, item = pickle.loads(record)
            if kind == "close":
                break
            if kind == "block":
                block = pickle.loads(item)
                if lost and block.gap_before >= 0:
                    block.gap_before += lost
                recorder.write(block, wall=wall)
            elif kind == "event":
                level, message, fields, t = item
                recorder.event(level, message, fields, t=t, wall=wall)
    finally:
        recorder.close()
        publish("closed")
        for ring in (feed, back):
            ring.close()
            if orphaned:  # nobody else is left to remove them
                ring.unlink(orphaned=True)


class RecorderProcess:
    """The acquisition process's handle on its recorder process.

    It takes the place of :class:`imunoise.daq.recorder.McapRecorder` for
    :class:`imunoise.live.recorder_sink.RecorderSink`: :meth:`write`, :meth:`event`, :meth:`close`,
    ``stats`` (``file``, ``files``, ``samples``, ``blocks_dropped``) and ``error``.

    Args:
        recorder_args: keyword arguments of ``McapRecorder`` (``out_dir``, ``device``,
            ``config``, ``rate_hz``, ``software``...; picklable).
        priority: the acquisition's priority mode (:data:`PRIORITY_OF` gives the recorder's).
        feed_bytes: data area of the feed ring.
    """

    def __init__(self, recorder_args: dict[str, Any], priority: str = "normal",
                 feed_bytes: int = FEED_BYTES) -> None:
        self.recorder_args = dict(recorder_args)
        self.priority = PRIORITY_OF.get(priority, "normal")
        self.feed = BlockRing(create=True, capacity=feed_bytes)
        self.back = BlockRing(create=True, capacity=4096)
        self.restarts = 0
        self.last_exit: str | None = None
        self._ctx = mp.get_context("spawn")
        self._proc: Any = None
        self._files: list[str] = []
        self._final: dict[str, Any] | None = None
        self._closing = False
        self._samples_before = 0  # samples written by recorder processes that died
        self._pause = RestartPause()
        self._respawn_at: float | None = None  # when a dead recorder is to be replaced
        self.lost_by_stream: dict[str, int] = {}  # samples the feed could not take

    # -- life cycle
    def _spawn(self, note: str | None = None) -> None:
        self._pause.started()
        self._proc = self._ctx.Process(
            target=_recorder_main, name="imunoise-recorder",
            args=(self.feed.name, self.back.name, self.recorder_args, self.priority,
                  os.getpid(), note))
        self._proc.start()

    def start(self, timeout_s: float = START_TIMEOUT_S) -> RecorderProcess:
        """Start the recorder process and wait until it can write (raises ``OSError`` with its
        reason when it cannot, e.g. an output folder that is not writable)."""
        self._spawn()
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            st = self.back.status()
            if st.get("state") == "failed":
                self._proc.join(5)
                self._release()
                raise OSError(st.get("error") or "the recorder process could not start")
            if st:
                return self
            if not self._proc.is_alive():
                code = self._proc.exitcode
                self._release()
                raise OSError(f"the recorder process ended at start ({describe_exit(code)})")
            time.sleep(0.02)
        self._proc.kill()
        self._proc.join(5)
        self._release()
        raise OSError(f"the recorder process did not start within {timeout_s:g} s")

    def check(self, *, now_or_never: bool = False) -> bool:
        """Replace a recorder process that died (True when it did); cheap, call it often.

        One that dies soon after its start (e.g. a folder that became unwritable) is replaced
        after a pause that doubles each time (:class:`imunoise.live.restart_pause.RestartPause`);
        the
        feed keeps what comes meanwhile. ``now_or_never``: no pause (at close)."""
        if self._closing or self._proc is None or self._proc.is_alive():
            return False
        if self._respawn_at is None:
            self.last_exit = describe_exit(self._proc.exitcode)
            last = self.back.status()
            self._remember_files(last)
            self._samples_before += int(last.get("samples") or 0)
            self._respawn_at = self._pause.ended()
        if time.monotonic() < self._respawn_at and not now_or_never:
            return False
        self._respawn_at = None
        self.restarts += 1
        self._spawn(note=f"recording restarted: the previous recorder process ended "
                         f"({self.last_exit}); samples it had not yet written are lost")
        return True

    def close(self, timeout_s: float = 60.0) -> None:
        """Ask the recorder to write everything handed to it and close its file; wait (a
        recorder found dead is replaced first, so that what the feed holds is written)."""
        if self._closing:
            return
        self.check(now_or_never=True)
        self._closing = True
        self._put("close", None, 0, "")
        if self._proc is not None:
            self._proc.join(timeout_s)
            if self._proc.is_alive():  # it ignores SIGTERM (see _recorder_main)
                self._proc.kill()
                self._proc.join(5)
        self._release()

    def _release(self) -> None:
        self._closing = True
        if self._final is None:
            self._final = self.back.status()
            self._remember_files(self._final)
            self._final_lost = self.feed.lost_samples, self.feed.lost_blocks
            for ring in (self.feed, self.back):
                ring.close()
                ring.unlink()

    # -- the recorder's interface
    def _put(self, kind: str, item: Any, n_samples: int, stream: str) -> None:
        if self._final is None:
            if not self.feed.put_bytes(pickle.dumps((kind, time.time(), item),
                                                    protocol=pickle.HIGHEST_PROTOCOL),
                                       n_samples, stream) and stream:
                self.lost_by_stream[stream] = self.lost_by_stream.get(stream, 0) + n_samples

    def write(self, block: Any, payload: bytes | None = None) -> None:
        """Hand a block to the recorder (never waits). ``payload``: the block already pickled,
        when the caller has it (the hand-over to the analysis pickles it too)."""
        if payload is None:
            payload = pickle.dumps(block, protocol=pickle.HIGHEST_PROTOCOL)
        self._put("block", payload, len(block), str(block.stream))

    def event(self, level: int, message: str, values: dict[str, str] | None = None,
              t: float | None = None) -> None:
        """A device-status event in the file (see ``McapRecorder.event``)."""
        self._put("event", (level, message, dict(values or {}), t), 0, "")

    # -- counters
    def _status(self) -> dict[str, Any]:
        return self._final if self._final is not None else self.back.status()

    def _remember_files(self, st: dict[str, Any]) -> None:
        for f in st.get("files") or []:
            if f not in self._files:
                self._files.append(f)

    def _lost(self) -> tuple[int, int]:
        if self._final is not None:
            return self._final_lost
        return self.feed.lost_samples, self.feed.lost_blocks

    @property
    def stats(self) -> SimpleNamespace:
        """``file``, ``files`` and ``samples`` (of every recorder process so far),
        ``blocks_dropped`` (the recorder's own and those the feed could not take),
        ``lost_samples`` (samples the feed could not take), ``restarts``, ``pid``,
        ``backlog_bytes`` (handed over and not yet read by the recorder)."""
        st = self._status()
        self._remember_files(st)
        lost_samples, lost_blocks = self._lost()
        return SimpleNamespace(
            file=st.get("file") or "", files=list(self._files),
            samples=self._samples_before + int(st.get("samples") or 0),
            blocks_dropped=int(st.get("blocks_dropped") or 0) + lost_blocks,
            lost_samples=lost_samples, lost_by_stream=dict(self.lost_by_stream),
            restarts=self.restarts, pid=st.get("pid"),
            backlog_bytes=0 if self._final is not None else self.feed.used_bytes)

    @property
    def error(self) -> str | None:
        st = self._status()
        if st.get("error"):
            return str(st["error"])
        if not self._closing and self._proc is not None and not self._proc.is_alive():
            return (f"the recorder process ended ({describe_exit(self._proc.exitcode)}); "
                    f"it is being replaced")
        return None

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None
