"""Record-level layout of an MCAP file, read tolerantly (complete, crashed or truncated files).

:func:`scan` walks the top-level records of the data section once (about three per chunk) and
returns where every chunk, message index, schema, channel and metadata record lies, without
decompressing chunks except to find Schema/Channel records that a crashed file has only inside
chunks. It stops at the first record that does not fit in the file or is not a valid opcode,
and says so in ``warnings``: everything before that point is usable.
"""

from __future__ import annotations

import mmap
import struct
import threading
from dataclasses import dataclass, field

import numpy as np
import zstandard
from mcap.opcode import Opcode
from mcap.writer import MCAP0_MAGIC

from imunoise.daq.errors import ReadError

MAGIC = MCAP0_MAGIC

# The mcap package's opcodes, as plain ints: the scan compares one per record, and an int
# comparison is several times cheaper than an IntEnum member's.
OP_HEADER = int(Opcode.HEADER)
OP_FOOTER = int(Opcode.FOOTER)
OP_SCHEMA = int(Opcode.SCHEMA)
OP_CHANNEL = int(Opcode.CHANNEL)
OP_MESSAGE = int(Opcode.MESSAGE)
OP_CHUNK = int(Opcode.CHUNK)
OP_MESSAGE_INDEX = int(Opcode.MESSAGE_INDEX)
OP_METADATA = int(Opcode.METADATA)
OP_DATA_END = int(Opcode.DATA_END)
OP_MAX = max(int(op) for op in Opcode)

RECORD_PREFIX = 9  # opcode u8 + length u64
MESSAGE_HEADER = 22  # channel u16, sequence u32, log_time u64, publish_time u64
FOOTER_LENGTH = RECORD_PREFIX + 20

_U8 = struct.Struct("<B")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_PREFIX = struct.Struct("<BQ")
_CHUNK_HEAD5 = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, len(compression)
_MI_HEAD = struct.Struct("<HI")
_DROP_EVERY = 32 << 20
_COMPRESSION = {b"": "", b"zstd": "zstd", b"lz4": "lz4"}


class McapFormatError(ReadError):
    """The file is not an MCAP file, or its records cannot be parsed."""


@dataclass
class SchemaInfo:
    id: int
    name: str
    encoding: str
    data: bytes


@dataclass
class ChannelInfo:
    id: int
    schema_id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]


@dataclass(slots=True)
class ChunkInfo:
    """One Chunk record and the MessageIndex records that follow it.

    ``mi`` maps channel id to (file offset of the first (log_time, offset) entry, entry count).
    ``has_index`` is False when no MessageIndex follows the chunk (the records must be walked).
    """

    start: int
    end: int
    message_start_time: int
    message_end_time: int
    uncompressed_size: int
    uncompressed_crc: int
    compression: str
    data_offset: int
    data_length: int
    mi: dict[int, tuple[int, int]] = field(default_factory=dict)
    mi_end: int = 0
    walked: bool = False

    @property
    def has_index(self) -> bool:
        return bool(self.mi)


