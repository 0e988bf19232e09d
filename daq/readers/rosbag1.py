"""ROS 1 bags (format 2.0): ``sensor_msgs/Imu`` and ``sensor_msgs/Temperature`` on any topic.

Most existing IMU calibration data (Kalibr, allan_variance_ros and imu_utils users) is ROS 1.
The bag is read front to back, chunk by chunk (uncompressed, bz2 or lz4), so that a bag cut
short (a recorder killed before it wrote its index) is read up to its last complete chunk, with
a warning, as ``imunoise repair`` does for MCAP. Messages are decoded in bulk: within a chunk
every Imu message with the same ``frame_id`` length has one fixed binary layout, which numpy
reads as a structured array, instead of one Python object per message. Time is
``header.stamp``; ``header.seq`` decides where samples are missing when the publisher numbered
its messages (see :mod:`imunoise.core.timing`).

Format facts (ROS wiki, "Bags/Format/2.0"): records are ``<header length u32><header><data
length u32><data>``; header fields are ``<field length u32>name=value``; ``op`` 0x03 bag header,
0x05 chunk (``compression``, ``size``), 0x07 connection (``conn``, ``topic``; the data holds
``type``, ``md5sum`` ...), 0x02 message data (``conn``, ``time``), 0x04 index, 0x06 chunk info.
"""

from __future__ import annotations

import bz2
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imunoise.core.record import Record
from imunoise.core.series import SAMPLE_LIMIT, ChannelSeries, usable_samples
from imunoise.core.timing import analyse_stamps
from imunoise.daq.errors import ReadError

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_BAG_HEADER, OP_INDEX, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = (
    0x02, 0x03, 0x04, 0x05, 0x06, 0x07)
IMU_TYPE = "sensor_msgs/Imu"
TEMPERATURE_TYPE = "sensor_msgs/Temperature"
GYRO = ("gyro_x", "gyro_y", "gyro_z")
ACCEL = ("accel_x", "accel_y", "accel_z")
_U32 = struct.Struct("<I")
# sensor_msgs/Imu after its header: orientation (4), orientation_covariance (9),
# angular_velocity (3) and its covariance (9), linear_acceleration (3) and its covariance (9)
_IMU_BODY = [("q", "<f8", 4), ("q_cov", "<f8", 9), ("w", "<f8", 3), ("w_cov", "<f8", 9),
             ("a", "<f8", 3), ("a_cov", "<f8", 9)]
_TEMPERATURE_BODY = [("temperature", "<f8"), ("variance", "<f8")]


class Rosbag1Error(ReadError):
    """Not a ROS 1 bag, or one with no readable Imu or Temperature message."""


@dataclass
class _Stream:
    """Decoded columns of one topic, gathered chunk by chunk."""

    topic: str
    kind: str  # "imu" or "temperature"
    parts: dict[str, list[np.ndarray]] = field(default_factory=dict)

    def add(self, name: str, values: np.ndarray) -> None:
        self.parts.setdefault(name, []).append(values)

    def column(self, name: str) -> np.ndarray:
        """One column of every message decoded so far, in file order."""
        if name not in self.parts:
            return np.zeros(0)
        values = np.concatenate(self.parts[name])
        order = np.concatenate(self.parts["order"])
        if order.size > 1 and np.any(np.diff(order) < 0):
            values = values[np.argsort(order, kind="stable")]
        return values


def _fields(header: bytes | memoryview) -> dict[str, bytes]:
    """The ``name=value`` fields of a record header."""
    out: dict[str, bytes] = {}
    pos, end = 0, len(header)
    while pos + 4 <= end:
        (n,) = _U32.unpack_from(header, pos)
        item = bytes(header[pos + 4:pos + 4 + n])
        pos += 4 + n
        name, _, value = item.partition(b"=")
        out[name.decode("latin-1")] = value
    return out


def _records(buf: bytes | memoryview, start: int = 0):
    """(header, data, end offset) of each complete record from ``start``; stops at the first
    record that runs past the end of ``buf``."""
    pos, end = start, len(buf)
    while pos + 4 <= end:
        (hlen,) = _U32.unpack_from(buf, pos)
        if pos + 8 + hlen > end:
            return
        (dlen,) = _U32.unpack_from(buf, pos + 4 + hlen)
        stop = pos + 8 + hlen + dlen
        if stop > end:
            return
        yield buf[pos + 4:pos + 4 + hlen], buf[pos + 8 + hlen:stop], stop
        pos = stop


def _decompress(kind: bytes, data: bytes | memoryview, size: int) -> bytes:
    if kind == b"none":
        return bytes(data)
    if kind == b"bz2":
        return bz2.decompress(data)
    if kind == b"lz4":
        import lz4.frame

        # bounded: a damaged frame header cannot make it claim gigabytes
        return lz4.frame.LZ4FrameDecompressor().decompress(
            bytes(data), max_length=2 * size + (1 << 20))
    raise Rosbag1Error(f"unknown chunk compression {kind.decode('latin-1', 'replace')[:20]!r}")


