"""Bulk numpy reader for ROS 2 MCAP files with ``sensor_msgs/msg/Imu`` and ``Temperature``.

The Imu and Temperature CDR layouts are fixed once ``header.frame_id`` is fixed, so instead of
decoding message by message the reader decompresses a batch of chunks, takes the message
offsets from the MessageIndex records (or walks the chunk when a file has none), checks every
message (opcode, record length, XCDR1 little-endian encapsulation, frame_id length) and gathers
the stamp, angular velocity, linear acceleration and temperature fields with one vectorised
indexing operation per field. Memory stays bounded: the file is read one batch of chunks at a
time with ``pread``; :func:`read_mcap` preallocates its output from the index counts.

Topics are chosen by schema name. A file this reader cannot take (message records outside
chunks, frame_id length changing within a topic, big-endian or XCDR2 payloads) raises
:class:`UnsupportedLayout`, and :func:`daq.readers.open_record` falls back to rosbags.
Crashed or truncated files are read up to the last complete chunk, with a warning.
"""

from __future__ import annotations

import mmap
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from core.blocks import SampleBlock
from core.record import Record
from core.series import ChannelSeries
from core.timing import Timing, analyse_stamps, relative_seconds, segment_starts_from_times
from daq import mcap_layout as ml
from daq import ros2_msgs as msgs

GYRO = ("gyro_x", "gyro_y", "gyro_z")
ACCEL = ("accel_x", "accel_y", "accel_z")
BATCH_BYTES = 1 << 20  # uncompressed bytes decoded per batch (cache-sized: gathers stay hot)
_PAYLOAD = ml.RECORD_PREFIX + ml.MESSAGE_HEADER  # record start -> CDR payload


class UnsupportedLayout(Exception):
    """The bulk reader cannot decode this file; a per-message reader can."""


@dataclass
class _Topic:
    cid: int
    topic: str
    kind: str  # "imu" or "temperature"
    payload_len: int = 0
    body: int = 0
    frame_len: int = -1
    has_gyro: bool = True
    has_accel: bool = True
    count: int = 0


@dataclass
class McapSource:
    """An opened MCAP file: layout, chosen topics and metadata."""

    path: Path
    layout: ml.McapLayout
    topics: dict[int, _Topic]
    metadata: dict[str, str]
    warnings: list[str] = field(default_factory=list)


def open_mcap(path: str | Path) -> McapSource:
    """Scan ``path`` and choose its Imu and Temperature channels by schema name."""
    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise ml.McapFormatError("empty file")
    with open(path, "rb") as f:
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            layout = ml.scan(buf, size)
        except (ml.McapFormatError, ValueError, OverflowError) as exc:
            raise ml.McapFormatError(str(exc)) from exc
        except Exception as exc:  # struct.error and friends on a damaged file
            raise ml.McapFormatError(f"damaged MCAP records ({exc})") from exc
        finally:
            buf.close()
    topics: dict[int, _Topic] = {}
    for cid, ch in sorted(layout.channels.items()):
        schema = layout.schemas.get(ch.schema_id)
        if schema is None or ch.message_encoding != msgs.MESSAGE_ENCODING:
            continue
        if schema.name == msgs.IMU:
            topics[cid] = _Topic(cid, ch.topic, "imu")
        elif schema.name == msgs.TEMPERATURE:
            topics[cid] = _Topic(cid, ch.topic, "temperature")
    metadata: dict[str, str] = {"profile": layout.profile, "library": layout.library}
    for md in layout.metadata:
        for key, value in md.data.items():
            metadata[key if md.name.startswith("imunoise") else f"{md.name}.{key}"] = value
    src = McapSource(path, layout, topics, metadata, list(layout.warnings))
    if layout.unchunked_messages:
        raise UnsupportedLayout("messages outside chunks")
    for c in layout.chunks:
        for cid, (_pos, n) in c.mi.items():
            if cid in topics:
                topics[cid].count += n
    return src


