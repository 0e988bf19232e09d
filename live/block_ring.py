"""A bounded shared-memory ring that hands sample blocks from the acquisition process to the
analysis side without ever blocking the producer.

One producer (the acquisition process) and one consumer (the analysis side of ``serve``). The
producer never waits: when the consumer has fallen so far behind that a block does not fit, the
block is not handed over, the samples are counted as lost *in the hand-over* and the next block
of the same stream that fits carries that count (``lost_before``), so the analysis of that
stream starts a new segment there (a temperature block handed over first must not take the IMU
stream's loss). The recording, which the producer writes itself, is not affected.

Layout of the shared memory (little-endian; counters are 8-byte aligned, written with single
aligned stores):

======  =====================================================================================
offset  content
======  =====================================================================================
0       magic ``b"IMURING1"``
8       capacity of the data area in bytes
16      bytes written so far (producer; only ever grows)
24      bytes read so far (consumer; only ever grows)
32      samples not handed over because the ring was full (producer)
40      blocks not handed over (producer)
48      status sequence number (odd while the producer rewrites the status)
56      status length in bytes
64      status: a JSON object of at most ``STATUS_BYTES`` (the producer's counters)
64+S    data area: records ``[u32 payload length][u32 crc32][u64 lost_before][payload]``,
        padded to 8 bytes; a length of ``0xFFFFFFFF`` marks the unused end of the area
        before a record that starts again at its beginning
======  =====================================================================================

The consumer checks each record's CRC: on a processor that may make the counter visible before
the payload, a record read too early is simply read again on the next poll.
"""

from __future__ import annotations

import json
import pickle
import struct
import zlib
from multiprocessing import shared_memory
from typing import Any

MAGIC = b"IMURING1"
STATUS_BYTES = 16 * 1024
_HEADER = 64 + STATUS_BYTES
_REC = struct.Struct("<IIQ")  # payload length, crc32, lost_before (samples)
_U64 = struct.Struct("<Q")
_WRAP = 0xFFFFFFFF
_OFF_CAP, _OFF_W, _OFF_R, _OFF_LOST, _OFF_LOST_BLOCKS, _OFF_SEQ, _OFF_SLEN = (
    8, 16, 24, 32, 40, 48, 56)

DEFAULT_CAPACITY = 64 * 1024 * 1024
"""Bytes of the data area: about 2.5 min of an ADIS16350 at 819 Hz, far more at 100 Hz,
before a stalled analysis side starts losing blocks."""


def _pad(n: int) -> int:
    return (n + 7) & ~7


