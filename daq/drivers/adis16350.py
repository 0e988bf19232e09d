"""ADIS16350/ADIS16355 tri-axis gyroscope and accelerometer on SPI (datasheet Rev. B).

Register table, pure scaling functions, and a driver that talks through a serial-to-SPI
bridge. The part has no product-id register and no burst mode: it is identified by the answer
pattern of its registers (a plausible supply reading, unused bits clear), and every register
is read with pipelined 16-bit frames (the reply to frame n arrives in frame n+1).
"""

from __future__ import annotations

import math

import numpy as np

from imunoise.core.units import DEG, G0
from imunoise.daq.clock import Clock, RealClock
from imunoise.daq.drivers.common import PolledSampleClock, StreamBuffer
from imunoise.daq.errors import PermanentDeviceError, TransientDeviceError
from imunoise.daq.registers import Field, RegisterMap
from imunoise.daq.transports.buspirate import SPI_SPEEDS_HZ, BusPirateSPI, speed_index

OUTPUT_REGISTERS = ("SUPPLY_OUT", "XGYRO_OUT", "YGYRO_OUT", "ZGYRO_OUT", "XACCL_OUT",
                    "YACCL_OUT", "ZACCL_OUT", "XTEMP_OUT", "YTEMP_OUT", "ZTEMP_OUT", "AUX_ADC")
IMU_REGISTERS = ("XGYRO_OUT", "YGYRO_OUT", "ZGYRO_OUT", "XACCL_OUT", "YACCL_OUT", "ZACCL_OUT")
TEMP_REGISTERS = ("XTEMP_OUT", "YTEMP_OUT", "ZTEMP_OUT", "SUPPLY_OUT")

# Output register flags (bits 15 and 14).
FLAG_ND = 0x8000  # new data since the last read
FLAG_EA = 0x4000  # STATUS has an error or alarm
WRITE_BIT = 0x8000

# COMMAND bits (Table 15).
CMD_SOFTWARE_RESET = 0x80
CMD_PRECISION_AUTONULL = 0x10
CMD_FLASH_UPDATE = 0x08
CMD_DAC_LATCH = 0x04
CMD_FACTORY_RESTORE = 0x02
CMD_AUTONULL = 0x01

# MSC_CTRL bits (Table 28).
MSC_SELF_TEST = 1 << 10

# STATUS bits (Table 31), LSB first.
STATUS_BITS: dict[int, str] = {
    0: "supply below 4.75 V",
    1: "supply above 5.25 V",
    2: "control register update failed",
    3: "SPI communication failure",
    4: "sensor over-range",
    5: "self-test failed",
    8: "alarm 1 active",
    9: "alarm 2 active",
    10: "X gyro self-diagnostic error",
    11: "Y gyro self-diagnostic error",
    12: "Z gyro self-diagnostic error",
    13: "X accelerometer self-diagnostic error",
    14: "Y accelerometer self-diagnostic error",
    15: "Z accelerometer self-diagnostic error",
}
STATUS_OVER_RANGE = 1 << 4
STATUS_SPI_FAILURE = 1 << 3
STATUS_SELF_TEST = 1 << 5

# SMPL_PRD (Tables 16/17): Ts = TB * (NS + 1).
SMPL_TIME_BASE_S = {0: 1.0 / 1638.4, 1: 18.921e-3}
SMPL_PRD_DEFAULT = 0x01
SMPL_PRD_FAST_MAX = 0x09  # SMPL_PRD <= 0x09: fast mode, SCLK up to 2 MHz; else 300 kHz
SCLK_MAX_FAST_HZ = 2.0e6
SCLK_MAX_NORMAL_HZ = 300e3

