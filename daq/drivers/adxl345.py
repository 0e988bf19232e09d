"""ADXL345 three-axis accelerometer on I2C (data sheet Rev. E).

Register table, pure conversions, and a driver: DEVID check, BW_RATE from the requested rate,
FULL_RES and range in DATA_FORMAT, the FIFO in stream mode with a watermark, measurement mode;
each poll reads INT_SOURCE (overrun) and FIFO_STATUS, then drains the FIFO with one 6-byte
little-endian read of DATAX0..DATAZ1 per entry (each such read pops one entry).
"""

from __future__ import annotations

import math

import numpy as np

from daq.clock import Clock, RealClock
from daq.drivers.common import StreamBuffer, sign_extend
from daq.errors import PermanentDeviceError, TransientDeviceError
from daq.transports.i2c import I2CBus

G0 = 9.80665
ADDRESSES = (0x53, 0x1D)  # ALT ADDRESS low / high
REG: dict[str, int] = {
    "DEVID": 0x00, "OFSX": 0x1E, "OFSY": 0x1F, "OFSZ": 0x20, "BW_RATE": 0x2C,
    "POWER_CTL": 0x2D, "INT_ENABLE": 0x2E, "INT_MAP": 0x2F, "INT_SOURCE": 0x30,
    "DATA_FORMAT": 0x31, "DATAX0": 0x32, "DATAX1": 0x33, "DATAY0": 0x34, "DATAY1": 0x35,
    "DATAZ0": 0x36, "DATAZ1": 0x37, "FIFO_CTL": 0x38, "FIFO_STATUS": 0x39,
}
DEVID = 0xE5
DATA_BYTES = 6
BW_RATE_RESET = 0x0A
BW_LOW_POWER = 1 << 4
POWER_MEASURE = 1 << 3
FORMAT_FULL_RES = 1 << 3
FORMAT_JUSTIFY = 1 << 2
RANGE_CODES_G: dict[int, int] = {2: 0b00, 4: 0b01, 8: 0b10, 16: 0b11}
FIFO_MODE_SHIFT = 6
FIFO_BYPASS, FIFO_FIFO, FIFO_STREAM, FIFO_TRIGGER = 0, 1, 2, 3
FIFO_DEPTH = 32
FIFO_AVAILABLE = 33  # 32 in the FIFO and one in the output registers
FIFO_ENTRIES_MASK = 0x3F
INT_DATA_READY = 1 << 7
INT_WATERMARK = 1 << 1
INT_OVERRUN = 1 << 0
LSB_PER_G = 256.0  # FULL_RES, any range (3.9 mg/LSB typical)
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
    """Rows of 6 little-endian bytes (X0 X1 Y0 Y1 Z0 Z1) to signed counts."""
    b = np.asarray(block, dtype=np.int64).reshape(-1, 3, 2)
    return sign_extend(b[..., 0] | (b[..., 1] << 8), 16)


def accel_m_s2(counts: np.ndarray) -> np.ndarray:
    """Full-resolution counts to m/s^2 (256 LSB per g)."""
    return np.asarray(counts, dtype=np.float64) * (G0 / LSB_PER_G)


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
        scale = G0 / LSB_PER_G
        self.imu = StreamBuffer(f"{prefix}/imu", ["accel_x", "accel_y", "accel_z"],
                                self.rate_hz, lambda raw: raw * scale)
        self.overruns = 0
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
        self.bus.write_u8(a, REG["FIFO_CTL"], FIFO_BYPASS << FIFO_MODE_SHIFT)  # flush
        fifo = (FIFO_STREAM << FIFO_MODE_SHIFT) | self.watermark
        self.bus.write_u8(a, REG["FIFO_CTL"], fifo)
        self.bus.write_u8(a, REG["POWER_CTL"], POWER_MEASURE)
        back = {name: self.bus.read_u8(a, REG[name])
                for name in ("BW_RATE", "DATA_FORMAT", "FIFO_CTL", "POWER_CTL")}
        expected = {"BW_RATE": self.code, "DATA_FORMAT": self.format, "FIFO_CTL": fifo,
                    "POWER_CTL": POWER_MEASURE}
        if back != expected:
            raise TransientDeviceError(f"{self.where}: configuration did not stick ({back})")
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
            "scale_accel_m_s2_per_lsb": f"{G0 / LSB_PER_G:.9g}",
        }

    def close(self) -> None:
        self.bus.close()

    def poll(self) -> int:
        """Drain the FIFO; the number of samples read."""
        a = self.address
        source = self.bus.read_u8(a, REG["INT_SOURCE"])
        entries = self.bus.read_u8(a, REG["FIFO_STATUS"]) & FIFO_ENTRIES_MASK
        now = self.clock.now()
        rows = [self.bus.read_block(a, REG["DATAX0"], DATA_BYTES) for _ in range(entries)]
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
            missed = max(0, produced - entries)
            self._reopened = False
        elif source & INT_OVERRUN:
            # Full FIFO: how many samples came since the last drain is known only from the
            # host clock; at least one was overwritten.
            self.overruns += 1
            produced = int(round((now - self._last_drain) * self.rate_hz))
            missed = max(1, produced - entries)
        self._last_drain = now
        if rows:
            self.imu.add_many(decode_data(np.asarray(rows)), missed=missed,
                              host_time=self.clock.wall())
        return len(rows)

    def take_blocks(self) -> list:
        return self.imu.take()

    @property
    def streams(self) -> list[StreamBuffer]:
        return [self.imu]
