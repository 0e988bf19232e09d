"""ITG-3200 tri-axis gyroscope on I2C (product specification rev. 1.4).

Register table, pure conversions, and a driver that identifies the part, resets it, selects
the X-gyro PLL as clock, sets FS_SEL = 3, DLPF and SMPLRT_DIV from the requested rate, and
polls INT_STATUS for data-ready before one 8-byte big-endian read of temperature and x, y, z.
"""

from __future__ import annotations

import numpy as np

from imunoise.core.units import DEG
from imunoise.daq.clock import Clock, RealClock
from imunoise.daq.drivers.common import PolledSampleClock, StreamBuffer
from imunoise.daq.errors import PermanentDeviceError, TransientDeviceError
from imunoise.daq.registers import Field, RegisterMap
from imunoise.daq.transports.i2c import I2CBus

ADDRESSES = (0x68, 0x69)  # AD0 low / high
WHO_AM_I_ID = 0x34  # bits [6:1]
LSB_PER_DPS = 14.375  # FS_SEL = 3
TEMP_LSB_PER_C = 280.0
TEMP_REF_C = 35.0
TEMP_REF_LSB = -13200.0

# Product specification section 8: register map. Data registers are 16-bit big-endian.
REGISTERS = RegisterMap([
    Field("WHO_AM_I", 0x00, bits=6, shift=1, nbytes=1),
    Field("SMPLRT_DIV", 0x15, bits=8, nbytes=1),
    Field("DLPF_FS", 0x16, bits=8, nbytes=1),
    Field("DLPF_CFG", 0x16, bits=3, nbytes=1),
    Field("FS_SEL", 0x16, bits=2, shift=3, nbytes=1),
    Field("INT_CFG", 0x17, bits=8, nbytes=1),
    Field("INT_STATUS", 0x1A, bits=8, nbytes=1),
    Field("TEMP_OUT", 0x1B, signed=True, scale=1.0 / TEMP_LSB_PER_C,
          offset=TEMP_REF_C - TEMP_REF_LSB / TEMP_LSB_PER_C, unit="degC"),
    Field("GYRO_XOUT", 0x1D, signed=True, scale=DEG / LSB_PER_DPS, unit="rad/s"),
    Field("GYRO_YOUT", 0x1F, signed=True, scale=DEG / LSB_PER_DPS, unit="rad/s"),
    Field("GYRO_ZOUT", 0x21, signed=True, scale=DEG / LSB_PER_DPS, unit="rad/s"),
    Field("PWR_MGM", 0x3E, bits=8, nbytes=1),
    Field("CLK_SEL", 0x3E, bits=3, nbytes=1),
])
REG: dict[str, int] = {name: f.addr for name, f in REGISTERS.items()}
DATA_FIELDS = ("TEMP_OUT", "GYRO_XOUT", "GYRO_YOUT", "GYRO_ZOUT")  # one burst, in this order
GYRO_FIELDS = DATA_FIELDS[1:]
DATA_BYTES = sum(REGISTERS[n].nbytes for n in DATA_FIELDS)

FS_SEL_2000DPS = 3
# DLPF_CFG -> (low-pass bandwidth Hz, internal sample rate Hz); 7 is reserved.
DLPF_CFG: dict[int, tuple[float, float]] = {
    0: (256.0, 8000.0), 1: (188.0, 1000.0), 2: (98.0, 1000.0), 3: (42.0, 1000.0),
    4: (20.0, 1000.0), 5: (10.0, 1000.0), 6: (5.0, 1000.0),
}

# INT_CFG bits.
INT_CFG_LATCH = 1 << 5
INT_CFG_ANYRD_2CLEAR = 1 << 4
INT_CFG_ITG_RDY_EN = 1 << 2
INT_CFG_RAW_RDY_EN = 1 << 0
# INT_STATUS bits.
INT_ITG_RDY = 1 << 2
INT_RAW_DATA_RDY = 1 << 0
# PWR_MGM bits and clock sources (CLK_SEL).
PWR_H_RESET = 1 << 7
PWR_SLEEP = 1 << 6
CLK_INTERNAL, CLK_PLL_X, CLK_PLL_Y, CLK_PLL_Z = 0, 1, 2, 3

STARTUP_S = 0.020
RESET_WAIT_S = 0.0015
PLL_TIMEOUT_S = 0.050
ZRO_SETTLE_S = 0.050
FROZEN_REPEATS = 200  # identical samples in a row that mean "data-ready stuck high"


def is_itg3200_id(who_am_i: int) -> bool:
    return int(REGISTERS["WHO_AM_I"].counts(who_am_i)) == WHO_AM_I_ID