# SENS/AVG (Tables 20/21): range code in [10:8], Bartlett taps 2^M in [2:0].
GYRO_RANGES_DPS: dict[int, int] = {300: 0b100, 150: 0b010, 75: 0b001}
GYRO_LSB_DPS: dict[int, float] = {300: 0.07326, 150: 0.03663, 75: 0.018315}
MIN_TAPS_EXPONENT: dict[int, int] = {300: 0, 150: 2, 75: 4}
MAX_TAPS_EXPONENT = 6
SENS_AVG_DEFAULT = 0x0402

ACCEL_LSB_G = 2.522e-3
TEMP_LSB_C = 0.1453
TEMP_OFFSET_C = 25.0
SUPPLY_LSB_V = 1.8315e-3
AUX_ADC_LSB_V = 0.6105e-3
SUPPLY_PLAUSIBLE_V = (4.5, 5.5)

# Datasheet Table 6 / Table 9: the register map, one field per register (data bits [13:0]
# or [11:0]; bits 15 and 14 of an output register are its ND and EA flags).
REGISTERS = RegisterMap([
    Field("ENDURANCE", 0x00),
    Field("SUPPLY_OUT", 0x02, 12, scale=SUPPLY_LSB_V, unit="V"),
    *(Field(f"{a}GYRO_OUT", 0x04 + 2 * k, 14, signed=True, scale=GYRO_LSB_DPS[300] * DEG,
            unit="rad/s") for k, a in enumerate("XYZ")),
    *(Field(f"{a}ACCL_OUT", 0x0A + 2 * k, 14, signed=True, scale=ACCEL_LSB_G * G0,
            unit="m/s^2") for k, a in enumerate("XYZ")),
    *(Field(f"{a}TEMP_OUT", 0x10 + 2 * k, 12, signed=True, scale=TEMP_LSB_C,
            offset=TEMP_OFFSET_C, unit="degC") for k, a in enumerate("XYZ")),
    Field("AUX_ADC", 0x16, 12, scale=AUX_ADC_LSB_V, unit="V"),
    *(Field(f"{a}GYRO_OFF", 0x1A + 2 * k, 13, signed=True, scale=GYRO_LSB_DPS[75] * DEG,
            unit="rad/s") for k, a in enumerate("XYZ")),
    *(Field(f"{a}ACCL_OFF", 0x20 + 2 * k, 12, signed=True, scale=ACCEL_LSB_G * G0,
            unit="m/s^2") for k, a in enumerate("XYZ")),
    Field("ALM_MAG1", 0x26), Field("ALM_MAG2", 0x28), Field("ALM_SMPL1", 0x2A),
    Field("ALM_SMPL2", 0x2C), Field("ALM_CTRL", 0x2E), Field("AUX_DAC", 0x30, 12),
    Field("GPIO_CTRL", 0x32), Field("MSC_CTRL", 0x34), Field("SMPL_PRD", 0x36),
    Field("SENS_AVG", 0x38), Field("SLP_CNT", 0x3A), Field("STATUS", 0x3C),
    Field("COMMAND", 0x3E),
])
ADDR = {name: f.addr for name, f in REGISTERS.items()}


def gyro_field(name: str, range_dps: int) -> Field:
    """Gyro output field ``name`` at the range SENS/AVG selects."""
    return REGISTERS[name].rescaled(GYRO_LSB_DPS[range_dps] * DEG)


STARTUP_S = 0.150
RESET_WAIT_S = 0.290
SELF_TEST_WAIT_S = 0.050


# -- pure conversions ----------------------------------------------------------------------
def sample_rate_hz(smpl_prd: int) -> float:
    """Output rate in Hz of a SMPL_PRD value."""
    tb = SMPL_TIME_BASE_S[(smpl_prd >> 7) & 1]
    return 1.0 / (tb * ((smpl_prd & 0x7F) + 1))


def supported_rates_hz() -> dict[int, float]:
    """All SMPL_PRD settings the datasheet allows (0x01 is the minimum) and their rates."""
    return {v: sample_rate_hz(v) for v in range(0x01, 0x100) if v != 0x80}


