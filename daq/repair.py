"""Turn a crashed, truncated or damaged MCAP file into a clean, indexed one.

- :func:`repair` (``imunoise repair``): :func:`rebuild` writes a fresh file from the records
  that pass every check (header, definitions that parse exactly, chunks whose size, CRC and
  record framing check and whose channels are defined, copied byte for byte with new message
  indexes, and a new summary); damaged chunks are dropped and named. Files with messages
  outside chunks go through :func:`rewrite`, which copies every readable message with the
  ``mcap`` writer (CRC validation on).
- :func:`finish_in_place`: cut a crashed file at the end of its last complete record and
  append what a clean ``finish()`` would have written (DataEnd, schemas, channels, statistics,
  chunk and metadata indexes, summary offsets, footer). Chunks are not rewritten, so it is
  fast and needs only a little free space (about 100 bytes per chunk): the recorder uses it
  when the disk fills up, on a file it wrote itself.
"""

from __future__ import annotations

import mmap
import os
import struct
from dataclasses import dataclass
from pathlib import Path

from mcap.data_stream import RecordBuilder
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    MessageIndex,
    MetadataIndex,
    Schema,
    Statistics,
)

from imunoise.daq import mcap_layout as ml
from imunoise.daq.mcap_writer import summary_bytes


@dataclass
class RepairResult:
    """What a repair did: messages kept, chunks kept, bytes dropped from a damaged tail,
    damaged chunks dropped, and one warning per thing left out."""

    path: str
    method: str  # "already complete", "finished in place", "rebuilt", "rewritten"
    messages: int
    chunks: int
    dropped_bytes: int
    warnings: list[str]
    dropped_chunks: int = 0


def _message_counts(buf, layout: ml.McapLayout) -> tuple[dict[int, int], list[dict[int, int]]]:
    totals: dict[int, int] = {}
    per_chunk = []
    for chunk in layout.chunks:
        if chunk.mi:
            counts = {cid: n for cid, (_pos, n) in chunk.mi.items()}
        else:
            offs = ml.walk_chunk(buf, chunk, layout, collect=set(layout.channels))
            counts = {cid: len(v) for cid, v in offs.items()}
        per_chunk.append(counts)
        for cid, n in counts.items():
            totals[cid] = totals.get(cid, 0) + n
    return totals, per_chunk


def _summary(buf, layout: ml.McapLayout, summary_start: int) -> bytes:
    totals, _ = _message_counts(buf, layout)
    chunks = layout.chunks
    statistics = Statistics(
        attachment_count=0, channel_count=len(layout.channels),
        channel_message_counts=totals, chunk_count=len(chunks),
        message_count=sum(totals.values()),
        message_start_time=min((c.message_start_time for c in chunks), default=0),
        message_end_time=max((c.message_end_time for c in chunks), default=0),
        metadata_count=len(layout.metadata), schema_count=len(layout.schemas))
    return summary_bytes(
        summary_start,
        [Schema(id=s.id, name=s.name, encoding=s.encoding, data=s.data)
         for s in sorted(layout.schemas.values(), key=lambda s: s.id)],
        [Channel(id=c.id, schema_id=c.schema_id, topic=c.topic,
                 message_encoding=c.message_encoding, metadata=c.metadata)
         for c in sorted(layout.channels.values(), key=lambda c: c.id)],
        statistics,
        [ChunkIndex(message_start_time=c.message_start_time,
                    message_end_time=c.message_end_time, chunk_start_offset=c.start,
                    chunk_length=c.end - c.start,
                    message_index_offsets={cid: pos - 6 - ml.RECORD_PREFIX
                                           for cid, (pos, _n) in c.mi.items()},
                    message_index_length=c.mi_end - c.end, compression=c.compression,
                    compressed_size=c.data_length, uncompressed_size=c.uncompressed_size)
         for c in chunks],
        [MetadataIndex(offset=m.offset, length=m.length, name=m.name) for m in layout.metadata])