def _batches(chunks: list[ml.ChunkInfo]) -> Iterator[list[ml.ChunkInfo]]:
    batch: list[ml.ChunkInfo] = []
    nbytes = 0
    for c in chunks:
        batch.append(c)
        nbytes += c.uncompressed_size
        if nbytes >= BATCH_BYTES:
            yield batch
            batch, nbytes = [], 0
    if batch:
        yield batch


def _overlapping(buf: np.ndarray, dtype: str) -> np.ndarray:
    """View of ``buf`` (uint8) whose element i is the ``dtype`` value starting at byte i, so
    that a field at any byte offset is read with one vectorised ``take``."""
    size = np.dtype(dtype).itemsize
    return np.ndarray(shape=(max(buf.size - size + 1, 0),), dtype=dtype, buffer=buf,
                      strides=(1,))


def _setup_topic(tp: _Topic, blob: np.ndarray, first: int) -> None:
    """Fix the payload layout of a topic from its first message."""
    p = first + _PAYLOAD
    if bytes(blob[p:p + 2]) != b"\x00\x01":
        raise UnsupportedLayout(f"{tp.topic}: payload is not XCDR1 little-endian")
    tp.frame_len = int(blob[p + 12:p + 16].view("<u4")[0])
    tp.body = msgs.body_offset(tp.frame_len)
    tail = msgs.IMU_TAIL if tp.kind == "imu" else msgs.TEMPERATURE_TAIL
    tp.payload_len = tp.body + tail
    if tp.kind == "imu":
        b = p + tp.body
        gcov = blob[b + msgs.IMU_GYRO_COV_OFFSET:b + msgs.IMU_GYRO_COV_OFFSET + 8].view("<f8")
        acov = blob[b + msgs.IMU_ACCEL_COV_OFFSET:b + msgs.IMU_ACCEL_COV_OFFSET + 8].view("<f8")
        tp.has_gyro = bool(gcov[0] != -1.0)
        tp.has_accel = bool(acov[0] != -1.0)


def _load_batch(fd: int, batch: list[ml.ChunkInfo], scratch: np.ndarray | None = None
                ) -> tuple[bytes, np.ndarray, list[int]]:
    """Read consecutive chunks with their message indexes and decompress them into one buffer:
    (file region, decompressed records, offset of each chunk in them).

    The records go into ``scratch`` (uint8) when it is large enough: reusing one buffer per
    batch avoids mapping fresh memory for every batch, which costs more than decompressing."""
    start, stop = batch[0].start, batch[-1].mi_end
    region = os.pread(fd, stop - start, start)
    if len(region) != stop - start:
        raise ml.McapFormatError("file shrank while being read")
    sizes = [c.uncompressed_size for c in batch]
    need = sum(sizes)
    out = scratch if scratch is not None and scratch.size >= need else np.empty(need, np.uint8)
    if len(batch) > 1 and all(c.compression == "zstd" for c in batch) and min(sizes) > 0:
        view = memoryview(region)
        frames = [view[c.data_offset - start:c.data_offset - start + c.data_length]
                  for c in batch]
        parts = ml.decompress_zstd_frames(frames, sizes)
        if parts is not None:
            np.concatenate([np.frombuffer(p, np.uint8) for p in parts], out=out[:need])
            bases = np.concatenate(([0], np.cumsum(sizes[:-1]))).tolist()
            return region, out[:need], bases
    bases, base = [], 0
    for c in batch:
        a = c.data_offset - start
        data = ml.decompress(c.compression, memoryview(region)[a:a + c.data_length],
                             c.uncompressed_size)
        n = len(data)
        if base + n > out.size:  # a chunk longer than its header says: keep all of it
            grown = np.empty(max(2 * out.size, base + n), np.uint8)
            grown[:base] = out[:base]
            out = grown
        out[base:base + n] = np.frombuffer(data, np.uint8)
        bases.append(base)
        base += n
    return region, out[:base], bases


Sink = Callable[[_Topic, int], dict[str, np.ndarray]]


