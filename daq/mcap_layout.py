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
import zlib
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
OP_CHUNK_INDEX = int(Opcode.CHUNK_INDEX)
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
    damaged: list[tuple[int, str]] = field(default_factory=list)
    """(file offset, reason) of every chunk left out of ``chunks`` because it is damaged."""
    indexed_chunks: list[tuple[int, int]] = field(default_factory=list)
    """(offset, length) of the chunks the summary's chunk index lists (a cleanly finished
    file): where the scan resumes after a damaged record."""

    def drop_chunk(self, start: int, reason: str) -> None:
        """Note a damaged chunk (its messages are lost) with a warning."""
        self.damaged.append((start, reason))
        self.warnings.append(damaged_chunk_note(start, reason))


def damaged_chunk_note(start: int, reason: str, messages: int | None = None,
                       times: tuple[int, int] | None = None) -> str:
    """The one-line warning for a damaged chunk left out."""
    what = f"its {messages} message(s)" if messages is not None else "its messages"
    when = ""
    if times is not None and 0 < times[0] <= times[1]:
        when = f", log time {times[0] * 1e-9:.3f} to {times[1] * 1e-9:.3f} s"
    return f"chunk at byte {start} is damaged ({reason}): {what}{when} are lost (a gap)"


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


class DamagedChunk(McapFormatError):
    """A chunk's records cannot be trusted: they do not decompress, their size or CRC differs
    from the chunk header, or they are not a sequence of complete records."""


def decompress(compression: str, data, uncompressed_size: int) -> bytes | memoryview:
    """Decompress one chunk's records (``""``, ``"zstd"`` or ``"lz4"``).

    Raises:
        DamagedChunk: the data do not decompress.
        McapFormatError: an unsupported compression.
    """
    if compression == "":
        out = data
    elif compression == "zstd":
        try:
            out = _zstd_context().decompress(data, max_output_size=uncompressed_size)
        except zstandard.ZstdError as exc:
            raise DamagedChunk(f"zstd: {first_line(exc)}") from None
    elif compression == "lz4":
        import lz4.frame

        try:  # at most one byte more than declared: a damaged frame cannot claim gigabytes
            out = lz4.frame.LZ4FrameDecompressor().decompress(
                bytes(data), max_length=2 * uncompressed_size + (1 << 20))
        except (RuntimeError, ValueError, MemoryError) as exc:
            raise DamagedChunk(f"lz4: {first_line(exc)}") from None
    else:
        raise McapFormatError(f"unsupported chunk compression {compression[:40]!r}")
    return out


def first_line(exc: BaseException, limit: int = 80) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else type(exc).__name__)[:limit]


# Records a chunk may hold (the specification's list).
_IN_CHUNK = frozenset({OP_SCHEMA, OP_CHANNEL, OP_MESSAGE})