def _only_message_indexes(buf, start: int, end: int) -> bool:
    return all(op == ml.OP_MESSAGE_INDEX for op, _a, _b in ml.iter_records(buf, start, end))


def _reindex_last_chunk(buf, layout: ml.McapLayout) -> bytes:
    """MessageIndex records for the last chunk of a crashed file (its own may be cut short);
    updates ``layout`` so that they follow the chunk. Empty when not applicable."""
    if not layout.chunks:
        return b""
    if len(layout.chunks) > 1 and not any(c.mi for c in layout.chunks[:-1]):
        return b""  # the file does not use message indexes
    last = layout.chunks[-1]
    if last.mi or not _only_message_indexes(buf, last.end, layout.data_end):
        return b""
    entries = ml.walk_chunk(buf, last, layout, collect=set(layout.channels))
    builder = RecordBuilder()
    for cid in sorted(entries):
        start = builder.count
        MessageIndex(channel_id=cid, records=sorted(entries[cid])).write(builder)
        last.mi[cid] = (last.end + start + ml.RECORD_PREFIX + 6, len(entries[cid]))
    last.mi_end = last.end + builder.count
    layout.data_end = last.mi_end
    return builder.end()


def finish_in_place(path: str | Path) -> RepairResult:
    """Append a summary to a crashed MCAP file (no-op for a complete one)."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "r+b") as f:
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
        try:
            layout = ml.scan(buf, size)
            if layout.complete:
                n = sum(n for c in layout.chunks for _p, n in c.mi.values())
                return RepairResult(str(path), "already complete", n, len(layout.chunks), 0,
                                    layout.warnings)
            cut = layout.chunks[-1].end if layout.chunks else layout.data_end
            kept_end = layout.data_end
            indexes = _reindex_last_chunk(buf, layout)
            if not indexes:
                cut = kept_end
            data_end = layout.data_end
            closing = RecordBuilder()
            DataEnd(data_section_crc=0).write(closing)
            closing_bytes = closing.end()
            summary = _summary(buf, layout, data_end + len(closing_bytes))
            totals, _ = _message_counts(buf, layout)
        finally:
            if isinstance(buf, mmap.mmap):
                buf.close()
        f.truncate(cut)
        f.seek(cut)
        f.write(indexes + closing_bytes + summary)
        f.flush()
        os.fsync(f.fileno())
    return RepairResult(str(path), "finished in place", sum(totals.values()),
                        len(layout.chunks), max(size - kept_end, 0), layout.warnings)


def rewrite(src: str | Path, dst: str | Path) -> RepairResult:
    """Copy every readable record of ``src`` into a fresh, indexed file ``dst`` (files with
    messages outside chunks). Stops at the first record that cannot be parsed; a message of a
    channel not defined before it, or whose record is malformed, is left out."""
    from mcap.exceptions import McapError
    from mcap.records import Channel as ChannelRec
    from mcap.records import Header, Message, Metadata
    from mcap.records import Schema as SchemaRec
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, IndexType, Writer

    src, dst = Path(src), Path(dst)
    warnings: list[str] = []
    messages = 0
    size = src.stat().st_size
    with open(src, "rb") as f, open(dst, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD,
                        index_types=IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA)
        started = False
        schema_map: dict[int, int] = {}
        channel_map: dict[int, int] = {}
        try:
            for record in StreamReader(f, skip_magic=False, record_size_limit=size,
                                       validate_crcs=True).records:
                if isinstance(record, Header):
                    writer.start(profile=record.profile[:200], library=record.library[:200])
                    started = True
                elif not started:
                    break
                elif isinstance(record, SchemaRec) and record.id not in schema_map:
                    if schema_usable(record.name, record.encoding, record.data):
                        schema_map[record.id] = writer.register_schema(
                            record.name, record.encoding, record.data)
                elif isinstance(record, ChannelRec) and record.id not in channel_map:
                    if record.schema_id and record.schema_id not in schema_map:
                        continue  # its schema is lost: so are its messages
                    channel_map[record.id] = writer.register_channel(
                        record.topic, record.message_encoding,
                        schema_map.get(record.schema_id, 0), record.metadata)
                elif isinstance(record, Message) and record.channel_id in channel_map:
                    writer.add_message(channel_map[record.channel_id], record.log_time,
                                       record.data, record.publish_time, record.sequence)
                    messages += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, record.metadata)
        except (McapError, struct.error, ValueError, EOFError, KeyError, IndexError,
                OverflowError, MemoryError) as exc:
            warnings.append(f"stopped at a damaged or truncated record ({type(exc).__name__})")
        if not started:
            raise ml.McapFormatError("not an MCAP file (no header record)")
        writer.finish()
    return RepairResult(str(dst), "rewritten", messages, 0, 0, warnings)


def schema_usable(name: str, encoding: str, data: bytes) -> bool:
    """Whether a schema's text parses (ROS 1 and ROS 2 message definitions: a damaged one would
    stop other tools reading the file); other encodings are taken as they are."""
    if encoding not in ("ros2msg", "ros1msg"):
        return True
    from rosbags.typesys import get_types_from_msg

    try:
        get_types_from_msg(bytes(data).decode("utf-8"), name)
    except Exception:  # noqa: BLE001 - the parser raises many types on damaged text
        return False
    return True


@dataclass
class _Kept:
    """A chunk that passed every check, with its fresh message index entries."""

    chunk: ml.ChunkInfo
    entries: dict[int, list[tuple[int, int]]]


def _strict_definitions(records, start: int, end: int) -> tuple[list[ml.SchemaInfo],
                                                                 list[ml.ChannelInfo]]:
    """The Schema and Channel records in ``records[start:end]``, each checked to fill its
    record exactly. Raises DamagedChunk otherwise."""
    schemas, channels = [], []
    for op, a, b in ml.iter_records(records, start, end):
        try:
            if op == ml.OP_SCHEMA:
                s = ml.parse_schema(records, a)
                if a + 2 + 12 + len(s.name.encode()) + len(s.encoding.encode()) + len(s.data) \
                        != b:
                    raise ml.DamagedChunk("a malformed schema record")
                schemas.append(s)
            elif op == ml.OP_CHANNEL:
                channels.append(_strict_channel(records, a, b))
        except (struct.error, ValueError) as exc:
            raise ml.DamagedChunk(f"a malformed definition ({type(exc).__name__})") from None
    return schemas, channels


def _strict_channel(buf, a: int, b: int) -> ml.ChannelInfo:
    c = ml.parse_channel(buf, a)
    pos = a + 4
    for _ in range(2):
        (n,) = struct.unpack_from("<I", buf, pos)
        pos += 4 + n
    (n,) = struct.unpack_from("<I", buf, pos)
    if pos + 4 + n != b:
        raise ml.DamagedChunk("a malformed channel record")
    _check_map(buf, pos + 4, pos + 4 + n)
    if any("\ufffd" in text for text in (c.topic, c.message_encoding)):
        raise ml.DamagedChunk("a channel record that is not UTF-8")
    return c


def _check_map(buf, pos: int, end: int) -> None:
    while pos < end:
        for _ in range(2):
            if pos + 4 > end:
                raise ml.DamagedChunk("a malformed metadata map")
            (n,) = struct.unpack_from("<I", buf, pos)
            pos += 4 + n
            if pos > end:
                raise ml.DamagedChunk("a malformed metadata map")
            if "\ufffd" in bytes(buf[pos - n:pos]).decode("utf-8", "replace"):
                raise ml.DamagedChunk("a metadata map that is not UTF-8")


def _walk_checked(buf, chunk: ml.ChunkInfo, known: set[int]
                  ) -> dict[int, list[tuple[int, int]]]:
    """(log time, offset) of every message of a checked chunk, per channel. Raises
    DamagedChunk when a message's channel is not defined anywhere."""
    records = ml.check_chunk(buf, chunk, exact_size=True)
    entries: dict[int, list[tuple[int, int]]] = {}
    for op, a, _b in ml.iter_records(records, 0, len(records)):
        if op == ml.OP_MESSAGE:
            cid, _seq, log_time = struct.unpack_from("<HIQ", records, a)
            if cid not in known:
                raise ml.DamagedChunk(f"a message of channel {cid}, whose definition is lost")
            entries.setdefault(cid, []).append((log_time, a - ml.RECORD_PREFIX))
    return entries


