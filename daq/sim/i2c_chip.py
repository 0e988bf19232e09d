"""Common wire behaviour of simple I2C register chips: a pointer, auto-increment, reads."""

from __future__ import annotations

import numpy as np

from imunoise.daq.clock import Clock

CHUNK = 256
"""Samples drawn from a signal source at a time. A real chip never stalls; drawing 4096 samples
of the seed-paper noise models at once took about 7 ms, longer than a sample period of a part
without a FIFO at 200 Hz and up, so the simulation itself lost samples. 256 take 0.7 ms for
three ITG-3200 channels, about 0.25 ms for one (see :meth:`SourceBuffer.prefetch`)."""


class RegisterChip:
    """Byte registers behind a pointer that the first written byte sets.

    Subclasses override :meth:`_update` (bring registers up to the clock), :meth:`_on_write`
    and :meth:`_read_byte` for registers with side effects.
    """

    n_registers = 0x40

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self.regs = bytearray(self.n_registers)
        self.pointer = 0
        self.power_on = clock.now()

    def i2c_write(self, data: bytes) -> None:
        self._update()
        if not data:
            return
        self.pointer = data[0] % self.n_registers
        for value in data[1:]:
            self._on_write(self.pointer, value)
            self.pointer = self._next(self.pointer)

    def i2c_read(self, n: int) -> bytes:
        self._update()
        out = bytearray()
        start = self.pointer
        for _ in range(n):
            out.append(self._read_byte(self.pointer) & 0xFF)
            self.pointer = self._next(self.pointer)
        self._after_read(start, n)
        return bytes(out)

    def _next(self, pointer: int) -> int:
        return (pointer + 1) % self.n_registers

    def _update(self) -> None:
        pass

    def _on_write(self, reg: int, value: int) -> None:
        self.regs[reg] = value

    def _read_byte(self, reg: int) -> int:
        return self.regs[reg]

    def _after_read(self, start: int, n: int) -> None:
        pass


class SourceBuffer:
    """Draws a triad signal source in chunks and hands out the next samples in order.

    A source that exposes its three channels (``source.channels``: the per-channel
    ``take(n)`` functions and the triad's offset, as :func:`imunoise.daq.sim.signals.model_source`
    does) is drawn ahead one channel per :meth:`prefetch`, so that no single read of the
    chip carries the cost of a whole chunk of three channels.
    """

    def __init__(self, source) -> None:
        self.source = source
        self._channels = getattr(source, "channels", None)
        self._pending: list[np.ndarray] = []
        self._buf = np.zeros((0, 3))
        self._pos = 0

    def _next_chunk(self, n: int = CHUNK) -> np.ndarray:
        """The next samples of the source: the chunk being drawn ahead, completed, if one is
        under way (the channels stay in step), else ``n`` new samples."""
        if self._channels is None:
            return self.source(n)
        takes, offset = self._channels
        if self._pending:
            parts = self._pending + [take(CHUNK) for take in takes[len(self._pending):]]
            self._pending = []
            return offset + np.column_stack(parts)
        return offset + np.column_stack([take(n) for take in takes])

    def take(self, n: int) -> np.ndarray:
        parts = []
        while n > 0:
            if self._pos >= len(self._buf):
                self._buf, self._pos = self._next_chunk(max(CHUNK, min(n, 1 << 16))), 0
            k = min(n, len(self._buf) - self._pos)
            parts.append(self._buf[self._pos:self._pos + k])
            self._pos += k
            n -= k
        return np.vstack(parts) if parts else np.zeros((0, 3))

    def prefetch(self) -> None:
        """Draw ahead when less than half a chunk is left: one channel per call when the
        source exposes its channels, else the whole next chunk.

        A chip model calls this right after the host has read a sample's data, when the host
        has the most time before it polls again; drawn later, inside the next status read,
        the draw would hold the host up between the status and the data reads.
        """
        left = len(self._buf) - self._pos
        if left >= CHUNK // 2:
            return
        if self._channels is not None:
            takes, _ = self._channels
            self._pending.append(takes[len(self._pending)](CHUNK))
            if len(self._pending) < len(takes):
                return
        self._buf = np.vstack([self._buf[self._pos:], self._next_chunk()])
        self._pos = 0

    def skip_take_last(self, n: int) -> np.ndarray:
        """Advance ``n`` samples (n >= 1), returning only the last (bounded memory)."""
        while n > len(self._buf) - self._pos:
            n -= len(self._buf) - self._pos
            self._buf, self._pos = self._next_chunk(), 0
        self._pos += n
        return self._buf[self._pos - 1]