def check_chunk(buf, chunk: ChunkInfo, exact_size: bool = False) -> bytes | memoryview:
    """The decompressed records of ``chunk`` after checking them: the data decompress, their
    CRC matches when the writer stored one (else their size must be the header's; with
    ``exact_size`` it must be in any case), and they are a sequence of complete Schema,
    Channel and Message records.

    Raises:
        DamagedChunk: what failed.
    """
    if chunk.data_offset + chunk.data_length > chunk.end:
        raise DamagedChunk("records run past the chunk")
    records = chunk_records(buf, chunk)
    if chunk.uncompressed_crc and zlib.crc32(records) != chunk.uncompressed_crc:
        raise DamagedChunk("CRC mismatch")
    if (exact_size or not chunk.uncompressed_crc) and len(records) != chunk.uncompressed_size:
        raise DamagedChunk(f"{len(records)} bytes of records where its header says "
                           f"{chunk.uncompressed_size}")
    pos, size = 0, len(records)
    while pos < size:
        if pos + RECORD_PREFIX > size:
            raise DamagedChunk(f"a record cut short at byte {pos} of its records")
        op, n = _PREFIX.unpack_from(records, pos)
        if op not in _IN_CHUNK or pos + RECORD_PREFIX + n > size or (
                op == OP_MESSAGE and n < MESSAGE_HEADER):
            raise DamagedChunk(f"a malformed record at byte {pos} of its records")
        pos += RECORD_PREFIX + n
    return records


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
    """Schemas and channels from the summary section of a cleanly finished file. A summary
    whose records do not fit exactly between its start and the footer is ignored (the file
    then counts as not cleanly finished)."""
    if size < len(MAGIC) * 2 + FOOTER_LENGTH or bytes(buf[size - 8:size]) != MAGIC:
        return
    foot = size - 8 - FOOTER_LENGTH
    op, n = _PREFIX.unpack_from(buf, foot)
    if op != OP_FOOTER or n != 20:
        return
    (summary_start,) = _U64.unpack_from(buf, foot + RECORD_PREFIX)
    if summary_start == 0:
        layout.footer_ok = True
        return
    if summary_start >= foot or summary_start < len(MAGIC):
        return
    found: list = []
    starts: list[tuple[int, int]] = []
    pos = summary_start
    try:
        while pos < foot:
            op, n = _PREFIX.unpack_from(buf, pos)
            if op == 0 or op > OP_MAX or pos + RECORD_PREFIX + n > foot:
                return
            if op == OP_SCHEMA:
                found.append(parse_schema(buf, pos + RECORD_PREFIX))
            elif op == OP_CHANNEL:
                found.append(parse_channel(buf, pos + RECORD_PREFIX))
            elif op == OP_CHUNK_INDEX and n >= 32:
                starts.append(struct.unpack_from("<QQ", buf, pos + RECORD_PREFIX + 16))
            pos += RECORD_PREFIX + n
    except (struct.error, ValueError):
        return
    layout.indexed_chunks = sorted(starts)
    for item in found:
        (layout.schemas if isinstance(item, SchemaInfo) else layout.channels)[item.id] = item
    layout.footer_ok = True
    layout.has_summary = True


def walk_chunk(buf, chunk: ChunkInfo, layout: McapLayout,
               collect: set[int] | None = None) -> dict[int, list[tuple[int, int]]]:
    """Walk the records of one chunk: register its Schema/Channel records in ``layout`` and
    return (log_time, record offset in the decompressed chunk) of the messages of channels in
    ``collect``. Raises DamagedChunk when :func:`check_chunk` fails (nothing registered)."""
    records = check_chunk(buf, chunk)
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
            cid, nbytes = mi_head(buf, body) if n >= 6 else (0, n)
            if last is not None and last.mi_end == pos:
                if 6 + nbytes != n or nbytes % 16:  # damaged: walk the chunk instead
                    last.mi, last.mi_end, last = {}, last.end, None
                else:
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
            resume = _resume_at(buf, pos, layout)
            if resume is None:
                layout.warnings.append(
                    f"file is truncated or damaged at byte {pos} of {size}: read up to the "
                    "last complete record")
                break
            layout.warnings.append(
                f"a damaged record at byte {pos}: its chunk's messages are lost (a gap); read "
                f"on from byte {resume}, the next chunk the file's summary lists")
            pos, last = resume, None
            continue
        if op == OP_CHUNK:
            last = _add_chunk(buf, pos, body, end, layout)
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


def _resume_at(buf, pos: int, layout: McapLayout) -> int | None:
    """The offset of the first chunk after ``pos`` that the summary lists and that is where
    it says (a Chunk record of the listed length), or None."""
    for start, length in layout.indexed_chunks:
        if start <= pos or start + length > layout.size:
            continue
        op, n = _PREFIX.unpack_from(buf, start)
        if op == OP_CHUNK and RECORD_PREFIX + n == length:
            return start
    return None


def _header(buf, size: int, layout: McapLayout) -> int:
    """Check the magic and the Header record; note profile and library; the offset after."""
    if size < len(MAGIC) + RECORD_PREFIX or bytes(buf[:8]) != MAGIC:
        raise McapFormatError("not an MCAP file (bad magic)")
    op, n = _PREFIX.unpack_from(buf, 8)
    if op != OP_HEADER or 8 + RECORD_PREFIX + n > size:
        raise McapFormatError("not an MCAP file (no header record)")
    try:
        layout.profile, pos = _string(buf, 8 + RECORD_PREFIX)
        layout.library, _ = _string(buf, pos)
    except struct.error:
        layout.warnings.append("the header record is damaged (profile and library unknown)")
    layout.profile, layout.library = layout.profile[:200], layout.library[:200]
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
    bad: set[int] = set()
    for i, chunk in enumerate(chunks):
        if not chunk.mi and not chunk.walked:
            try:
                walk_chunk(buf, chunk, layout)
            except DamagedChunk as exc:
                layout.drop_chunk(chunk.start, str(exc))
                bad.add(chunk.start)
                continue
            chunks[i] = chunk
    remove_chunks(layout, bad)


