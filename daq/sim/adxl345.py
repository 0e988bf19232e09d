"""Register-level model of the ADXL345 accelerometer as its I2C wire sees it.

Powers up in standby (no data until POWER_CTL.Measure), DEVID 0xE5, BW_RATE reset 0x0A,
INT_SOURCE reset 0x02; output rate from BW_RATE; full-resolution or 10-bit data clipped to the
range, the lowest bit zero at 1600 and 3200 Hz; little-endian DATAx registers; the FIFO in
bypass, FIFO or stream mode (32 entries plus the output registers: 33 available), one entry
popped by each read that covers the data registers, overrun when stream mode overwrites,
DATA_READY / watermark / overrun in INT_SOURCE following the FIFO. Fault: wrong DEVID.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np

from daq.clock import Clock
from daq.drivers import adxl345 as ax
from daq.sim.i2c_chip import RegisterChip, SourceBuffer
from daq.sim.signals import SignalSource

MAX_CATCH_UP = 1 << 16  # samples produced at once after a long pause (older ones are lost)


class Adxl345Sim(RegisterChip):
    """An ADXL345 driven by a specific-force source in m/s^2 (shape (n, 3))."""

    def __init__(self, clock: Clock, accel: SignalSource) -> None:
        super().__init__(clock)
        self.accel = SourceBuffer(accel)
        self.devid = ax.DEVID
        self.samples_made = 0
        self.samples_lost = 0  # ground truth: overwritten before being read
        self.fifo: deque[tuple[int, int, int]] = deque()
        self.regs[ax.REG["BW_RATE"]] = ax.BW_RATE_RESET
        self._overrun = False
        self._t0 = clock.now()
        self._index = -1

    @property
    def rate_hz(self) -> float:
        return ax.odr_hz(self.regs[ax.REG["BW_RATE"]] & 0x0F)

    @property
    def measuring(self) -> bool:
        return bool(self.regs[ax.REG["POWER_CTL"]] & ax.POWER_MEASURE)

    @property
    def fifo_mode(self) -> int:
        return self.regs[ax.REG["FIFO_CTL"]] >> ax.FIFO_MODE_SHIFT

    def _capacity(self) -> int:
        return 1 if self.fifo_mode == ax.FIFO_BYPASS else ax.FIFO_AVAILABLE

    def _restart(self) -> None:
        self._t0 = self.clock.now()
        self._index = -1

    def _update(self) -> None:
        if not self.measuring:
            return
        # Sample k is ready one output period after the one before; the first one period
        # after entering measurement mode.
        index = int(math.floor((self.clock.now() - self._t0) * self.rate_hz)) - 1
        n = index - self._index
        if n <= 0:
            return
        self._index = index
        self.samples_made += n
        if n > MAX_CATCH_UP:
            self.accel.skip_take_last(n - MAX_CATCH_UP)
            self._push_lost(n - MAX_CATCH_UP)
            n = MAX_CATCH_UP
        counts = self._quantize(self.accel.take(n))
        cap = self._capacity()
        if self.fifo_mode == ax.FIFO_FIFO:
            room = cap - len(self.fifo)
            if n > room:
                self._push_lost(n - max(room, 0))
            counts = counts[:max(room, 0)]
        for row in counts.tolist():
            if len(self.fifo) >= cap:
                self.fifo.popleft()
                self._push_lost(1)
            self.fifo.append(tuple(row))

    def _push_lost(self, n: int) -> None:
        self.samples_lost += n
        self._overrun = True

    def _quantize(self, x: np.ndarray) -> np.ndarray:
        fmt = self.regs[ax.REG["DATA_FORMAT"]]
        rng = fmt & 0x03
        lsb_g = 1.0 / ax.LSB_PER_G
        bits = 10
        if fmt & ax.FORMAT_FULL_RES:
            bits = 10 + rng
        else:
            lsb_g *= 2 ** rng
        offsets = np.frombuffer(bytes(self.regs[ax.REG["OFSX"]:ax.REG["OFSZ"] + 1]),
                                dtype=np.int8).astype(np.float64) * 15.6e-3
        g = x / ax.G0 + offsets
        counts = np.round(g / lsb_g)
        lim = 2 ** (bits - 1)
        counts = np.clip(counts, -lim, lim - 1).astype(np.int64)
        if (self.regs[ax.REG["BW_RATE"]] & 0x0F) >= 0x0E and fmt & ax.FORMAT_FULL_RES:
            counts &= ~1  # the LSB is always 0 at 1600 and 3200 Hz
        return counts

    # -- registers ---------------------------------------------------------------------------
    def _on_write(self, reg: int, value: int) -> None:
        r = ax.REG
        if reg in (r["DEVID"], r["INT_SOURCE"], r["FIFO_STATUS"]) or \
                r["DATAX0"] <= reg <= r["DATAZ1"]:
            return  # read-only
        old = self.regs[reg]
        self.regs[reg] = value
        if reg == r["POWER_CTL"] and (old ^ value) & ax.POWER_MEASURE:
            self._restart()
        elif reg == r["BW_RATE"] and (old ^ value) & 0x0F:
            self._restart()
        elif reg == r["FIFO_CTL"] and (old >> ax.FIFO_MODE_SHIFT) != (value >> ax.FIFO_MODE_SHIFT):
            if value >> ax.FIFO_MODE_SHIFT == ax.FIFO_BYPASS:
                while len(self.fifo) > 1:
                    self.fifo.popleft()
            self._overrun = False

    def _int_source(self) -> int:
        v = 0
        if self.fifo:
            v |= ax.INT_DATA_READY
        if len(self.fifo) >= (self.regs[ax.REG["FIFO_CTL"]] & 0x1F):
            v |= ax.INT_WATERMARK
        if self._overrun:
            v |= ax.INT_OVERRUN
        return v

    def _read_byte(self, reg: int) -> int:
        r = ax.REG
        if reg == r["DEVID"]:
            return self.devid
        if reg == r["INT_SOURCE"]:
            return self._int_source()
        if reg == r["FIFO_STATUS"]:
            return min(len(self.fifo), ax.FIFO_AVAILABLE) & ax.FIFO_ENTRIES_MASK
        if r["DATAX0"] <= reg <= r["DATAZ1"]:
            row = self.fifo[0] if self.fifo else self._last_row
            k = reg - r["DATAX0"]
            word = row[k // 2] & 0xFFFF
            return (word >> 8) if k % 2 else (word & 0xFF)
        return self.regs[reg]

    _last_row: tuple[int, int, int] = (0, 0, 0)

    def _after_read(self, start: int, n: int) -> None:
        r = ax.REG
        if start <= r["DATAZ1"] and start + n > r["DATAX0"] and self.fifo:
            self._last_row = self.fifo.popleft()
            self._overrun = False