def _message_layout(kind: str, frame_len: int) -> np.dtype:
    head = [("seq", "<u4"), ("sec", "<u4"), ("nsec", "<u4"), ("frame_len", "<u4")]
    if frame_len:
        head.append(("frame", f"V{frame_len}"))
    return np.dtype(head + (_IMU_BODY if kind == "imu" else _TEMPERATURE_BODY))


def _decode(stream: _Stream, buf: bytes, starts: np.ndarray, size: int, chunk_no: int) -> None:
    """Decode the messages of one topic and one data length found in chunk ``chunk_no``; their
    place in the file is kept (``order``) since lengths can alternate."""
    raw = np.frombuffer(buf, dtype=np.uint8)
    frame_len = int(_U32.unpack_from(buf, int(starts[0]) + 12)[0])
    layout = _message_layout(stream.kind, frame_len)
    if layout.itemsize != size:
        raise Rosbag1Error(f"{stream.topic}: a message of {size} bytes does not have the "
                           f"{stream.kind} layout")
    rows = raw[starts[:, None] + np.arange(size)].view(layout).ravel()
    if np.any(rows["frame_len"] != frame_len):  # same size, other frame_id lengths: regroup
        for length in np.unique(rows["frame_len"]):
            _decode(stream, buf, starts[rows["frame_len"] == length], size, chunk_no)
        return
    stream.add("order", (np.int64(chunk_no) << 32) + starts)
    stream.add("seq", rows["seq"].astype(np.int64))
    stream.add("t", rows["sec"].astype(np.int64) * 1_000_000_000 + rows["nsec"])
    if stream.kind == "imu":
        stream.add("w", np.array(rows["w"]))
        stream.add("a", np.array(rows["a"]))
        stream.add("w_cov0", np.array(rows["w_cov"][:, 0]))
        stream.add("a_cov0", np.array(rows["a_cov"][:, 0]))
    else:
        stream.add("temp", np.array(rows["temperature"]))


def _connection(header: bytes | memoryview, data: bytes | memoryview
                ) -> tuple[int, str, str]:
    h, d = _fields(header), _fields(data)
    return (_U32.unpack(h["conn"])[0],
            h.get("topic", d.get("topic", b"")).decode("utf-8", "replace")[:200],
            d.get("type", b"").decode("utf-8", "replace")[:200])


def _first_line(exc: BaseException, limit: int = 80) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:limit]


def _scan_chunk(buf: bytes, conns: dict[int, tuple[str, str]],
                streams: dict[int, _Stream], chunk_no: int) -> None:
    """Connections and messages of one decompressed chunk; when it fails, nothing of the
    chunk is kept (the streams are as before)."""
    known = set(streams)
    sizes = {cid: {k: len(v) for k, v in s.parts.items()} for cid, s in streams.items()}
    try:
        _scan_chunk_records(buf, conns, streams, chunk_no)
    except _DAMAGE:
        for cid in set(streams) - known:
            del streams[cid]
        for cid, lengths in sizes.items():
            parts = streams[cid].parts
            for k in list(parts):
                del parts[k][lengths.get(k, 0):]
        raise


def _scan_chunk_records(buf: bytes, conns: dict[int, tuple[str, str]],
                        streams: dict[int, _Stream], chunk_no: int) -> None:
    groups: dict[tuple[int, int], list[int]] = {}
    for header, data, stop in _records(buf):
        h = bytes(header)
        op = h[h.find(b"op=") + 3] if b"op=" in h else -1
        if op == OP_CONNECTION:
            cid, topic, msgtype = _connection(header, data)
            conns[cid] = (topic, msgtype)
        elif op == OP_MESSAGE:
            at = h.find(b"conn=")
            cid = _U32.unpack_from(h, at + 5)[0]
            if cid in streams:
                groups.setdefault((cid, len(data)), []).append(stop - len(data))
            elif cid in conns and conns[cid][1] in (IMU_TYPE, TEMPERATURE_TYPE):
                topic, msgtype = conns[cid]
                streams[cid] = _Stream(topic, "imu" if msgtype == IMU_TYPE else "temperature")
                groups.setdefault((cid, len(data)), []).append(stop - len(data))
    for (cid, size), starts in groups.items():
        _decode(streams[cid], buf, np.asarray(starts, dtype=np.int64), size, chunk_no)


# What damaged record bytes make the parsing raise.
_DAMAGE = (Rosbag1Error, struct.error, ValueError, IndexError, KeyError, TypeError,
           OverflowError, MemoryError, OSError, RuntimeError, EOFError)