def _definitions(buf, layout: ml.McapLayout) -> tuple[dict, dict, dict[int, str]]:
    """Every Schema and Channel record that parses strictly (top level, summary and the
    chunks that check), and the chunks that fail their checks (start -> reason)."""
    schemas: dict[int, ml.SchemaInfo] = {}
    channels: dict[int, ml.ChannelInfo] = {}
    bad: dict[int, str] = {}
    for chunk in layout.chunks:
        try:
            records = ml.check_chunk(buf, chunk, exact_size=True)
            found_s, found_c = _strict_definitions(records, 0, len(records))
        except ml.McapFormatError as exc:
            bad[chunk.start] = str(exc)
            continue
        for sch in found_s:
            schemas.setdefault(sch.id, sch)
        for ch in found_c:
            channels.setdefault(ch.id, ch)
    for sch in layout.schemas.values():
        schemas.setdefault(sch.id, sch)
    schemas = {sid: x for sid, x in schemas.items()
               if schema_usable(x.name, x.encoding, x.data)}
    for ch in layout.channels.values():
        channels.setdefault(ch.id, ch)
    channels = {cid: c for cid, c in channels.items()
                if c.schema_id == 0 or c.schema_id in schemas}
    return schemas, channels, bad


def rebuild(src: str | Path, dst: str | Path) -> RepairResult:
    """Write a fresh file ``dst`` from the checked records of ``src``: the header, every Schema,
    Channel and Metadata record that parses, every chunk that passes
    :func:`imunoise.daq.mcap_layout.check_chunk` (CRC, size, record framing) and whose messages'
    channels are defined, copied byte for byte with fresh message indexes; then a new summary.
    Chunks that fail are dropped and named in the warnings."""
    src, dst = Path(src), Path(dst)
    size = src.stat().st_size
    with open(src, "rb") as f:
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            return _rebuild(buf, size, src, dst)
        finally:
            buf.close()