class ChunkTable:
    """The chunks of a file as a sequence of :class:`ChunkInfo`, held in compact arrays.

    A day-long recording has about 10^5 chunks; as Python objects (a dataclass, a dict of
    message indexes and a dozen large ints each) they took about 0.9 kB apiece, so the index
    alone made a reader's memory grow with the file. Here a chunk takes about 0.15 kB. The
    last chunk appended stays a live object (the scan and the repair complete its message
    indexes in place); earlier ones are frozen into the arrays and read back as fresh
    :class:`ChunkInfo` objects, so a change to one of those must be stored back with
    ``table[i] = chunk``.
    """

    _COLS = ("start", "end", "message_start_time", "message_end_time", "uncompressed_size",
             "uncompressed_crc", "data_offset", "data_length", "mi_end", "walked")

    def __init__(self) -> None:
        self._rows = np.zeros((0, len(self._COLS) + 3), np.int64)  # + compression, mi at, mi n
        self._mi = np.zeros((0, 3), np.int64)  # channel id, offset, count
        self._n = 0
        self._n_mi = 0
        self._compressions: list[str] = []
        self._live: ChunkInfo | None = None

    def __len__(self) -> int:
        return self._n + (self._live is not None)

    def append(self, chunk: ChunkInfo) -> None:
        """Add the next chunk (it stays live until the following one is appended)."""
        if self._live is not None:
            self._freeze(self._n, self._live)
            self._n += 1
        self._live = chunk

    def _freeze(self, i: int, c: ChunkInfo) -> None:
        if i >= self._rows.shape[0]:
            grown = np.zeros((max(1024, 2 * self._rows.shape[0]), self._rows.shape[1]), np.int64)
            grown[:self._rows.shape[0]] = self._rows
            self._rows = grown
        if c.compression not in self._compressions:
            self._compressions.append(c.compression)
        at = self._n_mi
        if self._n_mi + len(c.mi) > self._mi.shape[0]:
            grown = np.zeros((max(1024, 2 * self._mi.shape[0] + len(c.mi)), 3), np.int64)
            grown[:self._n_mi] = self._mi[:self._n_mi]
            self._mi = grown
        for k, (cid, (pos, n)) in enumerate(c.mi.items()):
            self._mi[at + k] = (cid, pos, n)
        self._n_mi += len(c.mi)
        self._rows[i] = (c.start, c.end, c.message_start_time, c.message_end_time,
                         c.uncompressed_size, c.uncompressed_crc, c.data_offset, c.data_length,
                         c.mi_end, int(c.walked), self._compressions.index(c.compression), at,
                         len(c.mi))

    def _thaw(self, i: int) -> ChunkInfo:
        r = self._rows[i].tolist()
        at, k = r[11], r[12]
        mi = {int(cid): (int(pos), int(n)) for cid, pos, n in self._mi[at:at + k].tolist()}
        return ChunkInfo(r[0], r[1], r[2], r[3], r[4], r[5], self._compressions[r[10]], r[6],
                         r[7], mi, r[8], bool(r[9]))

    def _index(self, i: int) -> int:
        n = len(self)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError("chunk index out of range")
        return i

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(len(self)))]
        i = self._index(i)
        return self._live if i == self._n else self._thaw(i)

    def __setitem__(self, i: int, chunk: ChunkInfo) -> None:
        i = self._index(i)
        if i == self._n:
            self._live = chunk
        else:
            self._freeze(i, chunk)

    def __iter__(self):
        for i in range(self._n):
            yield self._thaw(i)
        if self._live is not None:
            yield self._live

    def __reversed__(self):
        if self._live is not None:
            yield self._live
        for i in range(self._n - 1, -1, -1):
            yield self._thaw(i)

    def __bool__(self) -> bool:
        return len(self) > 0

    def uncompressed_sizes(self) -> list[int]:
        """Every chunk's uncompressed size in bytes, in file order."""
        sizes = self._rows[:self._n, 4].tolist()
        if self._live is not None:
            sizes.append(self._live.uncompressed_size)
        return sizes


@dataclass
class MetadataInfo:
    name: str
    data: dict[str, str]
    offset: int
    length: int


@dataclass
class McapLayout:
    """What :func:`scan` found. ``data_end`` is the end of the last complete record of the data
    section (where a repaired file's DataEnd goes); ``complete`` is True when a DataEnd record
    was reached and the footer is intact (a cleanly finished file)."""

    size: int
    profile: str = ""
    library: str = ""
    schemas: dict[int, SchemaInfo] = field(default_factory=dict)
    channels: dict[int, ChannelInfo] = field(default_factory=dict)
    chunks: ChunkTable = field(default_factory=ChunkTable)
    metadata: list[MetadataInfo] = field(default_factory=list)
    unchunked_messages: int = 0
    data_end: int = 0
    complete: bool = False
    has_summary: bool = False
    footer_ok: bool = False
    warnings: list[str] = field(default_factory=list)