def rate_settings(rate_hz: float) -> tuple[int, int, float]:
    """(DLPF_CFG, SMPLRT_DIV, actual rate in Hz) for a requested rate.

    Above 1 kHz the 8 kHz internal rate is used (256 Hz filter); otherwise 1 kHz with the
    widest filter whose bandwidth stays below half the output rate (anti-aliasing).
    """
    if not (1000.0 / 256 * 0.99 <= rate_hz <= 8000.0 * 1.001):
        raise ValueError(f"ITG-3200 rate {rate_hz:g} Hz out of range 3.9..8000 Hz")
    if rate_hz > 1000.0:
        cfg = 0
    else:
        fitting = [c for c, (bw, fi) in DLPF_CFG.items() if fi == 1000.0 and bw <= rate_hz / 2]
        cfg = min(fitting) if fitting else 6
    f_int = DLPF_CFG[cfg][1]
    div = int(np.clip(round(f_int / rate_hz) - 1, 0, 255))
    return cfg, div, f_int / (div + 1)


def decode_data(block: np.ndarray) -> np.ndarray:
    """Rows of the 8-byte data burst to signed counts (temp, x, y, z)."""
    return REGISTERS.block_counts(DATA_FIELDS, block)


def dlpf_fs_value(dlpf_cfg: int) -> int:
    """DLPF_FS for FS_SEL = 3 (the only specified range) and a low-pass setting."""
    return int(REGISTERS["FS_SEL"].encode(FS_SEL_2000DPS,
                                          REGISTERS["DLPF_CFG"].encode(dlpf_cfg)))