def _rebuild(buf, size: int, src: Path, dst: Path) -> RepairResult:
    from mcap.records import Header, Metadata

    layout = ml.scan(buf, size)
    schemas, channels, bad = _definitions(buf, layout)
    kept: list[_Kept] = []
    for chunk in layout.chunks:
        if chunk.start in bad:
            continue
        try:
            kept.append(_Kept(chunk, _walk_checked(buf, chunk, set(channels))))
        except ml.McapFormatError as exc:
            bad[chunk.start] = str(exc)
    warnings = list(layout.warnings) + [ml.damaged_chunk_note(start, reason)
                                        for start, reason in bad.items()]
    head = RecordBuilder()
    Header(profile=layout.profile, library=layout.library).write(head)
    for sch in sorted(schemas.values(), key=lambda x: x.id):
        Schema(id=sch.id, name=sch.name, encoding=sch.encoding, data=sch.data).write(head)
    for ch in sorted(channels.values(), key=lambda x: x.id):
        Channel(id=ch.id, schema_id=ch.schema_id, topic=ch.topic,
                message_encoding=ch.message_encoding, metadata=ch.metadata).write(head)
    meta_index: list[MetadataIndex] = []
    totals: dict[int, int] = {}
    chunk_index: list[ChunkIndex] = []
    with open(dst, "wb") as out:
        out.write(ml.MAGIC)
        out.write(head.end())
        for md in layout.metadata:
            rec = RecordBuilder()
            Metadata(name=md.name, metadata=md.data).write(rec)
            data = rec.end()
            meta_index.append(MetadataIndex(offset=out.tell(), length=len(data), name=md.name))
            out.write(data)
        for k in kept:
            chunk_index.append(_copy_chunk(buf, k, out, totals))
        closing = RecordBuilder()
        DataEnd(data_section_crc=0).write(closing)
        out.write(closing.end())
        summary_start = out.tell()
        starts = [c.message_start_time for c in chunk_index]
        ends = [c.message_end_time for c in chunk_index]
        statistics = Statistics(
            attachment_count=0, channel_count=len(channels), channel_message_counts=totals,
            chunk_count=len(chunk_index), message_count=sum(totals.values()),
            message_start_time=min(starts, default=0), message_end_time=max(ends, default=0),
            metadata_count=len(meta_index), schema_count=len(schemas))
        out.write(summary_bytes(
            summary_start,
            [Schema(id=x.id, name=x.name, encoding=x.encoding, data=x.data)
             for x in sorted(schemas.values(), key=lambda x: x.id)],
            [Channel(id=c.id, schema_id=c.schema_id, topic=c.topic,
                     message_encoding=c.message_encoding, metadata=c.metadata)
             for c in sorted(channels.values(), key=lambda c: c.id)],
            statistics, chunk_index, meta_index))
        out.flush()
        os.fsync(out.fileno())
    method = ("rebuilt" if bad or layout.damaged else
              "already complete" if layout.complete else "finished in place")
    return RepairResult(str(dst), method, sum(totals.values()), len(chunk_index),
                        max(size - layout.data_end, 0) if not layout.complete else 0, warnings,
                        len(bad) + len(layout.damaged))