def smpl_prd_for_rate(rate_hz: float) -> int:
    """The SMPL_PRD value whose rate is closest (in ratio) to ``rate_hz``."""
    if not (0.4 <= rate_hz <= 820.0):
        raise ValueError(f"ADIS16350 rate {rate_hz:g} Hz out of range 0.413..819.2 Hz")
    rates = supported_rates_hz()
    return min(rates, key=lambda v: abs(math.log(rates[v] / rate_hz)))


def sclk_max_hz(smpl_prd: int) -> float:
    """Fastest SPI clock the datasheet allows at this SMPL_PRD (fast vs normal mode)."""
    fast = (smpl_prd & 0x80) == 0 and (smpl_prd & 0x7F) <= SMPL_PRD_FAST_MAX
    return SCLK_MAX_FAST_HZ if fast else SCLK_MAX_NORMAL_HZ


def sens_avg_value(range_dps: int, taps: int) -> int:
    """SENS/AVG register for a gyro range (deg/s) and a number of Bartlett taps (1..64)."""
    if range_dps not in GYRO_RANGES_DPS:
        raise ValueError(f"ADIS16350 gyro range {range_dps} deg/s: choose one of "
                         f"{sorted(GYRO_RANGES_DPS)}")
    m = int(round(math.log2(taps))) if taps >= 1 else -1
    if taps < 1 or 2 ** m != taps or m > MAX_TAPS_EXPONENT:
        raise ValueError(f"ADIS16350 filter taps {taps}: choose a power of two from 1 to 64")
    if m < MIN_TAPS_EXPONENT[range_dps]:
        raise ValueError(f"ADIS16350 range +-{range_dps} deg/s needs at least "
                         f"{2 ** MIN_TAPS_EXPONENT[range_dps]} filter taps")
    return (GYRO_RANGES_DPS[range_dps] << 8) | m


def decode_sens_avg(value: int) -> tuple[int, int]:
    """(range in deg/s, taps) from SENS/AVG; ValueError if the range code is not valid."""
    code = (value >> 8) & 0x07
    for rng, c in GYRO_RANGES_DPS.items():
        if c == code:
            return rng, 1 << (value & 0x07)
    raise ValueError(f"SENS/AVG 0x{value:04X}: no valid range code")


def decode_status(value: int) -> list[str]:
    """Names of the STATUS flags that are set."""
    return [text for bit, text in STATUS_BITS.items() if value & (1 << bit)]


def read_command(name: str) -> int:
    """DIN word that asks for register ``name`` (answered in the next frame)."""
    return ADDR[name] << 8


def write_commands(name: str, value: int, upper_first: bool = False) -> list[int]:
    """DIN words writing the 16-bit ``value`` to register ``name`` (one byte per frame)."""
    a = ADDR[name]
    lo = WRITE_BIT | (a << 8) | (value & 0xFF)
    hi = WRITE_BIT | ((a + 1) << 8) | ((value >> 8) & 0xFF)
    return [hi, lo] if upper_first else [lo, hi]