def remove_chunks(layout: McapLayout, starts: set[int]) -> None:
    """Take the chunks at file offsets ``starts`` out of ``layout.chunks``."""
    if not starts:
        return
    kept = ChunkTable()
    for chunk in layout.chunks:
        if chunk.start not in starts:
            kept.append(chunk)
    layout.chunks = kept


_MAX_CHUNK = 1 << 40  # uncompressed bytes: a larger chunk header is damaged
_MAX_TIME = (1 << 63) - 1  # log times are u64; those beyond int64 (year 2262) are damaged


def _add_chunk(buf, pos: int, body: int, end: int, layout: McapLayout) -> ChunkInfo | None:
    """Append the Chunk record at ``pos`` to the layout's chunks; None when its header is
    damaged (the chunk is left out, its message indexes are skipped)."""
    try:
        chunk = _chunk_info(buf, pos, body, end)
    except DamagedChunk as exc:
        layout.drop_chunk(pos, str(exc))
        return None
    layout.chunks.append(chunk)
    return chunk


def _chunk_info(buf, pos: int, body: int, end: int) -> ChunkInfo:
    """The place and header of the Chunk record at ``pos`` (message indexes come later).
    Raises DamagedChunk when the header's fields do not fit the record."""
    if body + _CHUNK_HEAD5.size + 8 > end:
        raise DamagedChunk("header cut short")
    t0, t1, usize, crc, clen = _CHUNK_HEAD5.unpack_from(buf, body)
    p = body + 32 + clen
    if p + 8 > end:
        raise DamagedChunk("compression field runs past the record")
    comp = _COMPRESSION.get(bytes(buf[body + 32:p])) or \
        bytes(buf[body + 32:p]).decode("utf-8", "replace")[:40]
    (rlen,) = _U64.unpack_from(buf, p)
    if p + 8 + rlen != end:
        raise DamagedChunk("records length differs from the record's")
    if usize > _MAX_CHUNK or t0 > _MAX_TIME or t1 > _MAX_TIME:
        raise DamagedChunk("header fields out of range")
    _check_declared_size(buf, comp, p + 8, rlen, usize)
    return ChunkInfo(pos, end, t0, t1, usize, crc, comp, p + 8, rlen, {}, end)


def _check_declared_size(buf, compression: str, at: int, length: int, usize: int) -> None:
    """A chunk's declared uncompressed size must be one its data can hold (readers allocate
    it): equal to the data for no compression, at most what lz4 can expand to, at most the
    zstd frame's own content size when the frame states it."""
    if compression == "" and usize != length:
        raise DamagedChunk("uncompressed size differs from its data's")
    if compression == "lz4" and usize > 255 * length + (1 << 16):
        raise DamagedChunk("uncompressed size larger than lz4 can expand to")
    if compression == "zstd":
        try:
            stated = zstandard.frame_content_size(bytes(buf[at:at + min(length, 18)]))
        except zstandard.ZstdError:
            raise DamagedChunk("not a zstd frame") from None
        if stated >= 0 and usize > max(stated, 0) + (1 << 16):
            raise DamagedChunk(f"uncompressed size {usize} beyond its frame's {stated}")
        if stated < 0 and usize > 32768 * length + (1 << 20):
            raise DamagedChunk("uncompressed size larger than zstd can expand to")


def _other_record(op: int, buf, pos: int, body: int, end: int, layout: McapLayout) -> None:
    """Schema, Channel, Metadata and un-chunked Message records met while scanning; a damaged
    one is skipped with a warning."""
    try:
        _parse_other(op, buf, pos, body, end, layout)
    except (struct.error, ValueError):
        layout.warnings.append(f"a damaged record (opcode {op}) at byte {pos} was skipped")


def _parse_other(op: int, buf, pos: int, body: int, end: int, layout: McapLayout) -> None:
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
        try:
            walk_chunk(buf, chunk, layout)
        except DamagedChunk:
            continue  # its messages are dropped when read; the reader says so
        chunks[i] = chunk
        wanted = {cid for cid in wanted if cid not in layout.channels}