def _string(buf, pos: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, pos)
    pos += 4
    return bytes(buf[pos:pos + n]).decode("utf-8", "replace"), pos + n


def _map(buf, pos: int) -> tuple[dict[str, str], int]:
    (n,) = _U32.unpack_from(buf, pos)
    pos += 4
    end = pos + n
    out: dict[str, str] = {}
    while pos < end:
        key, pos = _string(buf, pos)
        value, pos = _string(buf, pos)
        out[key] = value
    return out, end


def parse_schema(buf, pos: int) -> SchemaInfo:
    (sid,) = _U16.unpack_from(buf, pos)
    name, pos = _string(buf, pos + 2)
    encoding, pos = _string(buf, pos)
    (n,) = _U32.unpack_from(buf, pos)
    return SchemaInfo(sid, name, encoding, bytes(buf[pos + 4:pos + 4 + n]))


def parse_channel(buf, pos: int) -> ChannelInfo:
    cid, sid = struct.unpack_from("<HH", buf, pos)
    topic, pos = _string(buf, pos + 4)
    encoding, pos = _string(buf, pos)
    metadata, _ = _map(buf, pos)
    return ChannelInfo(cid, sid, topic, encoding, metadata)


def iter_records(buf, start: int, end: int):
    """Yield (opcode, body_start, body_end) of the records in ``buf[start:end]``; stops
    quietly at a record that does not fit."""
    pos = start
    limit = end - RECORD_PREFIX
    while pos <= limit:
        op, n = _PREFIX.unpack_from(buf, pos)
        body = pos + RECORD_PREFIX
        if body + n > end:
            return
        yield op, body, body + n
        pos = body + n


_ZSTD = threading.local()


def _zstd_context() -> zstandard.ZstdDecompressor:
    dctx = getattr(_ZSTD, "dctx", None)
    if dctx is None:  # a decompression context is costly to create: one per thread
        dctx = _ZSTD.dctx = zstandard.ZstdDecompressor()
    return dctx


def decompress(compression: str, data, uncompressed_size: int) -> bytes | memoryview:
    """Decompress one chunk's records (``""``, ``"zstd"`` or ``"lz4"``)."""
    if compression == "":
        return data
    if compression == "zstd":
        return _zstd_context().decompress(data, max_output_size=uncompressed_size)
    if compression == "lz4":
        import lz4.frame

        return lz4.frame.decompress(bytes(data))
    raise McapFormatError(f"unsupported chunk compression {compression!r}")


def decompress_zstd_frames(frames: list, sizes: list[int]):
    """Decompress several zstd chunks of declared uncompressed ``sizes`` in one call, which
    releases the interpreter lock once for all of them rather than once per chunk. Returns a
    sequence of buffers, or None when a frame is damaged or its size differs from the declared
    one (decompress the chunks one by one to find out)."""
    try:
        return _zstd_context().multi_decompress_to_buffer(
            frames, decompressed_sizes=struct.pack(f"<{len(sizes)}Q", *sizes), threads=1)
    except zstandard.ZstdError:
        return None


def chunk_records(buf, chunk: ChunkInfo) -> bytes | memoryview:
    data = buf[chunk.data_offset:chunk.data_offset + chunk.data_length]
    return decompress(chunk.compression, data, chunk.uncompressed_size)


