"""ADXL345 three-axis accelerometer on I2C (data sheet Rev. E).

Register table, pure conversions, and a driver: DEVID check, BW_RATE from the requested rate,
FULL_RES and range in DATA_FORMAT, the FIFO in stream mode with a watermark, measurement mode;
each poll reads INT_SOURCE (overrun) and FIFO_STATUS, then drains the FIFO with one 6-byte
little-endian read of DATAX..DATAZ per entry (each such read pops one entry).
"""

from __future__ import annotations

import math
from dataclasses import replace
from functools import lru_cache

import numpy as np

from imunoise.core.units import G0
from imunoise.daq.clock import Clock, RealClock
from imunoise.daq.drivers.common import StreamBuffer
from imunoise.daq.errors import PermanentDeviceError, TransientDeviceError
from imunoise.daq.registers import Field, RegisterMap
from imunoise.daq.transports.i2c import I2CBus

ADDRESSES = (0x53, 0x1D)  # ALT ADDRESS low / high
LSB_PER_G = 256.0  # FULL_RES, any range (3.9 mg/LSB typical)
OFFSET_LSB_G = 15.6e-3

# Data sheet Table 19: register map. Data registers are 16-bit little-endian.
REGISTERS = RegisterMap([
    Field("DEVID", 0x00, bits=8, nbytes=1),
    *(Field(f"OFS{a}", 0x1E + k, bits=8, signed=True, scale=OFFSET_LSB_G * G0, unit="m/s^2",
            nbytes=1) for k, a in enumerate("XYZ")),
    Field("BW_RATE", 0x2C, bits=8, nbytes=1),
    Field("RATE", 0x2C, bits=4, nbytes=1),
    Field("POWER_CTL", 0x2D, bits=8, nbytes=1),
    Field("INT_ENABLE", 0x2E, bits=8, nbytes=1),
    Field("INT_MAP", 0x2F, bits=8, nbytes=1),
    Field("INT_SOURCE", 0x30, bits=8, nbytes=1),
    Field("DATA_FORMAT", 0x31, bits=8, nbytes=1),
    Field("RANGE", 0x31, bits=2, nbytes=1),
    *(Field(f"DATA{a}", 0x32 + 2 * k, signed=True, scale=G0 / LSB_PER_G, unit="m/s^2",
            big_endian=False) for k, a in enumerate("XYZ")),
    Field("FIFO_CTL", 0x38, bits=8, nbytes=1),
    Field("FIFO_MODE", 0x38, bits=2, shift=6, nbytes=1),
    Field("FIFO_SAMPLES", 0x38, bits=5, nbytes=1),
    Field("FIFO_STATUS", 0x39, bits=8, nbytes=1),
    Field("FIFO_ENTRIES", 0x39, bits=6, nbytes=1),
])
REG: dict[str, int] = {name: f.addr for name, f in REGISTERS.items()}
DATA_FIELDS = ("DATAX", "DATAY", "DATAZ")  # one burst, in this order
DEVID = 0xE5
DATA_BYTES = sum(REGISTERS[n].nbytes for n in DATA_FIELDS)
BW_RATE_RESET = 0x0A
BW_LOW_POWER = 1 << 4
POWER_MEASURE = 1 << 3
FORMAT_FULL_RES = 1 << 3
FORMAT_JUSTIFY = 1 << 2
RANGE_CODES_G: dict[int, int] = {2: 0b00, 4: 0b01, 8: 0b10, 16: 0b11}
FIFO_BYPASS, FIFO_FIFO, FIFO_STREAM, FIFO_TRIGGER = 0, 1, 2, 3
FIFO_DEPTH = 32
FIFO_AVAILABLE = 33  # 32 in the FIFO and one in the output registers
CONTINUE_MARGIN = 4
"""Entries kept free when a drain goes on without reading the FIFO's status first."""
RATE_TOLERANCE = 0.1
"""Output data rate above nominal assumed when bounding how full the FIFO can be."""
INT_DATA_READY = 1 << 7
INT_WATERMARK = 1 << 1
INT_OVERRUN = 1 << 0
MAX_RATE_CODE = 0x0F
TURN_ON_S = 0.0011  # plus one output period


def odr_hz(code: int) -> float:
    """Output data rate of a BW_RATE rate code: 3200 Hz / 2^(15 - code)."""
    return 3200.0 / 2.0 ** (MAX_RATE_CODE - (code & 0x0F))


def rate_code(rate: float) -> int:
    """The BW_RATE code whose rate is nearest (in ratio) to ``rate`` Hz."""
    if not (0.09 <= rate <= 3200.0 * 1.001):
        raise ValueError(f"ADXL345 rate {rate:g} Hz out of range 0.1..3200 Hz")
    return int(np.clip(round(MAX_RATE_CODE - math.log2(3200.0 / rate)), 0, MAX_RATE_CODE))