def _copy_chunk(buf, kept: _Kept, out, totals: dict[int, int]) -> ChunkIndex:
    """Copy one checked chunk and write its message indexes; its ChunkIndex."""
    c = kept.chunk
    start = out.tell()
    out.write(buf[c.start:c.end])
    builder = RecordBuilder()
    offsets: dict[int, int] = {}
    for cid in sorted(kept.entries):
        offsets[cid] = start + (c.end - c.start) + builder.count
        MessageIndex(channel_id=cid, records=kept.entries[cid]).write(builder)
        totals[cid] = totals.get(cid, 0) + len(kept.entries[cid])
    index = builder.end()
    out.write(index)
    times = [t for e in kept.entries.values() for t, _o in e]
    return ChunkIndex(message_start_time=min(times, default=0),
                      message_end_time=max(times, default=0), chunk_start_offset=start,
                      chunk_length=c.end - c.start, message_index_offsets=offsets,
                      message_index_length=len(index), compression=c.compression,
                      compressed_size=c.data_length, uncompressed_size=c.uncompressed_size)


def repair(src: str | Path, dst: str | Path) -> RepairResult:
    """Write a clean, indexed copy of ``src`` to ``dst`` (which may not be ``src``): every
    record kept is checked first (:func:`rebuild`); files with messages outside chunks are
    rewritten message by message (:func:`rewrite`)."""
    src, dst = Path(src), Path(dst)
    size = src.stat().st_size
    if size == 0:
        raise ml.McapFormatError("empty file")
    with open(src, "rb") as f:
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            layout = ml.scan(buf, size)
        finally:
            buf.close()
    tmp = dst.with_name(dst.name + ".part")
    try:
        result = rewrite(src, tmp) if layout.unchunked_messages else rebuild(src, tmp)
        os.replace(tmp, dst)
    finally:
        tmp.unlink(missing_ok=True)
    result.path = str(dst)
    return result

