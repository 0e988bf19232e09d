"""Crash-safe recording of sample blocks into ROS 2 MCAP files.

One :class:`McapRecorder` per device. Each file is a ROS 2 bag (profile ``ros2``): Imu on
``/<device>/imu``, Temperature on ``/<device>/temperature``, gap and device-status events as
``diagnostic_msgs/msg/DiagnosticArray`` on ``/diagnostics``, zstd chunks with message indexes,
rosbag2-style channel metadata, and an ``imunoise`` metadata record (device, configuration, scale
factors, rate, software version).

Crash safety:
- the open chunk is closed, written and fsync'ed at least every ``flush_s`` seconds (wall clock
  or sample time, whichever comes first), so kill -9 or a power cut loses at most that much;
- files rotate every ``rotate_s`` seconds and are named by their start time (UTC);
- on a write error (disk full) the file is cut back to the end of the last complete flush, a
  small reserve file kept in the output directory is released, and the summary is appended so
  that the file stays a complete, indexed MCAP; the recorder then stops with ``error`` set.

Writing happens on a background thread (``threaded=True``), so a slow disk never stalls the
acquisition loop; :meth:`McapRecorder.write` only queues the block.
"""

from __future__ import annotations

import errno
import os
import queue
import re
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from imunoise.core.blocks import SampleBlock
from imunoise.daq import ros2_msgs as msgs
from imunoise.daq.mcap_writer import McapBlockWriter

SOFTWARE = "imunoise"
GYRO = ("gyro_x", "gyro_y", "gyro_z")
ACCEL = ("accel_x", "accel_y", "accel_z")
TEMP = "temp"
DIAGNOSTICS_TOPIC = "/diagnostics"
METADATA_NAME = "imunoise"
RESERVE_NAME = ".imunoise-reserve"
_POLL_S = 0.1