def _scan(path: Path) -> tuple[dict[int, _Stream], list[str]]:
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        raise Rosbag1Error(f"{path.name}: not a ROS 1 bag (no '#ROSBAG V2.0' line)")
    conns: dict[int, tuple[str, str]] = {}
    streams: dict[int, _Stream] = {}
    warnings: list[str] = []
    view = memoryview(data)
    end = len(MAGIC)
    indexed = False
    chunks = 0
    for header, body, stop in _records(view, len(MAGIC)):
        at, end = end, stop
        try:
            h = _fields(header)
            op = (h.get("op") or b"\xff")[0]
            if op == OP_BAG_HEADER:
                index_pos = struct.unpack("<Q", h.get("index_pos", b"\0" * 8))[0]
                indexed = 0 < index_pos <= len(data)
            elif op == OP_CHUNK:
                size = _U32.unpack(h.get("size", b"\0\0\0\0"))[0]
                chunk = _decompress(h.get("compression", b"none"), body, size)
                _scan_chunk(chunk, conns, streams, chunks)
                chunks += 1
            elif op == OP_CONNECTION:
                cid, topic, msgtype = _connection(header, body)
                conns[cid] = (topic, msgtype)
        except _DAMAGE as exc:
            warnings.append(f"{path.name}: a damaged record at byte {at} was skipped "
                            f"({_first_line(exc)}); its messages are lost (a gap)")
    if end < len(data) or not indexed:
        tail = f", {len(data) - end} bytes of an unfinished record" if end < len(data) else ""
        warnings.append(f"{path.name}: the bag was cut short (no index{tail}); read up to its "
                        "last complete chunk")
    return streams, warnings


def _series(name: str, values: np.ndarray, timing, units: str) -> ChannelSeries:
    return ChannelSeries(name=name, units=units, fs_hz=timing.fs_hz,
                         values=np.ascontiguousarray(values, dtype=np.float64),
                         segment_starts=timing.segment_starts, t0_s=timing.t0_s)


def _seq_or_none(seq: np.ndarray) -> np.ndarray | None:
    """Sequence numbers when the publisher numbered its messages (strictly increasing)."""
    return seq if seq.size > 1 and np.all(np.diff(seq) > 0) else None


def read_rosbag1(path: str | Path, rate_hz: float | None = None) -> Record:
    """Every Imu and Temperature topic of a ROS 1 bag as a Record (SI units, gap-free
    segments); ``rate_hz`` overrides the rate inferred from the stamps."""
    path = Path(path)
    streams, warnings = _scan(path)
    imu = [s for s in streams.values() if s.kind == "imu" and s.parts]
    temps = [s for s in streams.values() if s.kind == "temperature" and s.parts]
    if not imu and not temps:
        raise Rosbag1Error(f"{path.name}: no sensor_msgs/Imu or sensor_msgs/Temperature "
                           "messages")
    channels: dict[str, ChannelSeries] = {}
    timings: dict[str, dict] = {}
    for s in imu:
        t, seq = s.column("t"), s.column("seq")
        w, a = s.column("w"), s.column("a")
        keep = usable_samples(w).all(axis=1) & usable_samples(a).all(axis=1)
        if not keep.all():
            warnings.append(f"{s.topic}: {int((~keep).sum())} message(s) with non-finite "
                            f"values or values beyond {SAMPLE_LIMIT:g} dropped (treated as gaps)")
            t, seq, w, a = t[keep], seq[keep], w[keep], a[keep]
        if t.size < 2:
            warnings.append(f"{s.topic}: fewer than two messages; left out")
            continue
        try:
            timing = analyse_stamps(t, seq=_seq_or_none(seq) if keep.all() else None,
                                    rate_hz=rate_hz, name=s.topic)
        except ValueError as exc:
            raise Rosbag1Error(f"{path.name}: {s.topic}: {exc}") from None
        warnings.extend(timing.notes)
        timings[s.topic] = timing.facts()
        label = f"{s.topic}:" if len(imu) > 1 else ""
        present = [(GYRO, w, "rad/s", s.column("w_cov0")),
                   (ACCEL, a, "m/s^2", s.column("a_cov0"))]
        for names, arr, units, cov0 in present:
            if cov0.size and np.all(cov0 == -1.0):  # REP 145: -1 marks a field not provided
                continue
            for i, name in enumerate(names):
                channels[label + name] = _series(label + name, arr[:, i], timing, units)
    temperature = None
    if temps:
        s = temps[0]
        if len(temps) > 1:
            warnings.append(f"several temperature topics: using {s.topic}")
        t, v = s.column("t"), s.column("temp")
        keep = usable_samples(v)
        try:
            timing = analyse_stamps(t[keep], name=s.topic) if keep.sum() >= 2 else None
        except ValueError:
            warnings.append(f"{s.topic}: the temperature's time stamps never increase; left out")
            timing = None
        if timing is not None:
            temperature = _series("temp", v[keep], timing, "degC")
    if not channels and temperature is None:
        raise Rosbag1Error(f"{path.name}: no usable Imu or Temperature messages")
    metadata = {"format": "rosbag1", "topics": ",".join(s.topic for s in streams.values())}
    if channels:
        metadata["fs_hz"] = f"{next(iter(channels.values())).fs_hz:.9g}"
    return Record(source=str(path), channels=channels, temperature=temperature,
                  metadata=metadata, warnings=warnings,
                  facts={"timing": timings} if timings else {})
