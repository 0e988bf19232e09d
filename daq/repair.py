"""Turn a crashed or truncated MCAP file into a clean, indexed one.

Two ways, both keeping every complete record:

- :func:`finish_in_place`: cut the file at the end of its last complete record and append what
  a clean ``finish()`` would have written (DataEnd, schemas, channels, statistics, chunk and
  metadata indexes, summary offsets, footer). Chunks are not rewritten, so it is fast and needs
  only a little free space (about 100 bytes per chunk). Used by the recorder when the disk
  fills up, and by :func:`repair` when every chunk carries its message indexes.
- :func:`rewrite`: copy every readable message into a new file with the ``mcap`` writer, for
  files whose chunks lack message indexes or that hold messages outside chunks.
"""

from __future__ import annotations

import mmap
import os
import shutil
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
    """What a repair did: messages kept per topic, bytes dropped from a damaged tail."""

    path: str
    method: str  # "already complete", "finished in place", "rewritten"
    messages: int
    chunks: int
    dropped_bytes: int
    warnings: list[str]


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
    """Copy every readable record of ``src`` into a fresh, indexed file ``dst``."""
    from mcap.exceptions import McapError
    from mcap.records import Channel as ChannelRec
    from mcap.records import Header, Message, Metadata
    from mcap.records import Schema as SchemaRec
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, IndexType, Writer

    src, dst = Path(src), Path(dst)
    warnings: list[str] = []
    messages = 0
    with open(src, "rb") as f, open(dst, "wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD,
                        index_types=IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA)
        started = False
        schema_map: dict[int, int] = {}
        channel_map: dict[int, int] = {}
        try:
            for record in StreamReader(f, skip_magic=False).records:
                if isinstance(record, Header):
                    writer.start(profile=record.profile, library=record.library)
                    started = True
                elif isinstance(record, SchemaRec) and record.id not in schema_map:
                    schema_map[record.id] = writer.register_schema(record.name, record.encoding,
                                                                   record.data)
                elif isinstance(record, ChannelRec) and record.id not in channel_map:
                    channel_map[record.id] = writer.register_channel(
                        record.topic, record.message_encoding,
                        schema_map.get(record.schema_id, 0), record.metadata)
                elif isinstance(record, Message) and record.channel_id in channel_map:
                    writer.add_message(channel_map[record.channel_id], record.log_time,
                                       record.data, record.publish_time, record.sequence)
                    messages += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, record.metadata)
        except (McapError, struct.error, ValueError, EOFError) as exc:
            warnings.append(f"stopped at a damaged or truncated record ({type(exc).__name__})")
        if not started:
            raise ml.McapFormatError("not an MCAP file (no header record)")
        writer.finish()
    return RepairResult(str(dst), "rewritten", messages, 0, 0, warnings)


def repair(src: str | Path, dst: str | Path) -> RepairResult:
    """Write a clean, indexed copy of ``src`` to ``dst`` (which may not be ``src``)."""
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
    indexed = all(c.mi for c in layout.chunks[:-1]) and not layout.unchunked_messages
    if not indexed:
        return rewrite(src, dst)
    tmp = dst.with_name(dst.name + ".part")
    with open(src, "rb") as fin, open(tmp, "wb") as fout:
        shutil.copyfileobj(fin, fout, 1 << 20)
    if layout.complete:
        os.replace(tmp, dst)
        n = sum(n for c in layout.chunks for _p, n in c.mi.values())
        return RepairResult(str(dst), "already complete", n, len(layout.chunks), 0, [])
    result = finish_in_place(tmp)
    os.replace(tmp, dst)
    result.path = str(dst)
    return result
