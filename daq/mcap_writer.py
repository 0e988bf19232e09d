"""A chunked MCAP writer that takes a block of equal-size messages as one numpy array.

The recorder writes every inertial sample as one message. ``mcap.writer.Writer`` builds each
message record and each message-index entry with about a dozen Python calls (20 us per sample
for an Imu and a Temperature message); at 1 kHz that work, in the process that also polls the
sensor, delayed polls enough to miss samples. Here a block's records and index entries are
built by a few numpy operations whatever its length.

The files are those ``mcap.writer.Writer`` writes with ``CompressionType.ZSTD`` and index types
CHUNK | MESSAGE | METADATA: the same records in the same order (schemas and channels inside
the chunk that follows their registration, a chunk closed once its records pass
``chunk_size`` bytes or on :meth:`McapBlockWriter.flush`, message indexes after each chunk,
and the summary), byte for byte; ``tests/daq/test_mcap_writer.py`` checks that.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Channel,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from imunoise.daq.mcap_layout import MAGIC, MESSAGE_HEADER, RECORD_PREFIX

COMPRESSION = "zstd"
ZSTD_LEVEL = 3  # the level zstandard.compress, and so mcap's Writer, uses
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_INDEX_HEAD = struct.Struct("<BQHI")
_CHUNK_HEAD = struct.Struct("<BQQQQI")  # opcode, length, start and end time, size, crc
_COMPRESSION_FIELD = struct.pack("<I", len(COMPRESSION)) + COMPRESSION.encode()
_CHUNK_FIXED = _CHUNK_HEAD.size - RECORD_PREFIX + len(_COMPRESSION_FIELD) + 8
"""Bytes of a Chunk record's body besides the compressed records."""


class OutputStream(Protocol):
    def write(self, data: bytes | memoryview) -> int: ...
    def tell(self) -> int: ...
    def flush(self) -> None: ...


def _message_dtype(payload_size: int) -> np.dtype:
    """One Message record with a payload of ``payload_size`` bytes, packed little-endian."""
    return np.dtype([("opcode", "u1"), ("length", "<u8"), ("channel", "<u2"),
                     ("sequence", "<u4"), ("log_time", "<u8"), ("publish_time", "<u8"),
                     ("data", "u1", (payload_size,))])


@dataclass
class _OpenChunk:
    """The records of the chunk being built, and where each channel's messages lie in it.

    The records are copied into ``buffer``, which the writer keeps from chunk to chunk:
    joining the parts into a fresh buffer at every flush held the interpreter for 0.1-0.6 ms
    (measured on a 640 kB chunk) while the acquisition thread in the same process waited to
    poll; compression and the checksum read the buffer in place.
    """

    buffer: bytearray
    size: int = 0
    messages: int = 0
    start_time: int = 0
    end_time: int = 0
    # channel id -> (log time, offset in the chunk) pairs, channels in order of first message
    index: dict[int, list[np.ndarray]] = field(default_factory=dict)

    def add(self, data: bytes | np.ndarray) -> int:
        """Append records (bytes, or a contiguous array's memory); their offset."""
        offset = self.size
        view = memoryview(data).cast("B")
        self.buffer[offset:offset + view.nbytes] = view
        self.size += view.nbytes
        view.release()
        return offset

    def times(self, first: int, last: int) -> None:
        if self.messages == 0:
            self.start_time, self.end_time = first, last
        else:
            self.start_time = min(self.start_time, first)
            self.end_time = max(self.end_time, last)


