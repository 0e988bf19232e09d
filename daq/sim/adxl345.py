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

from imunoise.daq.clock import Clock
from imunoise.daq.drivers import adxl345 as ax
from imunoise.daq.sim.bench import SensorOnBench
from imunoise.daq.sim.i2c_chip import RegisterChip, SourceBuffer
from imunoise.daq.sim.signals import SignalSource

MAX_CATCH_UP = 1 << 16  # samples produced at once after a long pause (older ones are lost)


_ENTRIES = ax.REGISTERS["FIFO_ENTRIES"]


def _mode(fifo_ctl: int) -> int:
    return int(ax.REGISTERS["FIFO_MODE"].counts(fifo_ctl))


class Adxl345Sim(RegisterChip):
    """An ADXL345 driven by a specific-force source in m/s^2 (shape (n, 3))."""

    def __init__(self, clock: Clock, accel: SignalSource) -> None:
        super().__init__(clock)
        self.accel = SourceBuffer(accel)
        self.devid = ax.DEVID
        self.samples_made = 0
        self.samples_lost = 0  # ground truth: overwritten before being read
        self.environment: SensorOnBench | None = None  # the bench it sits on, if any
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
        return _mode(self.regs[ax.REG["FIFO_CTL"]])

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
        x = self.accel.take(n)
        if self.environment is not None:  # the bench's motion at these samples' times
            k = np.arange(index - n + 1, index + 1) + 1  # sample k is ready at t0 + (k+1)/rate
            x = x + self.environment.at(self._t0 + k / self.rate_hz)[:, 3:]
        counts = self._quantize(x)
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
        x = np.atleast_2d(x)
        offsets = [float(ax.REGISTERS[f"OFS{a}"].decode(self.regs[ax.REG[f"OFS{a}"]]))
                   for a in "XYZ"]
        counts = np.stack([ax.data_field(n, fmt).from_si(x[:, k] + offsets[k])
                           for k, n in enumerate(ax.DATA_FIELDS)], axis=1)
        if int(ax.REGISTERS["RATE"].counts(self.regs[ax.REG["BW_RATE"]])) >= 0x0E \
                and fmt & ax.FORMAT_FULL_RES:
            counts &= ~1  # the LSB is always 0 at 1600 and 3200 Hz
        return counts

    # -- registers ---------------------------------------------------------------------------
    def _on_write(self, reg: int, value: int) -> None:
        r = ax.REG
        if reg in (r["DEVID"], r["INT_SOURCE"], r["FIFO_STATUS"]) or \
                r["DATAX"] <= reg <= (r["DATAZ"] + 1):
            return  # read-only
        old = self.regs[reg]
        self.regs[reg] = value
        if reg == r["POWER_CTL"] and (old ^ value) & ax.POWER_MEASURE:
            self._restart()
        elif reg == r["BW_RATE"] and (old ^ value) & 0x0F:
            self._restart()
        elif reg == r["FIFO_CTL"] and _mode(old) != _mode(value):
            if _mode(value) == ax.FIFO_BYPASS:
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
            return int(_ENTRIES.encode(min(len(self.fifo), ax.FIFO_AVAILABLE)))
        if r["DATAX"] <= reg <= (r["DATAZ"] + 1):
            row = self.fifo[0] if self.fifo else self._last_row
            k = reg - r["DATAX"]
            field = ax.REGISTERS[ax.DATA_FIELDS[k // 2]]
            return field.bytes_of(int(field.encode(row[k // 2])))[k % 2]
        return self.regs[reg]

    _last_row: tuple[int, int, int] = (0, 0, 0)

    def _after_read(self, start: int, n: int) -> None:
        r = ax.REG
        if start <= (r["DATAZ"] + 1) and start + n > r["DATAX"] and self.fifo:
            self._last_row = self.fifo.popleft()
            self._overrun = False
            self.accel.prefetch()  # the host is reading the FIFO: draw ahead now