def _read_summary_definitions(buf, size: int, layout: McapLayout) -> None:
    """Schemas and channels from the summary section of a cleanly finished file."""
    if size < len(MAGIC) * 2 + FOOTER_LENGTH or bytes(buf[size - 8:size]) != MAGIC:
        return
    foot = size - 8 - FOOTER_LENGTH
    op, n = _PREFIX.unpack_from(buf, foot)
    if op != OP_FOOTER or n != 20:
        return
    (summary_start,) = _U64.unpack_from(buf, foot + RECORD_PREFIX)
    layout.footer_ok = True
    if summary_start == 0 or summary_start >= foot:
        return
    for op, a, _b in iter_records(buf, summary_start, foot):
        if op == OP_SCHEMA:
            s = parse_schema(buf, a)
            layout.schemas[s.id] = s
        elif op == OP_CHANNEL:
            c = parse_channel(buf, a)
            layout.channels[c.id] = c
    layout.has_summary = True


def walk_chunk(buf, chunk: ChunkInfo, layout: McapLayout,
               collect: set[int] | None = None) -> dict[int, list[tuple[int, int]]]:
    """Walk the records of one chunk: register its Schema/Channel records in ``layout`` and
    return (log_time, record offset in the decompressed chunk) of the messages of channels in
    ``collect``."""
    records = chunk_records(buf, chunk)
    offsets: dict[int, list[tuple[int, int]]] = {}
    for op, a, b in iter_records(records, 0, len(records)):
        if op == OP_MESSAGE:
            if collect is not None:
                (cid,) = _U16.unpack_from(records, a)
                if cid in collect:
                    (log_time,) = _U64.unpack_from(records, a + 6)
                    offsets.setdefault(cid, []).append((log_time, a - RECORD_PREFIX))
        elif op == OP_SCHEMA:
            s = parse_schema(records, a)
            layout.schemas.setdefault(s.id, s)
        elif op == OP_CHANNEL:
            c = parse_channel(records, a)
            layout.channels.setdefault(c.id, c)
        del b
    chunk.walked = True
    return offsets


