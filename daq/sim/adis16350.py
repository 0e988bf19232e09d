"""Register-level model of the ADIS16350 on its SPI pins.

Behaves as datasheet Rev. B describes: 16-bit frames, byte-wise writes, reads answered in the
next frame, new-data (ND) flags set by each internal update and cleared by reading, the error
flag (EA) mirroring STATUS, STATUS cleared on read, SMPL_PRD setting the update rate, SENS/AVG
the range, the self-test cycle, reset and power-up delays, over-range clipping at 14 bits.
The physical signal comes from injected sources (SI units), quantized to the part's LSB.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from imunoise.daq.clock import Clock
from imunoise.daq.drivers import adis16350 as reg
from imunoise.daq.sim.bench import SensorOnBench
from imunoise.daq.sim.signals import SignalSource, TemperatureSource, drifting_temperature

CHUNK = 256  # samples generated per call of a signal source (see imunoise.daq.sim.i2c_chip.CHUNK)
SELF_TEST_S = 0.035
TEMP_AXIS_OFFSET_C = (0.0, 0.4, -0.3)  # the three sensors do not sit at one temperature

VOLATILE_DEFAULTS = {"AUX_DAC": 0, "GPIO_CTRL": 0, "SLP_CNT": 0, "STATUS": 0}


class Adis16350Sim:
    """An ADIS16350 as seen from its SPI pins.

    Args:
        clock: time source (a :class:`~imunoise.daq.clock.VirtualClock` for faster than real time).
        gyro: source of angular rate (rad/s, shape (n, 3)) at ``source_rate_hz``.
        accel: source of specific force (m/s^2).
        temperature: degC as a function of time since power-up.
        source_rate_hz: the rate the sources were built for (they are drawn once per update).
        supply_v: supply voltage shown in SUPPLY_OUT.

    Fault switches (attributes): ``stuck_data`` (no more internal updates, ND never sets,
    until a software reset), ``self_test_fails``.

    Ground truth for the host's loss estimate (the part itself has no sample counter):
    ``samples_never_read`` counts the samples that appeared between two reads of fresh data
    (ND set in XGYRO_OUT) and were overwritten unread; ``on_never_read``, when set, is called
    with the new total whenever it grows.
    """

    def __init__(self, clock: Clock, gyro: SignalSource, accel: SignalSource,
                 temperature: TemperatureSource | None = None, *, source_rate_hz: float,
                 supply_v: float = 5.0) -> None:
        self.clock = clock
        self.gyro, self.accel = gyro, accel
        self.temperature = temperature or drifting_temperature()
        self.source_rate_hz = source_rate_hz
        self.supply_v = supply_v
        self.stuck_data = False
        self.self_test_fails = False
        self.undefined_writes = 0  # writes to byte 0x3F (e.g. a 0xFFFF dummy frame)
        self.emulator: object | None = None  # the bridge it sits behind, when there is one
        self.frames = 0
        self.samples_never_read = 0
        self.on_never_read: Callable[[int], None] | None = None
        self.environment: SensorOnBench | None = None  # the bench it sits on, if any
        self._last_read_index: int | None = None
        self.words = {r.addr: 0 for r in reg.REGISTERS.values()}
        self.words[reg.ADDR["SMPL_PRD"]] = reg.SMPL_PRD_DEFAULT
        self.words[reg.ADDR["SENS_AVG"]] = reg.SENS_AVG_DEFAULT
        self._power_on = clock.now()
        self._nd = 0  # bit set of output addresses with unread data
        self._status = 0
        self._self_test_until = -1.0
        self._selected = False
        self._shift_in: list[int] = []
        self._shift_out = 0
        self._next_out = 0
        self._spi_error = False
        self._buf = np.zeros((0, 6))
        self._pos = 0
        self._restart(reg.STARTUP_S)

    # -- time base -------------------------------------------------------------------------
    def _restart(self, delay_s: float) -> None:
        self._t0 = self.clock.now() + delay_s
        self._index = -1
        self._last_read_index = None  # a new time base: nothing before it counts

    @property
    def rate_hz(self) -> float:
        return reg.sample_rate_hz(self.words[reg.ADDR["SMPL_PRD"]])

    def _update(self) -> None:
        now = self.clock.now()
        if self.stuck_data or now < self._t0 or now < self._self_test_until:
            return
        if self._self_test_until >= 0:
            self._finish_self_test()
        index = int(math.floor((now - self._t0) * self.rate_hz))
        if index <= self._index:
            return
        x = self._advance(index - self._index)
        if self.environment is not None:  # the bench's motion at this sample's time
            x = x + self.environment.at(self._t0 + index / self.rate_hz)[0]
        self._latch(x)
        self._index = index
        self._nd = 0xFFFF

    def _advance(self, d: int) -> np.ndarray:
        """Draw the next ``d`` samples from the sources (in chunks); return the last one."""
        while d > len(self._buf) - self._pos:
            d -= len(self._buf) - self._pos
            self._buf = np.hstack([self.gyro(CHUNK), self.accel(CHUNK)])
            self._pos = 0
        self._pos += d
        return self._buf[self._pos - 1]

    def _latch(self, x: np.ndarray) -> None:
        rng = reg.decode_sens_avg(self.words[reg.ADDR["SENS_AVG"]])[0]
        fields = [reg.gyro_field(n, rng) if "GYRO" in n else reg.REGISTERS[n]
                  for n in reg.IMU_REGISTERS]
        for f, v in zip(fields, x, strict=True):
            c = int(f.from_si(v))
            if abs(c - v / f.scale) > 0.5 + 1e-9:  # saturated at 14 bits
                self._status |= reg.STATUS_OVER_RANGE
            self.words[f.addr] = int(f.encode(c))
        t = self.clock.now() - self._power_on
        temp = float(self.temperature(np.array([t]))[0])
        for name, off in zip(("XTEMP_OUT", "YTEMP_OUT", "ZTEMP_OUT"), TEMP_AXIS_OFFSET_C,
                             strict=True):
            f = reg.REGISTERS[name]
            self.words[f.addr] = int(f.encode(f.from_si(temp + off)))
        supply = reg.REGISTERS["SUPPLY_OUT"]
        self.words[supply.addr] = int(supply.encode(supply.from_si(self.supply_v)))
        if self.supply_v < 4.75:
            self._status |= 1 << 0
        elif self.supply_v > 5.25:
            self._status |= 1 << 1

    def _finish_self_test(self) -> None:
        self._self_test_until = -1.0
        msc = reg.ADDR["MSC_CTRL"]
        self.words[msc] &= ~reg.MSC_SELF_TEST & 0xFFFF
        if self.self_test_fails:
            self._status |= reg.STATUS_SELF_TEST | (1 << 10)

    # -- SPI pins --------------------------------------------------------------------------
    def select(self) -> None:
        """CS falls: the MSB of the pending answer appears on DOUT."""
        self._selected = True
        self._shift_in = []
        self._shift_out = self._next_out
        self._spi_error = False

    def deselect(self) -> None:
        """CS rises; a frame shorter than 16 clocks is discarded."""
        self._selected = False
        self._shift_in = []

    def exchange(self, mosi: int, *, mode: int, speed_hz: float) -> int:
        """One byte on the bus; returns the byte clocked out on DOUT."""
        if not self._selected:
            return 0xFF
        if mode != 3 or speed_hz > reg.sclk_max_hz(self.words[reg.ADDR["SMPL_PRD"]]) * 1.0001:
            self._spi_error = True
        first = not self._shift_in
        out = (self._shift_out >> 8) if first else (self._shift_out & 0xFF)
        if self._spi_error:
            out = (out >> 1) | 0x80  # sampled on the wrong edge / too fast: shifted bits
        self._shift_in.append(mosi & 0xFF)
        if len(self._shift_in) == 2:
            word = (self._shift_in[0] << 8) | self._shift_in[1]
            self._shift_in = []
            if self._spi_error:
                self._status |= reg.STATUS_SPI_FAILURE
            else:
                self._frame(word)
            self._shift_out = self._next_out
        return out & 0xFF

    # -- frame semantics ---------------------------------------------------------------------
    def _frame(self, word: int) -> None:
        self.frames += 1
        self._update()
        addr = (word >> 8) & 0x3F
        if word & reg.WRITE_BIT:
            self._write_byte(addr, word & 0xFF)
            self._next_out = 0
            return
        base = addr & ~1
        value = self.words.get(base, 0)
        if base == reg.ADDR["STATUS"]:
            value = self._status
            self._status = 0
        elif reg.ADDR["SUPPLY_OUT"] <= base <= reg.ADDR["AUX_ADC"]:
            nd = (self._nd >> (base // 2)) & 1
            ea = 1 if self._status else 0
            value = (value & 0x3FFF) | (nd << 15) | (ea << 14)
            self._nd &= ~(1 << (base // 2))
            if nd and base == reg.ADDR["XGYRO_OUT"]:
                self._count_unread()
        self._next_out = value & 0xFFFF

    def _count_unread(self) -> None:
        """Sample ``self._index`` is being read: the ones since the last read were not."""
        last, self._last_read_index = self._last_read_index, self._index
        if last is not None and self._index - last > 1:
            self.samples_never_read += self._index - last - 1
            if self.on_never_read is not None:
                self.on_never_read(self.samples_never_read)

    def _write_byte(self, addr: int, data: int) -> None:
        if addr == 0x3F:
            self.undefined_writes += 1
            return
        base, upper = addr & ~1, addr & 1
        if base == reg.ADDR["COMMAND"]:
            self._command(data)
            return
        if base < reg.ADDR["XGYRO_OFF"] or base == reg.ADDR["STATUS"]:
            return  # read-only
        old = self.words[base]
        new = (old & 0x00FF) | (data << 8) if upper else (old & 0xFF00) | data
        self.words[base] = new
        if base in (reg.ADDR["SMPL_PRD"], reg.ADDR["SENS_AVG"]) and new != old:
            self._restart(0.0)  # new rate or range: the filter starts over, old data is stale
            self._nd = 0
        if base == reg.ADDR["MSC_CTRL"] and new & reg.MSC_SELF_TEST:
            self._self_test_until = self.clock.now() + SELF_TEST_S
            self._nd = 0

    def _command(self, bits: int) -> None:
        if bits & reg.CMD_SOFTWARE_RESET:
            self.stuck_data = False
            for name, v in VOLATILE_DEFAULTS.items():
                self.words[reg.ADDR[name]] = v
            self.words[reg.ADDR["MSC_CTRL"]] &= 0x00FF
            self._status = 0
            self._nd = 0
            self._restart(reg.STARTUP_S)
            return
        if bits & reg.CMD_FACTORY_RESTORE:
            for name in ("XGYRO_OFF", "YGYRO_OFF", "ZGYRO_OFF", "XACCL_OFF", "YACCL_OFF",
                         "ZACCL_OFF"):
                self.words[reg.ADDR[name]] = 0
        if bits & (reg.CMD_FLASH_UPDATE | reg.CMD_FACTORY_RESTORE | reg.CMD_AUTONULL
                   | reg.CMD_PRECISION_AUTONULL):
            self.words[reg.ADDR["ENDURANCE"]] = (self.words[reg.ADDR["ENDURANCE"]] + 1) % 32768
