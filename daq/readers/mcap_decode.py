"""Decoding a batch of MCAP chunks at once: the stamp and field columns of every Imu and
Temperature message, gathered with one vectorised indexing operation per field (see
:mod:`imunoise.daq.readers.mcap` for the whole reader)."""

from __future__ import annotations

import os
import zlib
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from imunoise.daq import mcap_layout as ml
from imunoise.daq import ros2_msgs as msgs
from imunoise.daq.readers.mcap_scan import McapSource, UnsupportedLayout, _Topic

GYRO = ("gyro_x", "gyro_y", "gyro_z")
ACCEL = ("accel_x", "accel_y", "accel_z")
BATCH_BYTES = 1 << 20  # uncompressed bytes decoded per batch (cache-sized: gathers stay hot)
_PAYLOAD = ml.RECORD_PREFIX + ml.MESSAGE_HEADER  # record start -> CDR payload

def _batch_bounds(sizes: list[int]) -> list[tuple[int, int]]:
    """``[start, stop)`` chunk indices of each batch: chunks are added until a batch holds
    ``BATCH_BYTES`` of uncompressed data."""
    bounds, start, nbytes = [], 0, 0
    for i, size in enumerate(sizes):
        nbytes += size
        if nbytes >= BATCH_BYTES:
            bounds.append((start, i + 1))
            start, nbytes = i + 1, 0
    if start < len(sizes):
        bounds.append((start, len(sizes)))
    return bounds


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


VERIFY_CRC = True
"""Check every chunk's records against the CRC its writer stored (the official writer and
imunoise's store one): a damaged chunk whose data still decompress is then left out instead of
read as wrong samples. It costs about 15 % of a read's CPU time (docs/damaged-files.md)."""


def _check_crc(chunk: ml.ChunkInfo, records: np.ndarray) -> None:
    if chunk.uncompressed_crc and zlib.crc32(records) != chunk.uncompressed_crc:
        raise ml.DamagedChunk("CRC mismatch")


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
            if VERIFY_CRC:
                for c, base in zip(batch, bases, strict=True):
                    _check_crc(c, out[base:base + c.uncompressed_size])
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
        if VERIFY_CRC:
            _check_crc(c, out[base:base + n])
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
    ``sink``, into the arrays it hands out for (topic, message count). Every topic's messages
    are checked before any is handed to the sink, so a batch that fails leaves none behind."""
    region, blob, bases = loaded
    views = {dt: _overlapping(blob, dt) for dt in (f"V{_HEAD.itemsize}", "V24", "<f8")}
    planned = []
    for cid, tp in src.topics.items():
        rec = _record_offsets(cid, batch, region, blob, bases)
        if rec is None:
            continue
        if rec.min() < 0 or rec.max() + _PAYLOAD > blob.size:
            raise ml.McapFormatError(f"{tp.topic}: message index points outside its chunk")
        if tp.frame_len < 0:
            _setup_topic(tp, blob, int(rec[0]))
        planned.append((cid, tp, rec, _check_topic(tp, blob, rec, views)))
    out: dict[int, dict[str, np.ndarray]] = {}
    for cid, tp, rec, head in planned:
        dest = sink(tp, rec.size) if sink is not None else {
            name: np.empty(rec.size, np.int64 if name == "t" else np.float64)
            for name in _columns(tp)}
        out[cid] = _decode_topic(tp, blob, rec, head, views, dest)
    return out


def _record_offsets(cid: int, batch: list[ml.ChunkInfo], region: bytes, blob: np.ndarray,
                    bases: list[int]) -> np.ndarray | None:
    """Offsets in ``blob`` of channel ``cid``'s message records in the batch (from the message
    indexes, or by walking chunks that have none); None when there are none."""
    start = batch[0].start
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
        region_u8 = np.frombuffer(region, np.uint8)
        cnt = np.asarray(cnt_l, dtype=np.int64)
        total = int(cnt.sum())
        first = np.repeat(np.cumsum(cnt) - cnt, cnt)
        idx = np.repeat(np.asarray(pos_l, dtype=np.int64), cnt) + 16 * (
            np.arange(total, dtype=np.int64) - first) + 8
        entries = _overlapping(region_u8, "<u8")
        if idx.max() >= entries.size:
            raise ml.McapFormatError("a message index runs past its record")
        rel = entries[idx]
        if rel.max() > np.uint64(blob.size):
            raise ml.McapFormatError("message index points outside its chunk")
        offsets.append(rel.astype(np.int64) + np.repeat(np.asarray(base_l, dtype=np.int64), cnt))
    offsets.extend(walked)
    if not offsets:
        return None
    rec = np.concatenate(offsets) if len(offsets) > 1 else offsets[0]
    return rec if rec.size else None


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


def _check_topic(tp: _Topic, blob: np.ndarray, rec: np.ndarray, views: dict[str, np.ndarray]
                 ) -> np.ndarray:
    """The record and CDR headers of one topic's messages at record offsets ``rec`` in
    ``blob``, after checking that they all have the topic's fixed layout."""
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
    return head