def _columns(tp: _Topic) -> list[str]:
    if tp.kind == "temperature":
        return ["t", "temp"]
    return ["t"] + (list(GYRO) if tp.has_gyro else []) + (list(ACCEL) if tp.has_accel else [])


def _decode_batch(src: McapSource, batch: list[ml.ChunkInfo],
                  loaded: tuple[bytes, np.ndarray, list[int]], sink: Sink | None = None
                  ) -> dict[int, dict[str, np.ndarray]]:
    """Decode the chosen topics of consecutive chunks: {cid: {"t": ..., field: ...}}; with a
    ``sink``, into the arrays it hands out for (topic, message count)."""
    region, blob, bases = loaded
    start = batch[0].start
    region_u8 = np.frombuffer(region, np.uint8)
    views = {dt: _overlapping(blob, dt) for dt in (f"V{_HEAD.itemsize}", "V24", "<f8")}
    out: dict[int, dict[str, np.ndarray]] = {}
    for cid, tp in src.topics.items():
        pos_l, cnt_l, base_l, walked = [], [], [], []
        for k, c in enumerate(batch):
            entry = c.mi.get(cid)
            if entry is not None:
                if entry[1]:
                    pos_l.append(entry[0] - start)
                    cnt_l.append(entry[1])
                    base_l.append(bases[k])
            elif not c.has_index:
                offs = _walk_offsets(blob[bases[k]:bases[k] + c.uncompressed_size], cid)
                if offs.size:
                    walked.append(offs + bases[k])
        offsets = []
        if cnt_l:
            cnt = np.asarray(cnt_l, dtype=np.int64)
            total = int(cnt.sum())
            first = np.repeat(np.cumsum(cnt) - cnt, cnt)
            idx = np.repeat(np.asarray(pos_l, dtype=np.int64), cnt) + 16 * (
                np.arange(total, dtype=np.int64) - first) + 8
            rel = _overlapping(region_u8, "<u8")[idx].astype(np.int64)
            offsets.append(rel + np.repeat(np.asarray(base_l, dtype=np.int64), cnt))
        offsets.extend(walked)
        if not offsets:
            continue
        rec = np.concatenate(offsets) if len(offsets) > 1 else offsets[0]
        if rec.size == 0:
            continue
        if rec.min() < 0 or rec.max() + _PAYLOAD > blob.size:
            raise ml.McapFormatError(f"{tp.topic}: message index points outside its chunk")
        if tp.frame_len < 0:
            _setup_topic(tp, blob, int(rec[0]))
        dest = sink(tp, rec.size) if sink is not None else {
            name: np.empty(rec.size, np.int64 if name == "t" else np.float64)
            for name in _columns(tp)}
        out[cid] = _decode_topic(tp, blob, rec, views, dest)
    return out


def _walk_offsets(records: np.ndarray, cid: int) -> np.ndarray:
    offs = []
    buf = records.data
    for op, a, _b in ml.iter_records(buf, 0, len(records)):
        if op == ml.OP_MESSAGE and int.from_bytes(buf[a:a + 2], "little") == cid:
            offs.append(a - ml.RECORD_PREFIX)
    return np.asarray(offs, dtype=np.int64)


# Record start to the end of the CDR header fields, read in one gather per message. (Padded to
# 48 bytes: numpy's gather of odd-sized opaque items is 20 times slower.)
_HEAD = np.dtype([("op", "u1"), ("rlen", "<u8"), ("_mcap", "V22"), ("encap", "<u2"),
                  ("_opts", "V2"), ("sec", "<i4"), ("nanosec", "<u4"), ("frame_len", "<u4"),
                  ("_pad", "V1")])
_VEC3 = np.dtype([("x", "<f8"), ("y", "<f8"), ("z", "<f8")])