class Itg3200:
    """ITG-3200 on an :class:`I2CBus`, polled for data-ready at a little above its rate.

    Args:
        bus: the I2C bus (shared with other chips on a Razor board).
        rate_hz: requested output rate (nearest achievable is used; see ``config``).
        address: 0x68 (AD0 low) or 0x69.
        prefix: stream name prefix (``/itg3200`` or ``/razor/itg3200``).
        temp_period_s: spacing of the temperature stream samples.
    """

    name = "itg3200"
    model = "ITG-3200"
    stale_timeout_s = 0.5
    polls_data_ready = True  # no FIFO: polled on its sample phase (imunoise.daq.poll_schedule)

    def __init__(self, bus: I2CBus, *, rate_hz: float = 100.0, address: int = 0x68,
                 prefix: str = "/itg3200", temp_period_s: float = 1.0,
                 clock: Clock | None = None) -> None:
        self.bus = bus
        self.address = address
        self.dlpf_cfg, self.div, self.rate_hz = rate_settings(rate_hz)
        self.clock = clock or RealClock()
        self.poll_period_s = 1.0 / (self.rate_hz * 1.02)
        self.temp_every = max(1, int(round(temp_period_s * self.rate_hz)))
        scale = np.array([REGISTERS[n].scale for n in GYRO_FIELDS])
        self.imu = StreamBuffer(f"{prefix}/imu", ["gyro_x", "gyro_y", "gyro_z"], self.rate_hz,
                                lambda raw: raw * scale)
        self.temperature = StreamBuffer(f"{prefix}/temperature", ["temp"],
                                        self.rate_hz / self.temp_every,
                                        REGISTERS["TEMP_OUT"].to_si)
        self.stale_reads = 0
        self.frozen_reads = 0
        self._last_row: list[int] | None = None
        self._same_rows = 0
        self._last_fresh: float | None = None
        self.found_new_sample = False
        self._opened_at = 0.0
        self._phase = PolledSampleClock(self.rate_hz, reads_latch_at_once=True)
        self.config: dict[str, str] = self._describe(None)

    @property
    def where(self) -> str:
        return f"ITG-3200 at 0x{self.address:02X} on {self.bus.name}"

    def open(self) -> None:
        self.bus.open()
        who = self.bus.read_u8(self.address, REG["WHO_AM_I"])
        if not is_itg3200_id(who):
            raise PermanentDeviceError(f"{self.where}: WHO_AM_I reads 0x{who:02X}, expected "
                                       "0x68 or 0x69 (bits 6..1 = 0x34): not an ITG-3200")
        self.bus.write_u8(self.address, REG["PWR_MGM"], PWR_H_RESET)
        self.clock.sleep(RESET_WAIT_S)
        self.bus.write_u8(self.address, REG["PWR_MGM"], CLK_PLL_X)
        self.bus.write_u8(self.address, REG["INT_CFG"],
                          INT_CFG_LATCH | INT_CFG_ITG_RDY_EN | INT_CFG_RAW_RDY_EN)
        deadline = self.clock.now() + PLL_TIMEOUT_S
        while not self.bus.read_u8(self.address, REG["INT_STATUS"]) & INT_ITG_RDY:
            if self.clock.now() > deadline:
                raise TransientDeviceError(f"{self.where}: PLL not ready after "
                                           f"{PLL_TIMEOUT_S * 1e3:g} ms")
            self.clock.sleep(0.001)
        dlpf_fs = dlpf_fs_value(self.dlpf_cfg)
        self.bus.write_u8(self.address, REG["DLPF_FS"], dlpf_fs)
        self.bus.write_u8(self.address, REG["SMPLRT_DIV"], self.div)
        back = self.bus.read_block(self.address, REG["SMPLRT_DIV"], 2)
        if back != [self.div, dlpf_fs]:
            raise TransientDeviceError(f"{self.where}: configuration did not stick "
                                       f"(SMPLRT_DIV, DLPF_FS = {back})")
        self.clock.sleep(ZRO_SETTLE_S)
        self.bus.read_u8(self.address, REG["INT_STATUS"])  # drop data from before settling
        self._opened_at = self.clock.now()
        if self._last_fresh is not None:
            self._phase.reconnected()
        self.config = self._describe(who)

    def _describe(self, who: int | None) -> dict[str, str]:
        """Configuration for the recording's metadata (WHO_AM_I filled in by open)."""
        return {
            "device": self.name, "model": self.model, "transport": self.bus.name,
            "i2c_address": f"0x{self.address:02X}",
            "who_am_i": f"0x{who:02X}" if who is not None else "",
            "rate_hz": f"{self.rate_hz:.6g}", "smplrt_div": str(self.div),
            "dlpf_cfg": str(self.dlpf_cfg),
            "dlpf_bandwidth_hz": f"{DLPF_CFG[self.dlpf_cfg][0]:g}",
            "internal_rate_hz": f"{DLPF_CFG[self.dlpf_cfg][1]:g}",
            "gyro_range_dps": "2000", "fs_sel": "3", "clock_source": "PLL, X gyro reference",
            "scale_gyro_rad_s_per_lsb": f"{REGISTERS['GYRO_XOUT'].scale:.9g}",
            "temp_formula": "35 + (raw + 13200) / 280 degC",
            "temperature_rate_hz": f"{self.rate_hz / self.temp_every:.6g}",
        }

    def close(self) -> None:
        self.bus.close()

    def poll(self) -> int:
        # Times are taken before each read: "nothing new" holds from before the status read,
        # and the data are the newest sample at the data read, however late that comes.
        now = self.clock.now()
        status = self.bus.read_u8(self.address, REG["INT_STATUS"])
        self.found_new_sample = bool(status & INT_RAW_DATA_RDY)
        if not self.found_new_sample:
            self.stale_reads += 1
            self._phase.stale(now, self.imu.next_index - 1)
            since = max(self._last_fresh or self._opened_at, self._opened_at)
            if now - since > max(self.stale_timeout_s, 20 / self.rate_hz):
                raise TransientDeviceError(f"{self.where}: no data-ready for "
                                           f"{now - since:.2f} s (stuck)")
            return 0
        seen = now  # when the status read found the new sample
        now = self.clock.now()
        row = decode_data(self.bus.read_block(self.address, REG["TEMP_OUT"], DATA_BYTES))[0]
        self._check_frozen(row.tolist())
        missed = 0
        if self._last_fresh is None:
            self.imu.anchor(self.clock.wall())
            self.temperature.anchor(self.clock.wall())
            self._phase.fresh(now, 0)
        else:
            missed = self._phase.fresh(now, self.imu.next_index, seen_at=seen)
        self._last_fresh = now
        index = self.imu.next_index + missed
        self.imu.add(row[1:].tolist(), missed=missed, host_time=self.clock.wall())
        if index % self.temp_every == 0 or self.temperature.next_index == 0:
            target = index // self.temp_every
            if target >= self.temperature.next_index:
                self.temperature.add([int(row[0])], missed=target - self.temperature.next_index)
        return 1

    def _check_frozen(self, row: list[int]) -> None:
        """Identical temperature and x, y, z many times running: data-ready stuck high."""
        if row == self._last_row:
            self._same_rows += 1
            if self._same_rows >= FROZEN_REPEATS:
                self.frozen_reads += 1
                self._same_rows = 0
                raise TransientDeviceError(f"{self.where}: data frozen (same sample "
                                           f"{FROZEN_REPEATS} times "
                                           "with data-ready set)")
        else:
            self._same_rows = 0
        self._last_row = row

    def take_blocks(self) -> list:
        return self.imu.take() + self.temperature.take()

    @property
    def streams(self) -> list[StreamBuffer]:
        return [self.imu, self.temperature]