def _decode_topic(tp: _Topic, blob: np.ndarray, rec: np.ndarray, head: np.ndarray,
                  views: dict[str, np.ndarray], dest: dict[str, np.ndarray]
                  ) -> dict[str, np.ndarray]:
    """Decode the checked messages of one topic (``head`` from :func:`_check_topic`) into the
    arrays ``dest`` (one per column of :func:`_columns`, each of ``len(rec)``).

    Fields are gathered as opaque byte groups (one per message for the record and CDR header,
    one per vector), then reinterpreted: far fewer gathers than one per scalar."""
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
    # batches are taken from the chunk table one at a time: the table is compact, its rows
    # as objects are not (see imunoise.daq.mcap_layout.ChunkTable)
    chunks = src.layout.chunks
    sizes = chunks.uncompressed_sizes()
    bounds = _batch_bounds(sizes)
    if not bounds:
        return
    size = max(sum(sizes[a:b]) for a, b in bounds)
    batches = (chunks[a:b] for a, b in bounds)
    if not read_ahead():
        scratch = np.empty(size, np.uint8)
        with open(src.path, "rb") as f:
            for batch in batches:
                yield _decode_checked(src, batch, f.fileno(),
                                      lambda b=batch: _load_batch(f.fileno(), b, scratch), sink)
        return
    # Two buffers in turn: the next batch is decompressed into one while this one is decoded
    # from the other (decoding copies everything it keeps).
    buffers = [np.empty(size, np.uint8), np.empty(size, np.uint8)]
    with open(src.path, "rb") as f, ThreadPoolExecutor(max_workers=1) as pool:
        fd = f.fileno()
        batch = next(batches)
        pending = pool.submit(_load_batch, fd, batch, buffers[0])
        for i in range(len(bounds)):
            done = pending
            following = next(batches, None)
            if following is not None:
                done.exception()  # this batch is in its buffer before the next one is read
                pending = pool.submit(_load_batch, fd, following, buffers[(i + 1) % 2])
            yield _decode_checked(src, batch, fd, done.result, sink)
            batch = following




# What a damaged chunk makes the decoding raise (besides DamagedChunk, a McapFormatError).
_DAMAGE = (ml.McapFormatError, UnsupportedLayout, IndexError, ValueError, OverflowError)


def _topic_state(src: McapSource) -> dict[int, tuple]:
    return {cid: (tp.frame_len, tp.body, tp.payload_len, tp.has_gyro, tp.has_accel)
            for cid, tp in src.topics.items()}


def _restore_topics(src: McapSource, state: dict[int, tuple]) -> None:
    """Undo what a failed decoding fixed from a damaged first message (the payload layout)."""
    for cid, values in state.items():
        tp = src.topics[cid]
        tp.frame_len, tp.body, tp.payload_len, tp.has_gyro, tp.has_accel = values


def _decode_checked(src: McapSource, batch: list[ml.ChunkInfo], fd: int,
                    load: Callable[[], tuple[bytes, np.ndarray, list[int]]],
                    sink: Sink | None) -> dict[int, dict[str, np.ndarray]]:
    """:func:`_decode_batch` of a batch; when it fails, the batch is decoded chunk by chunk and
    the damaged chunks are left out, each with a warning in ``src.warnings`` (their messages
    are lost: the stamps around them make a gap)."""
    state = _topic_state(src)
    try:
        return _decode_batch(src, batch, load(), sink)
    except _DAMAGE:
        _restore_topics(src, state)
    parts = [_decode_chunk(src, chunk, fd, sink) for chunk in batch]
    out: dict[int, dict[str, np.ndarray]] = {}
    for cid in src.topics:
        cols = [p[cid] for p in parts if cid in p]
        if cols:
            out[cid] = {k: np.concatenate([c[k] for c in cols]) for k in cols[0]}
    return out


def _decode_chunk(src: McapSource, chunk: ml.ChunkInfo, fd: int, sink: Sink | None
                  ) -> dict[int, dict[str, np.ndarray]]:
    """One chunk decoded, or nothing (with a warning) when it is damaged. A chunk whose
    records are intact (CRC) but not of the bulk reader's layout raises UnsupportedLayout."""
    state = _topic_state(src)
    try:
        return _decode_batch(src, [chunk], _load_batch(fd, [chunk]), sink)
    except ml.DamagedChunk as exc:
        reason = str(exc)
    except _DAMAGE as exc:
        _restore_topics(src, state)
        # A layout the bulk reader does not take is genuine when the chunk's CRC says its
        # records are intact, or, without a CRC, when no earlier chunk fixed the layout.
        established = any(values[0] >= 0 for values in state.values())
        if isinstance(exc, UnsupportedLayout) and _intact(fd, chunk) and (
                chunk.uncompressed_crc or not established):
            raise
        reason = ml.first_line(exc)
    _restore_topics(src, state)
    counts = sum(n for cid, (_p, n) in chunk.mi.items() if cid in src.topics) \
        if chunk.has_index else None
    src.warnings.append(ml.damaged_chunk_note(
        chunk.start, reason, counts, (chunk.message_start_time, chunk.message_end_time)))
    return {}


def _intact(fd: int, chunk: ml.ChunkInfo) -> bool:
    """Whether a chunk's records decompress and match a stored CRC (True without one)."""
    data = os.pread(fd, chunk.end - chunk.start, chunk.start)
    shifted = ml.ChunkInfo(0, len(data), 0, 0, chunk.uncompressed_size, chunk.uncompressed_crc,
                           chunk.compression, chunk.data_offset - chunk.start, chunk.data_length)
    try:
        ml.check_chunk(data, shifted)
    except ml.McapFormatError:
        return False
    return True