def _decode_topic(tp: _Topic, blob: np.ndarray, rec: np.ndarray, views: dict[str, np.ndarray],
                  dest: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Check and decode the messages of one topic at record offsets ``rec`` in ``blob`` into
    the arrays ``dest`` (one per column of :func:`_columns`, each of ``len(rec)``).

    Fields are gathered as opaque byte groups (one per message for the record and CDR header,
    one per vector), then reinterpreted: far fewer gathers than one per scalar."""
    if rec.max() + _PAYLOAD + tp.payload_len > blob.size:
        raise UnsupportedLayout(f"{tp.topic}: message longer than its chunk")
    head = views[f"V{_HEAD.itemsize}"][rec].view(_HEAD)
    if not np.all(head["op"] == ml.OP_MESSAGE):
        raise ml.McapFormatError(f"{tp.topic}: message index does not point at messages")
    if (not np.all(head["encap"] == 0x0100)
            or not np.all(head["frame_len"] == tp.frame_len)
            or not np.all(head["rlen"] == ml.MESSAGE_HEADER + tp.payload_len)):
        raise UnsupportedLayout(
            f"{tp.topic}: messages differ in layout (frame_id length or encoding)")
    t = dest["t"]
    t[:] = head["sec"]
    t *= 1_000_000_000
    t += head["nanosec"]
    body = rec + (_PAYLOAD + tp.body)
    if tp.kind == "imu":
        v24 = views["V24"]
        for present, offset, names in ((tp.has_gyro, msgs.IMU_GYRO_OFFSET, GYRO),
                                       (tp.has_accel, msgs.IMU_ACCEL_OFFSET, ACCEL)):
            if present:
                vec = v24[body + offset].view(_VEC3)
                for axis, name in zip("xyz", names, strict=True):
                    dest[name][:] = vec[axis]
    else:
        dest["temp"][:] = views["<f8"][body]
    return dest


READ_AHEAD: bool | None = None
"""Read and decompress the next batch on a second thread while this one is decoded: True,
False, or None to decide per read (only when a core is idle, see :func:`read_ahead`)."""


def read_ahead() -> bool:
    """Whether :func:`iter_decoded` reads ahead on a second thread. By default only when the
    one-minute load average leaves a core idle: on a busy machine the second thread gets no
    core of its own, and handing batches over between threads then costs more CPU and wall
    time than it saves (measured on the replay benchmark)."""
    if READ_AHEAD is not None:
        return READ_AHEAD
    cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()[0]
    except OSError:
        return cores > 1
    return cores > 1 and load <= cores - 1


def iter_decoded(src: McapSource, sink: Sink | None = None
                 ) -> Iterator[dict[int, dict[str, np.ndarray]]]:
    """Decoded batches of the source's topics, in file order. With :func:`read_ahead`, the
    next batch is read and decompressed on a second thread (zstd and pread release the GIL)
    while this one is decoded; at most two batches are in memory."""
    batches = list(_batches(src.layout.chunks))
    if not batches:
        return
    size = max(sum(c.uncompressed_size for c in b) for b in batches)
    if not read_ahead():
        scratch = np.empty(size, np.uint8)
        with open(src.path, "rb") as f:
            for batch in batches:
                yield _decode_batch(src, batch, _load_batch(f.fileno(), batch, scratch), sink)
        return
    # Two buffers in turn: the next batch is decompressed into one while this one is decoded
    # from the other (decoding copies everything it keeps).
    buffers = [np.empty(size, np.uint8), np.empty(size, np.uint8)]
    with open(src.path, "rb") as f, ThreadPoolExecutor(max_workers=1) as pool:
        fd = f.fileno()
        pending = pool.submit(_load_batch, fd, batches[0], buffers[0])
        for i, batch in enumerate(batches):
            loaded = pending.result()
            if i + 1 < len(batches):
                pending = pool.submit(_load_batch, fd, batches[i + 1], buffers[(i + 1) % 2])
            yield _decode_batch(src, batch, loaded, sink)
            del loaded


def _split(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v for k, v in data.items() if k != "t"}


def topic_timing(ns: np.ndarray, name: str, metadata: dict[str, str] | None = None,
                 rate_hz: float | None = None) -> Timing:
    """Timing of one topic's int64 nanosecond stamps (:func:`core.timing.analyse_stamps`); with
    fewer than two increasing stamps the rate comes from the ``rate_hz`` metadata, else
    ValueError. A given ``rate_hz`` replaces the inferred rate."""
    try:
        return analyse_stamps(ns, rate_hz=rate_hz, name=name)
    except ValueError:
        fs = float((metadata or {}).get("rate_hz", "nan"))
        if not np.isfinite(fs) or fs <= 0:
            raise
        return analyse_stamps(ns, rate_hz=fs, name=name)


def make_series(name: str, t: np.ndarray, values: np.ndarray, timing: Timing,
                warnings: list[str], units: str) -> ChannelSeries:
    """A ChannelSeries from stamps (int64 ns), values and the topic's timing. Non-finite samples
    are dropped with a warning; the hole they leave becomes a segment boundary."""
    finite = np.isfinite(values)
    if finite.all():
        return ChannelSeries(name=name, units=units, fs_hz=timing.fs_hz,
                             values=np.ascontiguousarray(values, dtype=np.float64),
                             segment_starts=timing.segment_starts, t0_s=timing.t0_s)
    bad = int((~finite).sum())
    warnings.append(f"{name}: {bad} non-finite samples dropped (treated as gaps)")
    t, values = t[finite], np.ascontiguousarray(values[finite], dtype=np.float64)
    rel, t0 = relative_seconds(t)
    starts = segment_starts_from_times(rel, timing.fs_hz) if t.size else np.zeros(1, np.int64)
    return ChannelSeries(name=name, units=units, fs_hz=timing.fs_hz, values=values,
                         segment_starts=starts, t0_s=t0)


def read_mcap(path: str | Path, rate_hz: float | None = None) -> Record:
    """Read every Imu and Temperature channel of a ROS 2 MCAP file into a Record
    (``rate_hz``: nominal rate overriding the one inferred from the stamps)."""
    src = open_mcap(path)
    if not src.topics:
        raise ml.McapFormatError("no sensor_msgs/msg/Imu or Temperature channel")
    arrays: dict[int, dict[str, np.ndarray]] = {}
    fill: dict[int, int] = dict.fromkeys(src.topics, 0)

    def sink(tp: _Topic, n: int) -> dict[str, np.ndarray]:
        """Slices of the output arrays, allocated once from the index counts."""
        have = arrays.get(tp.cid)
        k = fill[tp.cid]
        if have is None:
            cap = max(tp.count, n)
            have = arrays[tp.cid] = {c: np.empty(cap, np.int64 if c == "t" else np.float64)
                                     for c in _columns(tp)}
        cap = len(have["t"])
        if k + n > cap:  # chunks without message indexes: counts were not known
            for c, v in have.items():
                grown = np.empty(max(k + n, 2 * cap), v.dtype)
                grown[:k] = v[:k]
                have[c] = grown
        fill[tp.cid] = k + n
        return {c: v[k:k + n] for c, v in have.items()}

    for _decoded in iter_decoded(src, sink):
        pass
    warnings = list(src.warnings)
    channels: dict[str, ChannelSeries] = {}
    temperature: ChannelSeries | None = None
    imu_topics = [tp for tp in src.topics.values() if tp.kind == "imu" and fill[tp.cid]]
    temp_topics = [tp for tp in src.topics.values()
                   if tp.kind == "temperature" and fill[tp.cid]]
    if not imu_topics and not temp_topics:
        raise ml.McapFormatError("no Imu or Temperature messages in the file")
    timings: dict[str, dict] = {}
    for tp in imu_topics:
        n = fill[tp.cid]
        cols = {k: v[:n] for k, v in arrays.pop(tp.cid).items()}
        t = cols.pop("t")
        timing = topic_timing(t, tp.topic, src.metadata, rate_hz)
        timings[tp.topic] = timing.facts()
        warnings.extend(timing.notes)
        label = tp.topic if len(imu_topics) > 1 else ""
        for name, v in cols.items():
            key = f"{label}:{name}" if label else name
            channels[key] = make_series(key, t, v, timing, warnings,
                                        "rad/s" if name.startswith("gyro") else "m/s^2")
        del t, cols
    if temp_topics:
        tp = temp_topics[0]
        n = fill[tp.cid]
        cols = arrays.pop(tp.cid)
        t = cols["t"][:n]
        if len(temp_topics) > 1:
            warnings.append(f"several temperature topics: using {tp.topic}")
        timing = topic_timing(t, tp.topic, {"rate_hz": "1.0"})
        temperature = make_series("temp", t, cols["temp"][:n], timing, warnings, "degC")
    meta = dict(src.metadata)
    meta["format"] = "mcap"
    if imu_topics:
        meta["fs_hz"] = f"{next(iter(channels.values())).fs_hz:.9g}"
    meta["topics"] = ",".join(tp.topic for tp in src.topics.values())
    return Record(source=str(path), channels=channels, temperature=temperature, metadata=meta,
                  warnings=warnings, facts={"timing": timings} if timings else {})


def raw_counts(values: np.ndarray, metadata: dict[str, str], channel: str) -> np.ndarray | None:
    """Raw register counts of a channel recorded by imunoise (``value = offset + scale *
    count``, scale and offset in the metadata record), or None when the file has no scale
    or a value is not finite."""
    base = channel.split(":")[-1]
    try:
        scale = float(metadata[f"scale.{base}"])
        offset = float(metadata.get(f"offset.{base}", "0"))
    except (KeyError, ValueError):
        return None
    values = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(values)):
        return None
    return np.rint((np.asarray(values, dtype=np.float64) - offset) / scale).astype(np.int64)


def iter_blocks(path: str | Path, src: McapSource | None = None) -> Iterator[SampleBlock]:
    """Stream a file as SampleBlocks (one per topic, batch and gap-free run), bounded memory.

    Each block is contiguous in time; ``gap_before`` counts the samples missing before it
    (-1 when time went backwards or the rate is unknown). Raw counts are attached when the
    file carries scale factors. ``src`` may be passed when the file is already opened.
    """
    src = open_mcap(path) if src is None else src
    last_t: dict[int, float] = {}
    rates: dict[int, float] = {}
    for decoded in iter_decoded(src):
        for cid, data in decoded.items():
            tp = src.topics[cid]
            ns = data["t"]
            if ns.size == 0:
                continue
            fs = rates.get(cid)
            if fs is None:
                try:
                    fs = topic_timing(ns, tp.topic, src.metadata).fs_hz
                except ValueError:
                    fs = 1.0
                rates[cid] = fs
            cols = _split(data)
            rel, t_first = relative_seconds(ns)
            t = rel + t_first
            timing = (analyse_stamps(ns, rate_hz=fs) if ns.size > 1 and np.any(np.diff(ns) > 0)
                      else None)
            starts = timing.segment_starts if timing else np.zeros(1, np.int64)
            inner = dict(zip(starts[1:].tolist(), timing.gaps.tolist(), strict=True)) \
                if timing else {}
            bounds = np.append(starts, t.size)  # jitter is no gap here either (core.timing)
            for a, b in zip(bounds[:-1], bounds[1:], strict=True):
                if b <= a:
                    continue
                prev = last_t.get(cid)
                gap = int(inner.get(int(a), 0))
                if a == 0 and prev is not None:
                    steps = (t[a] - prev) * fs
                    if steps > 1.5:
                        gap = int(round(steps)) - 1
                    elif steps < 0.5:
                        gap = -1
                chans = {k: np.ascontiguousarray(v[a:b]) for k, v in cols.items()}
                raw = {}
                for k, v in chans.items():
                    counts = raw_counts(v, src.metadata, k)
                    if counts is not None:
                        raw[k] = counts
                yield SampleBlock(stream=tp.topic, t=t[a:b].copy(), channels=chans, fs_hz=fs,
                                  raw=raw, gap_before=gap)
                last_t[cid] = float(t[b - 1])