def data_format(range_g: int) -> int:
    """DATA_FORMAT for full resolution, right-justified, at +-``range_g``."""
    if range_g not in RANGE_CODES_G:
        raise ValueError(f"ADXL345 range +-{range_g} g: choose one of {sorted(RANGE_CODES_G)}")
    return FORMAT_FULL_RES | RANGE_CODES_G[range_g]


def full_res_bits(range_g: int) -> int:
    """Output bits in full-resolution mode: 10 at +-2 g up to 13 at +-16 g."""
    return 10 + RANGE_CODES_G[range_g]


def decode_data(block: np.ndarray) -> np.ndarray:
    """Rows of the 6-byte data burst (X0 X1 Y0 Y1 Z0 Z1) to signed counts."""
    return REGISTERS.block_counts(DATA_FIELDS, block)


@lru_cache(maxsize=256)  # a simulator asks for every sample it makes
def data_field(name: str, fmt: int) -> Field:
    """The data field ``name`` as DATA_FORMAT ``fmt`` sets it: 10 bits at 3.9 mg, or at full
    resolution 10 to 13 bits at 3.9 mg; otherwise the LSB doubles with each range step."""
    rng = int(REGISTERS["RANGE"].counts(fmt))
    f = REGISTERS[name]
    if fmt & FORMAT_FULL_RES:
        return replace(f, bits=10 + rng)
    return replace(f, bits=10, scale=f.scale * 2**rng)