def scan(buf, size: int | None = None) -> McapLayout:
    """Scan an MCAP file held in ``buf`` (an mmap or bytes). Raises McapFormatError when the
    file does not start with the MCAP magic and a Header record."""
    size = len(buf) if size is None else size
    layout = McapLayout(size=size)
    pos = _header(buf, size, layout)
    _read_summary_definitions(buf, size, layout)
    layout.data_end = pos
    chunks = layout.chunks
    channels = layout.channels
    last: ChunkInfo | None = None
    unknown_pending = False
    prefix = _PREFIX.unpack_from
    mi_head = _MI_HEAD.unpack_from
    drop = _PageDropper(buf)
    while True:
        drop(pos)
        if pos + RECORD_PREFIX > size:
            layout.data_end = pos
            if pos < size or not layout.complete:
                layout.warnings.append(
                    f"file ends without a summary after {pos} bytes (crashed or truncated "
                    "recording): read up to the last complete record")
            break
        op, n = prefix(buf, pos)
        body = pos + RECORD_PREFIX
        end = body + n
        if op == OP_MESSAGE_INDEX and end <= size:  # the most frequent record: keep it short
            cid, nbytes = mi_head(buf, body)
            if last is not None and last.mi_end == pos:
                last.mi[cid] = (body + 6, nbytes // 16)
                last.mi_end = end
                if cid not in channels:
                    unknown_pending = True
            pos = end
            continue
        if unknown_pending:
            _discover_channels(buf, layout)
            unknown_pending = False
        layout.data_end = pos
        if op == 0 or op > OP_MAX or end > size:
            layout.warnings.append(
                f"file is truncated or damaged at byte {pos} of {size}: read up to the last "
                "complete record")
            break
        if op == OP_CHUNK:
            last = _chunk_info(buf, pos, body, end)
            chunks.append(last)
        elif op == OP_DATA_END:
            layout.complete = layout.footer_ok
            if not layout.complete:
                layout.warnings.append("file has a damaged summary or footer: read up to the "
                                       "end of its data section")
            layout.data_end = pos
            break
        else:
            _other_record(op, buf, pos, body, end, layout)
        pos = end
    if unknown_pending:
        _discover_channels(buf, layout)
    _finish_chunks(buf, layout)
    return layout


def _header(buf, size: int, layout: McapLayout) -> int:
    """Check the magic and the Header record; note profile and library; the offset after."""
    if size < len(MAGIC) + RECORD_PREFIX or bytes(buf[:8]) != MAGIC:
        raise McapFormatError("not an MCAP file (bad magic)")
    op, n = _PREFIX.unpack_from(buf, 8)
    if op != OP_HEADER or 8 + RECORD_PREFIX + n > size:
        raise McapFormatError("not an MCAP file (no header record)")
    layout.profile, pos = _string(buf, 8 + RECORD_PREFIX)
    layout.library, _ = _string(buf, pos)
    return 8 + RECORD_PREFIX + n


class _PageDropper:
    """Drops scanned pages of a memory map as the scan goes, so that scanning a large file
    does not hold it all in resident memory (does nothing for bytes)."""

    def __init__(self, buf) -> None:
        self._drop = getattr(buf, "madvise", None) if hasattr(mmap, "MADV_DONTNEED") else None
        self._dropped = 0

    def __call__(self, pos: int) -> None:
        if self._drop is not None and pos - self._dropped > _DROP_EVERY:
            upto = pos - pos % mmap.PAGESIZE
            self._drop(mmap.MADV_DONTNEED, self._dropped, upto - self._dropped)
            self._dropped = upto


def _finish_chunks(buf, layout: McapLayout) -> None:
    """Chunks without (complete) message indexes are walked to find their messages."""
    chunks = layout.chunks
    if not layout.complete and chunks and chunks[-1].mi_end >= layout.data_end:
        # The message indexes after the last chunk of a crashed file may be cut short.
        chunks[-1].mi = {}
        chunks[-1].mi_end = chunks[-1].end
    for i, chunk in enumerate(chunks):
        if not chunk.mi and not chunk.walked:
            walk_chunk(buf, chunk, layout)
            chunks[i] = chunk


def _chunk_info(buf, pos: int, body: int, end: int) -> ChunkInfo:
    """The place and header of the Chunk record at ``pos`` (message indexes come later)."""
    t0, t1, usize, crc, clen = _CHUNK_HEAD5.unpack_from(buf, body)
    p = body + 32 + clen
    comp = _COMPRESSION.get(bytes(buf[body + 32:p])) or \
        bytes(buf[body + 32:p]).decode("utf-8", "replace")
    (rlen,) = _U64.unpack_from(buf, p)
    return ChunkInfo(pos, end, t0, t1, usize, crc, comp, p + 8, rlen, {}, end)


def _other_record(op: int, buf, pos: int, body: int, end: int, layout: McapLayout) -> None:
    """Schema, Channel, Metadata and un-chunked Message records met while scanning."""
    if op == OP_SCHEMA:
        s = parse_schema(buf, body)
        layout.schemas.setdefault(s.id, s)
    elif op == OP_CHANNEL:
        c = parse_channel(buf, body)
        layout.channels.setdefault(c.id, c)
    elif op == OP_MESSAGE:
        layout.unchunked_messages += 1
    elif op == OP_METADATA:
        name, p = _string(buf, body)
        data, _ = _map(buf, p)
        layout.metadata.append(MetadataInfo(name, data, pos, end - pos))


def _discover_channels(buf, layout: McapLayout) -> None:
    """Find Channel/Schema records of channel ids named by message indexes, walking chunks
    backwards from the newest (a channel record precedes its first message)."""
    wanted = {cid for c in layout.chunks for cid in c.mi if cid not in layout.channels}
    chunks = layout.chunks
    for i in range(len(chunks) - 1, -1, -1):
        if not wanted:
            return
        chunk = chunks[i]
        if chunk.walked:
            continue
        walk_chunk(buf, chunk, layout)
        chunks[i] = chunk
        wanted = {cid for cid in wanted if cid not in layout.channels}