class BlockRing:
    """The ring in one process. Create it in the consumer's process (``create=True``), attach
    to it by ``name`` in the producer's.

    Args:
        name: shared-memory name (``None`` with ``create``: a fresh one).
        create: create the segment (and own it: :meth:`unlink` removes it).
        capacity: data-area bytes (with ``create``).
    """

    def __init__(self, name: str | None = None, *, create: bool = False,
                 capacity: int = DEFAULT_CAPACITY) -> None:
        if create:
            capacity = _pad(int(capacity))
            if capacity < 4096:
                raise ValueError(f"ring capacity must be at least 4096 bytes, got {capacity}")
            self._shm = shared_memory.SharedMemory(name=name, create=True,
                                                   size=_HEADER + capacity)
            buf = self._shm.buf
            buf[:_HEADER] = bytes(_HEADER)
            buf[:8] = MAGIC
            _U64.pack_into(buf, _OFF_CAP, capacity)
        else:
            if name is None:
                raise ValueError("attach needs the ring's name")
            self._shm = shared_memory.SharedMemory(name=name, create=False)
            if bytes(self._shm.buf[:8]) != MAGIC:
                self._shm.close()
                raise ValueError(f"shared memory {name!r} is not a block ring")
        self.owner = create
        self.name = self._shm.name
        self._buf = self._shm.buf
        self.capacity = self._get(_OFF_CAP)
        # producer: per stream, samples dropped since its last record handed over
        self._pending_lost: dict[str, int] = {}

    # ------------------------------------------------------------------ counters
    def _get(self, off: int) -> int:
        return _U64.unpack_from(self._buf, off)[0]

    def _set(self, off: int, value: int) -> None:
        _U64.pack_into(self._buf, off, value)

    @property
    def lost_samples(self) -> int:
        """Samples the producer could not hand over (ring full), since the ring was made."""
        return self._get(_OFF_LOST)

    @property
    def lost_blocks(self) -> int:
        return self._get(_OFF_LOST_BLOCKS)

    @property
    def used_bytes(self) -> int:
        """Bytes written and not yet read."""
        return self._get(_OFF_W) - self._get(_OFF_R)

    # ------------------------------------------------------------------ producer
    def put(self, block: Any, n_samples: int) -> bool:
        """Hand a block over (pickled); False, with its ``n_samples`` counted as lost, when it
        does not fit. Never blocks."""
        payload = pickle.dumps(block, protocol=pickle.HIGHEST_PROTOCOL)
        return self.put_bytes(payload, n_samples, str(getattr(block, "stream", "")))

    def put_bytes(self, payload: bytes, n_samples: int, stream: str = "") -> bool:
        """:meth:`put` of a block already pickled; ``stream`` keys its hand-over losses."""
        cap = self.capacity
        w = self._get(_OFF_W)
        free = cap - (w - self._get(_OFF_R))
        need = _REC.size + _pad(len(payload))
        at = w % cap
        waste = cap - at if at + need > cap else 0  # the record must not straddle the end
        if need > cap // 2 or need + waste > free:
            self._pending_lost[stream] = self._pending_lost.get(stream, 0) + n_samples
            self._set(_OFF_LOST, self._get(_OFF_LOST) + n_samples)
            self._set(_OFF_LOST_BLOCKS, self._get(_OFF_LOST_BLOCKS) + 1)
            return False
        buf = self._buf
        if waste:
            if waste >= 4:
                struct.pack_into("<I", buf, _HEADER + at, _WRAP)
            w += waste
            at = 0
        start = _HEADER + at
        buf[start + _REC.size:start + _REC.size + len(payload)] = payload
        _REC.pack_into(buf, start, len(payload), zlib.crc32(payload),
                       self._pending_lost.get(stream, 0))
        self._set(_OFF_W, w + need)  # publish after the record is in place
        self._pending_lost.pop(stream, None)
        return True

    def publish_status(self, status: dict[str, Any]) -> None:
        """Replace the status the consumer reads (JSON, at most ``STATUS_BYTES``)."""
        data = json.dumps(status, default=str).encode()[:STATUS_BYTES]
        seq = self._get(_OFF_SEQ)
        self._set(_OFF_SEQ, seq + 1)  # odd: being written
        self._buf[64:64 + len(data)] = data
        self._set(_OFF_SLEN, len(data))
        self._set(_OFF_SEQ, seq + 2)

    # ------------------------------------------------------------------ consumer
    def get(self) -> tuple[Any, int] | None:
        """The next block and the samples lost in the hand-over just before it, or None when
        nothing (complete) is waiting."""
        got = self.get_bytes()
        if got is None:
            return None
        payload, lost = got
        return pickle.loads(payload), lost

    def get_bytes(self) -> tuple[bytes, int] | None:
        cap = self.capacity
        while True:
            r = self._get(_OFF_R)
            if r >= self._get(_OFF_W):
                return None
            at = r % cap
            if cap - at < _REC.size or struct.unpack_from("<I", self._buf,
                                                          _HEADER + at)[0] == _WRAP:
                self._set(_OFF_R, r + (cap - at))
                continue
            length, crc, lost = _REC.unpack_from(self._buf, _HEADER + at)
            start = _HEADER + at + _REC.size
            payload = bytes(self._buf[start:start + length])
            if zlib.crc32(payload) != crc:
                return None  # not complete yet: read again later
            self._set(_OFF_R, r + _REC.size + _pad(length))
            return payload, lost

    def status(self) -> dict[str, Any]:
        """The producer's last published status ({} before the first)."""
        for _ in range(100):
            seq = self._get(_OFF_SEQ)
            if seq % 2:
                continue
            n = self._get(_OFF_SLEN)
            data = bytes(self._buf[64:64 + n])
            if self._get(_OFF_SEQ) == seq:
                try:
                    return json.loads(data) if n else {}
                except ValueError:
                    return {}
        return {}

    # ------------------------------------------------------------------ life cycle
    def close(self) -> None:
        self._buf = None
        try:
            self._shm.close()
        except BufferError:  # a view still exported: the mapping goes with the process
            pass

    def unlink(self, *, orphaned: bool = False) -> None:
        """Remove the segment (owner only, or with ``orphaned`` when its owner has died);
        attached processes keep their mapping."""
        if self.owner or orphaned:
            try:
                self._shm.unlink()
            except FileNotFoundError:
                pass