class Adxl345:
    """ADXL345 on an :class:`I2CBus`, drained from its FIFO in stream mode.

    Args:
        bus: the I2C bus.
        rate_hz: requested output data rate (nearest code is used; see ``config``).
        range_g: 2, 4, 8 or 16 (full resolution: the LSB stays 3.9 mg).
        address: 0x53 (ALT ADDRESS low) or 0x1D.
        watermark: FIFO watermark in entries (1..31).
        prefix: stream name prefix.
    """

    name = "adxl345"
    model = "ADXL345"

    def __init__(self, bus: I2CBus, *, rate_hz: float = 100.0, range_g: int = 16,
                 address: int = 0x53, watermark: int = 16, prefix: str = "/adxl345",
                 clock: Clock | None = None) -> None:
        self.bus = bus
        self.address = address
        self.code = rate_code(rate_hz)
        self.rate_hz = odr_hz(self.code)
        self.range_g = range_g
        self.format = data_format(range_g)
        if not 1 <= watermark < FIFO_DEPTH:
            raise ValueError(f"ADXL345 FIFO watermark {watermark}: must be 1..31")
        self.watermark = watermark
        self.clock = clock or RealClock()
        # Drain when the FIFO is about half full, at least ten times a second.
        self.poll_period_s = min(0.1, watermark / self.rate_hz)
        scale = np.array([REGISTERS[n].scale for n in DATA_FIELDS])
        self.imu = StreamBuffer(f"{prefix}/imu", ["accel_x", "accel_y", "accel_z"],
                                self.rate_hz, lambda raw: raw * scale)
        self.overruns = 0
        self.fifo_left = 0  # entries a drain cut short left in the FIFO
        self._status_at = -math.inf  # when the FIFO's count was last known (clock, s)
        self._last_drain: float | None = None
        self._reopened = False
        self.config: dict[str, str] = self._describe(None)

    @property
    def where(self) -> str:
        return f"ADXL345 at 0x{self.address:02X} on {self.bus.name}"

    def open(self) -> None:
        self.bus.open()
        devid = self.bus.read_u8(self.address, REG["DEVID"])
        if devid != DEVID:
            raise PermanentDeviceError(f"{self.where}: DEVID reads 0x{devid:02X}, expected "
                                       f"0x{DEVID:02X}: not an ADXL345")
        a = self.address
        self.bus.write_u8(a, REG["POWER_CTL"], 0)  # standby while configuring
        self.bus.write_u8(a, REG["BW_RATE"], self.code)
        self.bus.write_u8(a, REG["DATA_FORMAT"], self.format)
        self.bus.write_u8(a, REG["INT_ENABLE"], 0)
        mode, samples = REGISTERS["FIFO_MODE"], REGISTERS["FIFO_SAMPLES"]
        self.bus.write_u8(a, REG["FIFO_CTL"], int(mode.encode(FIFO_BYPASS)))  # flush
        fifo = int(mode.encode(FIFO_STREAM, samples.encode(self.watermark)))
        self.bus.write_u8(a, REG["FIFO_CTL"], fifo)
        self.bus.write_u8(a, REG["POWER_CTL"], POWER_MEASURE)
        back = {name: self.bus.read_u8(a, REG[name])
                for name in ("BW_RATE", "DATA_FORMAT", "FIFO_CTL", "POWER_CTL")}
        expected = {"BW_RATE": self.code, "DATA_FORMAT": self.format, "FIFO_CTL": fifo,
                    "POWER_CTL": POWER_MEASURE}
        if back != expected:
            raise TransientDeviceError(f"{self.where}: configuration did not stick ({back})")
        self._status_at = self.clock.now()  # flushed: none in the FIFO (fifo_left adds more)
        self.clock.sleep(TURN_ON_S + 1.0 / self.rate_hz)
        # Reopened after a fault: the FIFO was flushed, so the first drain has to count the
        # samples made since the last good one from the host clock.
        self._reopened = self._last_drain is not None
        self.config = self._describe(devid)
    def _describe(self, devid: int | None) -> dict[str, str]:
        """Configuration for the recording's metadata (DEVID filled in by open)."""
        return {
            "device": self.name, "model": self.model, "transport": self.bus.name,
            "i2c_address": f"0x{self.address:02X}",
            "devid": f"0x{devid:02X}" if devid is not None else "",
            "rate_hz": f"{self.rate_hz:.6g}", "bw_rate": f"0x{self.code:02X}",
            "bandwidth_hz": f"{self.rate_hz / 2:.6g}", "range_g": str(self.range_g),
            "data_format": f"0x{self.format:02X}", "full_res": "1",
            "resolution_bits": str(full_res_bits(self.range_g)),
            "fifo": f"stream, watermark {self.watermark}",
            "scale_accel_m_s2_per_lsb": f"{REGISTERS['DATAX'].scale:.9g}",
        }

    def close(self) -> None:
        self.bus.close()

    def poll(self, deadline: float | None = None) -> int:
        """Drain the FIFO; the number of samples read.

        With ``deadline`` (on ``clock``), stop reading entries once it has passed (at least
        one is read); :attr:`fifo_left` then says how many stayed in the FIFO. The drain that
        follows such a cut-short one reads those entries without the two status reads first,
        while the FIFO cannot have filled since the last status read (:meth:`_can_continue`):
        on a shared bus (the Razor's) the status reads took most of the time a drain is given
        between two gyro samples, so a backlog went down by about one entry per drain.
        """
        a = self.address
        now = self.clock.now()
        if self._can_continue(now):
            source, entries = 0, self.fifo_left  # all still there: nothing overwritten
        else:
            source = self.bus.read_u8(a, REG["INT_SOURCE"])
            entries = int(REGISTERS["FIFO_ENTRIES"].counts(
                self.bus.read_u8(a, REG["FIFO_STATUS"])))
            now = self.clock.now()
            self._status_at = now
        rows = []
        for _ in range(entries):
            rows.append(self.bus.read_block(a, REG["DATAX"], DATA_BYTES))
            if deadline is not None and self.clock.now() >= deadline:
                break
        left_before, self.fifo_left = self.fifo_left, entries - len(rows)
        missed = 0
        if self._last_drain is None:
            if not rows:
                return 0
            # The newest entry is about as old as this read.
            self.imu.anchor(self.clock.wall() - (entries - 1) / self.rate_hz)
        elif self._reopened:
            if not rows:
                return 0
            produced = int(round((now - self._last_drain) * self.rate_hz))
            missed = max(0, produced + left_before - entries)
            self._reopened = False
        elif source & INT_OVERRUN:
            # Full FIFO: how many samples came since the last drain is known only from the
            # host clock; at least one was overwritten.
            self.overruns += 1
            produced = int(round((now - self._last_drain) * self.rate_hz))
            missed = max(1, produced + left_before - entries)
        self._last_drain = now
        if rows:
            self.imu.add_many(decode_data(np.asarray(rows)), missed=missed,
                              host_time=self.clock.wall())
        return len(rows)

    def entries_at_most(self, now: float) -> float:
        """An upper bound of the entries in the FIFO at ``now`` (clock, s): those known to be
        left at the last status read (or at the start of measurement), less those read since,
        and as many as the chip makes from then on at :data:`RATE_TOLERANCE` above its
        nominal rate."""
        return self.fifo_left + (now - self._status_at) * self.rate_hz * (1.0 + RATE_TOLERANCE)

    def _can_continue(self, now: float) -> bool:
        """Whether the entries a cut-short drain left can be read without the status reads:
        at most :data:`FIFO_DEPTH` - :data:`CONTINUE_MARGIN` entries can be in the FIFO now, so
        none was overwritten."""
        if not self.fifo_left or self._last_drain is None or self._reopened:
            return False
        return self.entries_at_most(now) <= FIFO_DEPTH - CONTINUE_MARGIN

    def take_blocks(self) -> list:
        return self.imu.take()

    @property
    def streams(self) -> list[StreamBuffer]:
        return [self.imu]