def summary_bytes(summary_start: int, schemas: list[Schema], channels: list[Channel],
                  statistics: Statistics, chunk_indexes: list[ChunkIndex],
                  metadata_indexes: list[MetadataIndex]) -> bytes:
    """The summary section, footer and closing magic of a file whose data section ends (with
    its DataEnd record) at byte ``summary_start``."""
    builder = RecordBuilder()
    offsets: list[SummaryOffset] = []

    def group(opcode: int, records: list) -> None:
        start = builder.count
        for record in records:
            record.write(builder)
        offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + start,
                                     group_length=builder.count - start))

    group(Opcode.SCHEMA, schemas)
    group(Opcode.CHANNEL, channels)
    group(Opcode.STATISTICS, [statistics])
    group(Opcode.CHUNK_INDEX, chunk_indexes)
    group(Opcode.METADATA_INDEX, metadata_indexes)
    offset_start = summary_start + builder.count
    for offset in offsets:
        offset.write(builder)
    data = builder.end()
    crc = zlib.crc32(data)
    crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), crc)
    tail = RecordBuilder()
    Footer(summary_start=summary_start, summary_offset_start=offset_start,
           summary_crc=crc).write(tail)
    return data + tail.end() + MAGIC


class McapBlockWriter:
    """Writes one MCAP file to ``stream`` (anything with ``write``, ``tell`` and ``flush``).

    Args:
        stream: the output, positioned at its start.
        chunk_size: a chunk is closed once its uncompressed records pass this many bytes.
    """

    def __init__(self, stream: OutputStream, chunk_size: int = 1 << 20) -> None:
        self._stream = stream
        self._chunk_size = chunk_size
        self._compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
        self._buffer = bytearray()
        self._chunk = _OpenChunk(self._buffer)
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._counts: dict[int, int] = {}
        self._messages = 0
        self._start_time = 0
        self._end_time = 0
        self._dtypes: dict[int, np.dtype] = {}

    # ---- records outside messages ------------------------------------------------------------

    def start(self, profile: str, library: str) -> None:
        self._stream.write(MAGIC + _record_bytes(Header(profile=profile, library=library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._chunk.add(_record_bytes(schema))
        self._maybe_close_chunk()
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int,
                         metadata: dict[str, str]) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic,
                          message_encoding=message_encoding, schema_id=schema_id,
                          metadata=dict(metadata))
        self._channels.append(channel)
        self._chunk.add(_record_bytes(channel))
        self._maybe_close_chunk()
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A Metadata record, written at once (outside the open chunk) and indexed."""
        record = _record_bytes(Metadata(name=name, metadata=dict(data)))
        offset = self._stream.tell()
        self._stream.write(record)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=len(record),
                                                    name=name))

    # ---- messages ------------------------------------------------------------------------------

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int,
                    sequence: int) -> None:
        """One message of any size (times in ns)."""
        head = _MESSAGE_HEAD.pack(Opcode.MESSAGE, MESSAGE_HEADER + len(data), channel_id,
                                  sequence, log_time, publish_time)
        self._note_messages(channel_id, np.array([log_time], dtype=np.uint64),
                            np.array([self._chunk.size], dtype=np.uint64))
        self._chunk.add(head + bytes(data))
        self._maybe_close_chunk()

    def add_messages(self, channel_id: int, log_times: np.ndarray, payloads: np.ndarray,
                     first_sequence: int) -> None:
        """Messages of one channel with equal-size payloads, in order.

        Args:
            channel_id: a registered channel.
            log_times: log and publish time of each message, ns (n integers >= 0).
            payloads: (n, payload bytes) uint8 array, one row per message.
            first_sequence: sequence number of the first message; the rest count up by one.
        """
        n = len(payloads)
        record_size = RECORD_PREFIX + MESSAGE_HEADER + payloads.shape[1]
        start = 0
        while start < n:
            # As mcap's Writer: the chunk closes right after the message that takes it past
            # chunk_size, so a block may be split between two chunks.
            room = self._chunk_size - self._chunk.size
            take = min(n - start, max(room // record_size + 1, 1))
            self._add_equal_messages(channel_id, log_times[start:start + take],
                                     payloads[start:start + take], first_sequence + start)
            start += take

    def _add_equal_messages(self, channel_id: int, log_times: np.ndarray, payloads: np.ndarray,
                            first_sequence: int) -> None:
        n = len(payloads)
        size = payloads.shape[1]
        dtype = self._dtypes.get(size)
        if dtype is None:
            dtype = self._dtypes[size] = _message_dtype(size)
        records = np.empty(n, dtype=dtype)
        records["opcode"] = Opcode.MESSAGE
        records["length"] = MESSAGE_HEADER + size
        records["channel"] = channel_id
        records["sequence"] = (first_sequence + np.arange(n, dtype=np.int64)) & 0xFFFFFFFF
        times = np.asarray(log_times, dtype=np.uint64)
        records["log_time"] = times
        records["publish_time"] = times
        records["data"] = payloads
        offsets = self._chunk.size + dtype.itemsize * np.arange(n, dtype=np.uint64)
        self._note_messages(channel_id, times, offsets)
        self._chunk.add(records)
        self._maybe_close_chunk()

    def _note_messages(self, channel_id: int, times: np.ndarray, offsets: np.ndarray) -> None:
        first, last = int(times.min()), int(times.max())
        self._chunk.times(first, last)
        if self._messages == 0:
            self._start_time, self._end_time = first, last
        else:
            self._start_time = min(self._start_time, first)
            self._end_time = max(self._end_time, last)
        n = len(times)
        self._chunk.messages += n
        self._messages += n
        self._counts[channel_id] = self._counts.get(channel_id, 0) + n
        self._chunk.index.setdefault(channel_id, []).append(np.column_stack([times, offsets]))

    # ---- chunks, flush and finish -------------------------------------------------------------

    def flush(self) -> None:
        """Close the open chunk (when it holds a message) and flush the stream."""
        self._close_chunk()
        self._stream.flush()

    def finish(self) -> None:
        """Close the open chunk and write the summary and footer (the stream stays open)."""
        self._close_chunk()
        self._stream.write(_record_bytes(DataEnd(data_section_crc=0)))
        statistics = Statistics(
            message_count=self._messages, schema_count=len(self._schemas),
            channel_count=len(self._channels), attachment_count=0,
            metadata_count=len(self._metadata_indexes), chunk_count=len(self._chunk_indexes),
            message_start_time=self._start_time, message_end_time=self._end_time,
            channel_message_counts=dict(self._counts))
        self._stream.write(summary_bytes(self._stream.tell(), self._schemas, self._channels,
                                         statistics, self._chunk_indexes,
                                         self._metadata_indexes))

    def _maybe_close_chunk(self) -> None:
        if self._chunk.size > self._chunk_size:
            self._close_chunk()

    def _close_chunk(self) -> None:
        chunk = self._chunk
        if chunk.messages == 0:
            return
        with memoryview(self._buffer) as whole, whole[:chunk.size] as data:
            compressed = self._compressor.compress(data)
            crc = zlib.crc32(data)
        # The Chunk record as mcap's RecordBuilder lays it out, written as a header and the
        # compressed bytes without first copying them into one record.
        head = (_CHUNK_HEAD.pack(Opcode.CHUNK, _CHUNK_FIXED + len(compressed),
                                 chunk.start_time, chunk.end_time, chunk.size, crc)
                + _COMPRESSION_FIELD + struct.pack("<Q", len(compressed)))
        chunk_start = self._stream.tell()
        self._stream.write(head)
        self._stream.write(compressed)
        index_start = self._stream.tell()
        index_offsets: dict[int, int] = {}
        parts = []
        pos = index_start
        for channel_id, pieces in chunk.index.items():
            entries = np.concatenate(pieces).astype("<u8", copy=False)
            index_head = _INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 6 + entries.nbytes, channel_id,
                                          entries.nbytes)
            index_offsets[channel_id] = pos
            parts.append(index_head)
            parts.append(entries.tobytes())
            pos += len(index_head) + entries.nbytes
        self._stream.write(b"".join(parts))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=chunk.start_time, message_end_time=chunk.end_time,
            chunk_start_offset=chunk_start, chunk_length=index_start - chunk_start,
            message_index_offsets=index_offsets, message_index_length=pos - index_start,
            compression=COMPRESSION, compressed_size=len(compressed),
            uncompressed_size=chunk.size))
        self._chunk = _OpenChunk(self._buffer)


def _record_bytes(record: object) -> bytes:
    builder = RecordBuilder()
    record.write(builder)  # type: ignore[attr-defined]  # every mcap record class has write()
    return builder.end()