# -- driver --------------------------------------------------------------------------------
class Adis16350:
    """ADIS16350 behind a Bus Pirate: identify, configure, poll samples, self-test.

    Args:
        spi: the bridge (opened and closed by this driver).
        rate_hz: requested output rate; the nearest SMPL_PRD setting is used.
        range_dps: gyro range, 300, 150 or 75 deg/s.
        taps: Bartlett FIR taps (power of two, at least 4 at 150 deg/s and 16 at 75 deg/s).
        temp_period_s: how often the three temperatures and the supply are read.
        self_test: run the internal self-test when first opened (result in ``config``; a
            failure is recorded, not fatal, so a marginal part can still be characterised).
        clock: time source for pacing waits (shared with a simulator in tests).
    """

    name = "adis16350"
    model = "ADIS16350"
    stale_timeout_s = 0.5
    polls_data_ready = True  # no FIFO: polled on its sample phase (imunoise.daq.poll_schedule)

    def __init__(self, spi: BusPirateSPI, *, rate_hz: float = 102.4, range_dps: int = 300,
                 taps: int | None = None, temp_period_s: float = 1.0, self_test: bool = True,
                 clock: Clock | None = None) -> None:
        self.spi = spi
        self.smpl_prd = smpl_prd_for_rate(rate_hz)
        self.rate_hz = sample_rate_hz(self.smpl_prd)
        if taps is None:
            taps = max(4, 2 ** MIN_TAPS_EXPONENT.get(range_dps, 0))
        self.sens_avg = sens_avg_value(range_dps, taps)
        self.range_dps, self.taps = range_dps, taps
        self.clock = clock or RealClock()
        self.temp_every = max(1, int(round(temp_period_s * self.rate_hz)))
        self.poll_period_s = 1.0 / (self.rate_hz * 1.02)
        self.imu_fields = [gyro_field(n, range_dps) if "GYRO" in n else REGISTERS[n]
                           for n in IMU_REGISTERS]
        scale = np.array([f.scale for f in self.imu_fields])
        self.imu = StreamBuffer(f"/{self.name}/imu",
                                ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"],
                                self.rate_hz, lambda raw: raw * scale)
        self.temperature = StreamBuffer(
            f"/{self.name}/temperature", ["temp"], self.rate_hz / self.temp_every,
            lambda raw: REGISTERS["XTEMP_OUT"].to_si(raw[:, :3].mean(axis=1, keepdims=True)),
            raw_names=["temp_x", "temp_y", "temp_z", "supply"])
        self.status_seen: dict[str, int] = {}
        self.stale_reads = 0
        self.supply_v: float | None = None
        self.endurance: int | None = None
        self._last_fresh_host: float | None = None
        self.found_new_sample = False
        self._phase = PolledSampleClock(self.rate_hz)
        self._opened_at = 0.0
        self.run_self_test = self_test
        self.self_test_result = ""
        self.config: dict[str, str] = self._describe()

    # -- register access -------------------------------------------------------------------
    def read_registers(self, names: list[str] | tuple[str, ...]) -> dict[str, int]:
        """Raw 16-bit words of ``names`` with pipelined frames (N + 1 frames for N)."""
        words = [read_command(n) for n in names] + [read_command("ENDURANCE")]
        miso = self.spi.transfer_frames(words)
        return {n: int(miso[i + 1]) for i, n in enumerate(names)}

    def write_register(self, name: str, value: int, upper_first: bool = False) -> None:
        self.spi.transfer_frames(write_commands(name, value, upper_first))

    def command(self, bits: int) -> None:
        """Write the COMMAND register (one frame: only the lower byte is defined)."""
        self.spi.transfer_frames([WRITE_BIT | (ADDR["COMMAND"] << 8) | (bits & 0xFF)])

    # -- lifecycle -------------------------------------------------------------------------
    def open(self) -> None:
        """Connect, identify, configure rate and range, verify by reading back."""
        self.spi.open()
        self.spi.configure(SCLK_MAX_NORMAL_HZ * 0.9, mode=3)
        try:
            self.identify()
        except PermanentDeviceError:
            # Just powered up (first conversion after 150 ms): look once more.
            self.clock.sleep(STARTUP_S)
            self.identify()
        if self._last_fresh_host is not None:
            # Reopening after a fault: start the part from a clean state.
            self.reset()
        elif self.run_self_test:
            failed = self.self_test()
            self.self_test_result = "passed" if not failed else "failed: " + "; ".join(failed)
        self.write_register("SMPL_PRD", self.smpl_prd)
        # The datasheet asks for the range (upper byte) before the filter (lower byte).
        self.write_register("SENS_AVG", self.sens_avg, upper_first=True)
        back = self.read_registers(["SMPL_PRD", "SENS_AVG", "STATUS"])
        if back["SMPL_PRD"] != self.smpl_prd or back["SENS_AVG"] != self.sens_avg:
            raise TransientDeviceError(
                f"ADIS16350 on {self.spi.port}: configuration did not stick (SMPL_PRD "
                f"0x{back['SMPL_PRD']:04X}, SENS/AVG 0x{back['SENS_AVG']:04X})")
        self.spi.configure(min(sclk_max_hz(self.smpl_prd), 1.0e6), mode=3)
        # Discard whatever the output registers held from before the configuration.
        self.clock.sleep(2.0 / self.rate_hz)
        self.read_registers(list(IMU_REGISTERS))
        self._opened_at = self.clock.now()
        if self._last_fresh_host is not None:
            self._phase.reconnected()
        self.config = self._describe()

    def close(self) -> None:
        self.spi.close()

    def identify(self) -> dict[str, int]:
        """Check the answer pattern of an ADIS16350; PermanentDeviceError if it is not one."""
        regs = self.read_registers(["SUPPLY_OUT", "SMPL_PRD", "SENS_AVG", "SUPPLY_OUT",
                                    "ENDURANCE"])
        where = f"ADIS16350 on {self.spi.port}"
        words = [regs["SUPPLY_OUT"], regs["SMPL_PRD"], regs["SENS_AVG"]]
        if all(w == 0xFFFF for w in words) or all(w == 0 for w in words):
            raise PermanentDeviceError(f"{where}: no answer on SPI (MISO reads "
                                       f"0x{words[0]:04X}; check wiring and sensor power)")
        volts = float(REGISTERS["SUPPLY_OUT"].decode(regs["SUPPLY_OUT"]))
        lo, hi = SUPPLY_PLAUSIBLE_V
        if not (lo <= volts <= hi) or regs["SUPPLY_OUT"] & 0x3000:
            raise PermanentDeviceError(f"{where}: not an ADIS16350 (SUPPLY_OUT "
                                       f"0x{regs['SUPPLY_OUT']:04X} = {volts:.2f} V, expected "
                                       f"{lo}-{hi} V)")
        if regs["SMPL_PRD"] & 0xFF00 or regs["SENS_AVG"] & 0xF8F8:
            raise PermanentDeviceError(f"{where}: not an ADIS16350 (unused bits set: SMPL_PRD "
                                       f"0x{regs['SMPL_PRD']:04X}, SENS/AVG "
                                       f"0x{regs['SENS_AVG']:04X})")
        try:
            decode_sens_avg(regs["SENS_AVG"])
        except ValueError as exc:
            raise PermanentDeviceError(f"{where}: not an ADIS16350 ({exc})") from exc
        self.supply_v = volts
        self.endurance = regs["ENDURANCE"]
        return regs

    def reset(self) -> None:
        """Software reset; waits until the part answers again."""
        self.command(CMD_SOFTWARE_RESET)
        self.clock.sleep(RESET_WAIT_S)

    def self_test(self) -> list[str]:
        """Run the internal self-test; the failing flags (empty list: passed)."""
        self.spi.transfer_frames([WRITE_BIT | ((ADDR["MSC_CTRL"] + 1) << 8)
                                  | (MSC_SELF_TEST >> 8)])
        deadline = self.clock.now() + RESET_WAIT_S
        self.clock.sleep(SELF_TEST_WAIT_S)
        while self.read_registers(["MSC_CTRL"])["MSC_CTRL"] & MSC_SELF_TEST:
            if self.clock.now() > deadline:
                raise TransientDeviceError(f"ADIS16350 on {self.spi.port}: self-test did not "
                                           "finish")
            self.clock.sleep(0.01)
        status = self.read_registers(["STATUS"])["STATUS"]
        return decode_status(status)

    def read_status(self) -> list[str]:
        """Read (and so clear) STATUS; the flags that were set."""
        return decode_status(self.read_registers(["STATUS"])["STATUS"])

    def _describe(self) -> dict[str, str]:
        """Configuration for the recording's metadata (device answers filled in by open)."""
        gyro_lsb = gyro_field("XGYRO_OUT", self.range_dps).scale
        sclk = min(sclk_max_hz(self.smpl_prd), 1.0e6)
        return {
            "device": self.name, "model": self.model,
            "transport": f"Bus Pirate binary SPI on {self.spi.port}, mode 3, "
                         f"{(self.spi.speed_hz or SPI_SPEEDS_HZ[speed_index(sclk)]) / 1e3:g} kHz",
            "rate_hz": f"{self.rate_hz:.6g}", "smpl_prd": f"0x{self.smpl_prd:04X}",
            "gyro_range_dps": str(self.range_dps), "filter_taps": str(self.taps),
            "sens_avg": f"0x{self.sens_avg:04X}",
            "scale_gyro_rad_s_per_lsb": f"{gyro_lsb:.9g}",
            "scale_accel_m_s2_per_lsb": f"{REGISTERS['XACCL_OUT'].scale:.9g}",
            "scale_temp_degc_per_lsb": f"{TEMP_LSB_C}", "temp_offset_degc": f"{TEMP_OFFSET_C}",
            "supply_v": f"{self.supply_v:.3f}" if self.supply_v is not None else "",
            "flash_endurance": str(self.endurance),
            "temperature_rate_hz": f"{self.rate_hz / self.temp_every:.6g}",
            "self_test": self.self_test_result,
        }

    # -- sampling --------------------------------------------------------------------------
    def poll(self) -> int:
        """Read one sample if a new one is there; the number of fresh samples (0 or 1)."""
        with_temp = self.imu.next_index % self.temp_every == 0
        names = IMU_REGISTERS + (TEMP_REGISTERS if with_temp else ())
        words = [read_command(n) for n in names] + [read_command("ENDURANCE")]
        # The registers are read a bridge latency after the request goes out, while the reply
        # may reach a busy host much later: the request time places the sample best.
        now = self.clock.now()
        miso = self.spi.transfer_frames(words)[1:].astype(np.int64)
        self.found_new_sample = bool(miso[0] & FLAG_ND)
        if not self.found_new_sample:
            self.stale_reads += 1
            self._phase.stale(now, self.imu.next_index - 1)
            since = max(self._last_fresh_host or self._opened_at, self._opened_at)
            if now - since > max(self.stale_timeout_s, 20 / self.rate_hz):
                raise TransientDeviceError(
                    f"ADIS16350 on {self.spi.port}: no new data for {now - since:.2f} s "
                    "(data-ready stuck)")
            return 0
        if np.any(miso & FLAG_EA):
            self._note_status(self.read_registers(["STATUS"])["STATUS"])
        missed = 0
        if self._last_fresh_host is None:
            self.imu.anchor(self.clock.wall())
            self.temperature.anchor(self.clock.wall())
            self._phase.fresh(now, 0)
        else:
            missed = self._phase.fresh(now, self.imu.next_index)
        self._last_fresh_host = now
        counts = [int(f.counts(w)) for f, w in zip(self.imu_fields, miso[:6], strict=True)]
        self.imu.add(counts, missed=missed, host_time=self.clock.wall())
        if with_temp:
            row = [int(REGISTERS[n].counts(w)) for n, w in zip(TEMP_REGISTERS, miso[6:10],
                                                              strict=True)]
            self.temperature_add(row, self.imu.next_index - 1)
        return 1

    def temperature_add(self, row: list[int], imu_index: int) -> None:
        """Temperature sample taken with IMU sample ``imu_index``."""
        target = imu_index // self.temp_every
        if target >= self.temperature.next_index:
            self.temperature.add(row, missed=target - self.temperature.next_index)

    def _note_status(self, status: int) -> None:
        for flag in decode_status(status):
            self.status_seen[flag] = self.status_seen.get(flag, 0) + 1

    def take_blocks(self) -> list:
        return self.imu.take() + self.temperature.take()

    @property
    def streams(self) -> list[StreamBuffer]:
        return [self.imu, self.temperature]