class SyncedFile:
    """Unbuffered file with explicit fsync and a record of the last durable offset.

    The MCAP writer writes whole records through :meth:`write`; after each writer flush the
    recorder calls :meth:`sync`, which fsyncs and remembers the offset as a clean cut point.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self.pos = 0
        self.synced = 0

    def write(self, data: bytes | memoryview) -> int:
        view = memoryview(data)
        total = len(view)
        while view:
            n = os.write(self.fd, view)
            self.pos += n
            view = view[n:]
        return total

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def sync(self, fsync: bool = True) -> None:
        if fsync:
            os.fsync(self.fd)
        self.synced = self.pos

    def truncate_to_synced(self) -> None:
        os.ftruncate(self.fd, self.synced)
        os.lseek(self.fd, self.synced, os.SEEK_SET)
        self.pos = self.synced

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


@dataclass
class RecorderStats:
    """Counters for the status line; sizes in bytes, times in seconds."""

    samples: int = 0  # inertial samples (Imu messages)
    messages: int = 0
    files: list[str] = field(default_factory=list)
    file: str = ""
    bytes_written: int = 0
    events: int = 0
    blocks_dropped: int = 0
    raw_mismatch: int = 0
    last_flush_wall: float = 0.0


def _safe_name(device: str) -> str:
    name = device.split(":")[-1]
    return re.sub(r"[^A-Za-z0-9_]", "_", name) or "imu"


def affine_from_raw(raw: np.ndarray, values: np.ndarray) -> tuple[float, float] | None:
    """(scale, offset) with ``values = offset + scale * raw`` from two distinct raw points, or
    None if the block has fewer than two distinct raw values."""
    raw = np.asarray(raw, dtype=np.float64)
    values = np.asarray(values, dtype=np.float64)
    ok = np.isfinite(values)
    raw, values = raw[ok], values[ok]
    if raw.size < 2:
        return None
    i, j = int(np.argmin(raw)), int(np.argmax(raw))
    if raw[i] == raw[j]:
        return None
    scale = (values[j] - values[i]) / (raw[j] - raw[i])
    return float(scale), float(values[i] - scale * raw[i])


def raw_recoverable(raw: np.ndarray, values: np.ndarray, scale: float, offset: float) -> bool:
    """True when ``round((values - offset) / scale)`` gives back ``raw`` exactly."""
    finite = np.isfinite(values)
    back = np.rint((values[finite] - offset) / scale)
    return bool(np.array_equal(back, np.asarray(raw)[finite]))


class McapRecorder:
    """Record the sample blocks of one device into rotating, crash-safe ROS 2 MCAP files.

    Args:
        out_dir: directory for the files (created if missing).
        device: device name, e.g. ``"adis16350"`` or ``"sim:adis16350"`` (the topic prefix is
            the name without ``sim:``).
        config: device configuration written to the metadata record.
        scales: per channel ``(scale, offset)`` in SI units per count, so that
            ``value = offset + scale * raw``; channels with raw counts but no entry get theirs
            from the first block (and every block is checked to reproduce its counts exactly).
        rate_hz: nominal sampling rate (metadata); taken from the blocks when None.
        rotate_s: start a new file after this many seconds (None: never).
        flush_s: close, write and fsync the open chunk at least this often (seconds).
        fsync: call fsync on each flush (turn off only for throwaway files).
        frame_id: ``header.frame_id`` of every message (default ``<device>_link``).
        threaded: write from a background thread; ``write`` then only queues.
        clock: wall clock in seconds (for log times, flush and rotation timing).
        reserve_bytes: size of the reserve file released on a full disk to finish the file.
        chunk_size: uncompressed chunk size threshold in bytes.
        software: the writing program and its version (MCAP header and metadata), passed in
            by the command line (``daq`` does not import it).
        devices: several devices in one file: topic name (the first path component of its
            streams, :mod:`imunoise.daq.device_group`) -> ``{"spec", "config", "rate_hz",
            "scales"}``. Each device's topics then carry ``frame_id`` ``<name>_link``, its
            scale factors are keyed ``scale.<topic>:<channel>`` (``scale./razor/itg3200/imu:
            gyro_x``) and its description ``device.<name>.spec``, ``device.<name>.rate_hz``,
            ``device.<name>.config.<key>``; ``devices`` lists the names. ``device`` then
            names the file (``adis16350+razor`` -> ``adis16350_razor_<UTC>.mcap``).
    """

    def __init__(self, out_dir: str | Path, device: str, *, config: dict[str, str] | None = None,
                 scales: dict[str, tuple[float, float]] | None = None,
                 rate_hz: float | None = None, rotate_s: float | None = 3600.0,
                 flush_s: float = 1.0, fsync: bool = True, frame_id: str | None = None,
                 threaded: bool = True, clock: Callable[[], float] = time.time,
                 reserve_bytes: int = 2 << 20, chunk_size: int = 1 << 20,
                 file_opener: Callable[[Path], SyncedFile] = SyncedFile,
                 queue_blocks: int = 4096, software: str = SOFTWARE,
                 devices: dict[str, dict] | None = None) -> None:
        self.out_dir = Path(out_dir)
        self.devices = {name: dict(d) for name, d in (devices or {}).items()}
        self.software = software
        self.device = device
        self.name = _safe_name(device)
        self.config = dict(config or {})
        self.scales: dict[str, tuple[float, float]] = dict(scales or {})
        for d in self.devices.values():
            for key, value in (d.get("scales") or {}).items():  # "<topic>:<channel>"
                self.scales[key] = tuple(value)
        self.rate_hz = rate_hz
        self.rotate_s = rotate_s
        self.flush_s = flush_s
        # The writer thread checks every _POLL_S, so flushing _POLL_S early keeps the data at
        # risk (written but not yet durable) within flush_s of wall-clock time.
        self._flush_wall_s = max(flush_s - _POLL_S, flush_s / 2)
        self.fsync = fsync
        self.frame_id = frame_id if frame_id is not None else f"{self.name}_link"
        self.clock = clock
        self.reserve_bytes = reserve_bytes
        self.chunk_size = chunk_size
        self._opener = file_opener
        self.stats = RecorderStats()
        self.error: str | None = None
        self._writer: McapBlockWriter | None = None
        self._file: SyncedFile | None = None
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence: dict[int, int] = {}
        self._file_t0_wall = 0.0
        self._file_t0_sample: float | None = None
        self._flush_t_sample: float | None = None
        self._dirty = False
        self._closed = False
        self._last_log: dict[str, int] = {}
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self._reserve = self.out_dir / RESERVE_NAME
        self._make_reserve()
        self._queue: queue.Queue | None = None
        self._thread: threading.Thread | None = None
        if threaded:
            self._queue = queue.Queue(maxsize=queue_blocks)
            self._thread = threading.Thread(target=self._run, name=f"recorder-{self.name}",
                                            daemon=True)
            self._thread.start()

    # ---- public API -------------------------------------------------------------------------

    def write(self, block: SampleBlock, wall: float | None = None) -> None:
        """Record one block (queued when threaded). Raises nothing; check :attr:`error`.

        ``wall``: when the block was received (seconds, the recorder's clock); default now. A
        recorder fed from another process passes the time the block was handed to it."""
        if self.error or self._closed:
            return
        wall = self.clock() if wall is None else wall
        if self._queue is None:
            self._guarded(self._write_block, block, wall)
            return
        try:
            self._queue.put(("block", block, wall), timeout=1.0)
        except queue.Full:
            self.stats.blocks_dropped += 1

    def event(self, level: int, message: str, values: dict[str, str] | None = None,
              t: float | None = None, wall: float | None = None) -> None:
        """Record a device-status event (``ros2_msgs.OK/WARN/ERROR/STALE``) at time ``t``
        (seconds, sample time base; default: ``wall``), received at ``wall`` (seconds, the
        recorder's clock; default now)."""
        if self.error or self._closed:
            return
        item = ("event", (level, message, dict(values or {}), t),
                self.clock() if wall is None else wall)
        if self._queue is None:
            self._guarded(self._write_event, *item[1], item[2])
        else:
            try:
                self._queue.put(item, timeout=1.0)
            except queue.Full:
                self.stats.blocks_dropped += 1

    def flush(self) -> None:
        """Write and fsync everything recorded so far (waits for the writer thread)."""
        if self._queue is not None and self._thread is not None:
            done = threading.Event()
            self._queue.put(("flush", done, 0.0))
            while not done.wait(0.5) and self._thread.is_alive():
                pass
        else:
            self._guarded(self._flush)

    def flush_if_due(self) -> None:
        """Without a writer thread: write and fsync what is recorded once ``flush_s`` has
        passed since the last flush (the caller's idle loop calls this; with the thread, the
        thread does it)."""
        if (self._queue is None and self._dirty and not self._closed
                and self.clock() - self.stats.last_flush_wall >= self._flush_wall_s):
            self._guarded(self._flush)

    def close(self) -> None:
        """Finish the current file (summary, footer) and release the reserve file."""
        if self._closed:
            return
        if self._queue is not None and self._thread is not None:
            self._queue.put(("close", None, 0.0))
            self._thread.join()
        else:
            self._guarded(self._finish_file)
        self._closed = True
        self._release_reserve()

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ---- writer thread ----------------------------------------------------------------------

    def _run(self) -> None:
        assert self._queue is not None
        while True:
            try:
                kind, item, wall = self._queue.get(timeout=min(_POLL_S, self.flush_s / 4))
            except queue.Empty:
                if self._dirty and self.clock() - self.stats.last_flush_wall >= self._flush_wall_s:
                    self._guarded(self._flush)
                continue
            if kind == "close":
                self._guarded(self._finish_file)
                return
            if kind == "flush":
                self._guarded(self._flush)
                item.set()
                continue
            if self.error:
                continue
            if kind == "block":
                self._guarded(self._write_block, item, wall)
            else:
                self._guarded(self._write_event, *item, wall)

    def _guarded(self, fn: Callable, *args: object) -> None:
        if self.error:
            return
        try:
            fn(*args)
        except OSError as exc:
            self._on_write_error(exc)
        except Exception as exc:  # noqa: BLE001 - a bad block must not lose the file
            self.error = f"recording stopped: {type(exc).__name__}: {exc}"
            try:
                self._finish_file()
            except Exception:  # noqa: BLE001 - the data already flushed stays readable
                pass

    # ---- files ------------------------------------------------------------------------------

    def _make_reserve(self) -> None:
        if self.reserve_bytes <= 0:
            return
        try:
            with open(self._reserve, "wb") as f:
                f.write(b"\0" * self.reserve_bytes)
                f.flush()
                os.fsync(f.fileno())
        except OSError as exc:
            self._release_reserve()
            raise OSError(exc.errno, f"cannot write to {self.out_dir}: {exc.strerror}") from exc

    def _release_reserve(self) -> None:
        try:
            self._reserve.unlink()
        except FileNotFoundError:
            pass

    def _file_path(self, wall: float) -> Path:
        stamp = datetime.fromtimestamp(wall, UTC).strftime("%Y%m%dT%H%M%SZ")
        path = self.out_dir / f"{self.name}_{stamp}.mcap"
        k = 1
        while path.exists():
            path = self.out_dir / f"{self.name}_{stamp}_{k}.mcap"
            k += 1
        return path

    def _open_file(self, wall: float, block: SampleBlock | None) -> None:
        path = self._file_path(wall)
        self._file = self._opener(path)
        self._writer = McapBlockWriter(self._file, chunk_size=self.chunk_size)
        self._writer.start(profile=msgs.PROFILE, library=self.software)
        self._channels.clear()
        self._schemas.clear()
        self._sequence.clear()
        self._file_t0_wall = wall
        self._file_t0_sample = None
        self._writer.add_metadata(METADATA_NAME, self._metadata(block))
        self._file.sync(self.fsync)
        if self.fsync:
            _fsync_dir(self.out_dir)  # the new name must survive a power cut too
        self.stats.files.append(str(path))
        self.stats.file = str(path)

    def _metadata(self, block: SampleBlock | None) -> dict[str, str]:
        md = {"device": self.device, "software": self.software,
              "frame_id": self.frame_id, "units.gyro": "rad/s", "units.accel": "m/s^2",
              "units.temp": "degC", "time_base": "header.stamp = sensor sample time (s), "
              "log_time = host receive time"}
        rate = self.rate_hz or (block.fs_hz if block is not None and not self.devices
                                else None)
        if rate:
            md["rate_hz"] = repr(float(rate))
        for key, value in self.config.items():
            md[f"config.{key}"] = str(value)
        for ch, (scale, offset) in sorted(self.scales.items()):
            md[f"scale.{ch}"] = repr(scale)
            md[f"offset.{ch}"] = repr(offset)
        if self.devices:
            md.pop("frame_id")
            md["devices"] = ",".join(self.devices)
            for name, d in self.devices.items():
                md[f"device.{name}.spec"] = str(d.get("spec", name))
                md[f"device.{name}.frame_id"] = f"{name}_link"
                if d.get("rate_hz"):
                    md[f"device.{name}.rate_hz"] = repr(float(d["rate_hz"]))
                for key, value in (d.get("config") or {}).items():
                    md[f"device.{name}.config.{key}"] = str(value)
        return md

    def _channel(self, topic: str, msgtype: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            assert self._writer is not None
            sid = self._schemas.get(msgtype)
            if sid is None:
                sid = self._writer.register_schema(
                    msgtype, msgs.SCHEMA_ENCODING, msgs.SCHEMA_TEXT[msgtype].encode())
                self._schemas[msgtype] = sid
            cid = self._writer.register_channel(topic, msgs.MESSAGE_ENCODING, sid,
                                                msgs.channel_metadata(msgtype))
            self._channels[topic] = cid
            self._sequence[cid] = 0
        return cid

    def _flush(self) -> None:
        if self._writer is None or self._file is None:
            return
        self._writer.flush()
        self._file.sync(self.fsync)
        self.stats.bytes_written = sum(_size(p) for p in self.stats.files[:-1]) + self._file.pos
        self.stats.last_flush_wall = self.clock()
        self._dirty = False

    def _finish_file(self) -> None:
        if self._writer is None or self._file is None:
            return
        self._writer.finish()
        self._file.sync(self.fsync)
        self._file.close()
        self.stats.bytes_written = sum(_size(p) for p in self.stats.files)
        self._writer = None
        self._file = None

    def _on_write_error(self, exc: OSError) -> None:
        """Cut the file back to its last durable state, finish it, and stop recording."""
        path = self._file.path if self._file is not None else self.out_dir
        reason = "disk full" if exc.errno in (errno.ENOSPC, errno.EDQUOT) else str(exc.strerror)
        finished = False
        if self._file is not None:
            from imunoise.daq.repair import finish_in_place

            self._release_reserve()
            try:
                self._file.truncate_to_synced()
                self._file.close()
                finish_in_place(path)
                finished = True
            except Exception:  # noqa: BLE001 - leave the clean cut if the summary cannot fit
                try:
                    os.truncate(path, self._file.synced)
                except OSError:
                    pass
            self._file = None
            self._writer = None
        saved = "complete and indexed" if finished else "readable up to the last flush"
        self.error = (f"{reason} while writing {path}: recording stopped; the file is {saved} "
                      f"({self.stats.samples} samples recorded)")

    # ---- encoding ---------------------------------------------------------------------------

    def _maybe_rotate_or_open(self, wall: float, block: SampleBlock) -> None:
        if self._writer is None:
            self._open_file(wall, block)
            return
        if self.rotate_s is None:
            return
        t_first = float(block.t[0]) if len(block) else None
        by_wall = wall - self._file_t0_wall >= self.rotate_s
        by_sample = (t_first is not None and self._file_t0_sample is not None
                     and t_first - self._file_t0_sample >= self.rotate_s)
        if by_wall or by_sample:
            self._finish_file()
            self._open_file(wall, block)

    def _log_times(self, stream: str, t: np.ndarray, wall: float) -> np.ndarray:
        """Log times in ns: the host receive time of the block, back-dated per sample by the
        sample spacing, and never earlier than the stream's previous log time (so log-time
        order equals sample order for every reader)."""
        t_ns = np.rint(t * 1e9).astype(np.int64)
        shift = int(round(wall * 1e9)) - int(t_ns[-1])
        prev = self._last_log.get(stream)
        if prev is not None:
            shift = max(shift, prev + 1 - int(t_ns[0]))
        log = np.maximum(t_ns + shift, 0)
        self._last_log[stream] = int(log[-1])
        return log

    def _scale_key(self, block: SampleBlock, ch: str) -> str:
        """The channel's key in :attr:`scales`: the channel, or with several devices
        ``<topic>:<channel>``."""
        return f"{block.stream}:{ch}" if self.devices else ch

    def _check_raw(self, block: SampleBlock) -> None:
        for ch, raw in block.raw.items():
            values = block.channels.get(ch)
            if values is None or len(raw) == 0:
                continue
            key = self._scale_key(block, ch)
            if key not in self.scales:
                fit = affine_from_raw(raw, values)
                if fit is None:
                    continue
                self.scales[key] = fit
                if self._writer is not None:
                    self._writer.add_metadata(f"{METADATA_NAME}.scale",
                                              {f"scale.{key}": repr(fit[0]),
                                               f"offset.{key}": repr(fit[1])})
            scale, offset = self.scales[key]
            if not raw_recoverable(raw, values, scale, offset):
                self.stats.raw_mismatch += 1

    def _write_block(self, block: SampleBlock, wall: float) -> None:
        n = len(block)
        if n == 0:
            return
        t = np.asarray(block.t, dtype=np.float64)
        pending_scales = [ch for ch in block.raw if self._scale_key(block, ch) not in self.scales]
        if pending_scales and self._writer is None:
            for ch in pending_scales:
                fit = affine_from_raw(block.raw[ch], block.channels.get(ch, np.empty(0)))
                if fit is not None:
                    self.scales[self._scale_key(block, ch)] = fit
        self._maybe_rotate_or_open(wall, block)
        assert self._writer is not None
        self._check_raw(block)
        if self._file_t0_sample is None:
            self._file_t0_sample = float(t[0])
        if self._flush_t_sample is None:
            self._flush_t_sample = float(t[0])
        if block.gap_before:
            missing = "unknown" if block.gap_before < 0 else str(block.gap_before)
            self._write_event(msgs.WARN, f"gap: {missing} samples missing before this time",
                              {"event": "gap", "stream": block.stream,
                               "missing_samples": missing}, float(t[0]), wall)
        base = block.stream if block.stream.startswith("/") else f"/{self.name}/imu"
        prefix = base.rsplit("/", 1)[0] if base.count("/") > 1 else f"/{self.name}"
        log_ns = self._log_times(block.stream, t, wall)
        frame_id = (f"{prefix.lstrip('/').split('/', 1)[0]}_link" if self.devices
                    else self.frame_id)
        ch = block.channels
        has_gyro = all(c in ch for c in GYRO)
        has_accel = all(c in ch for c in ACCEL)
        if has_gyro or has_accel:
            gyro = np.column_stack([ch[c] for c in GYRO]) if has_gyro else None
            accel = np.column_stack([ch[c] for c in ACCEL]) if has_accel else None
            rec = msgs.encode_imu(t, gyro, accel, frame_id)
            self._add_messages(self._channel(f"{prefix}/imu", msgs.IMU), rec, log_ns)
        if TEMP in ch:
            rec = msgs.encode_temperature(t, np.asarray(ch[TEMP], dtype=np.float64),
                                          frame_id=frame_id)
            self._add_messages(self._channel(f"{prefix}/temperature", msgs.TEMPERATURE), rec,
                               log_ns)
        if has_gyro or has_accel:
            self.stats.samples += n
        self._dirty = True
        if (wall - self.stats.last_flush_wall >= self._flush_wall_s
                or float(t[-1]) - self._flush_t_sample >= self.flush_s):
            self._flush()
            self._flush_t_sample = float(t[-1])

    def _add_messages(self, cid: int, rec: np.ndarray, log_ns: np.ndarray) -> None:
        assert self._writer is not None
        payload = rec.view(np.uint8).reshape(len(rec), rec.dtype.itemsize)
        seq0 = self._sequence[cid]
        self._writer.add_messages(cid, log_ns, payload, seq0)
        self._sequence[cid] = seq0 + len(rec)
        self.stats.messages += len(rec)

    def _write_event(self, level: int, message: str, values: dict[str, str], t: float | None,
                     wall: float) -> None:
        if self._writer is None:
            self._open_file(wall, None)
        assert self._writer is not None
        t_event = wall if t is None else t
        payload = msgs.encode_diagnostic_array(
            t_event, [(level, f"{self.name}/acquisition", message, self.device,
                       sorted(values.items()))])
        cid = self._channel(DIAGNOSTICS_TOPIC, msgs.DIAGNOSTIC_ARRAY)
        log = max(int(round((wall if t is None else t) * 1e9)), 0)
        self._writer.add_message(cid, log, payload, log, self._sequence[cid])
        self._sequence[cid] += 1
        self.stats.events += 1
        self._dirty = True


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _size(path: str) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0
