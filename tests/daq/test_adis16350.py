"""ADIS16350: scaling against datasheet examples; the driver against its register-level model
behind the emulated Bus Pirate, through the real pyserial, at many rates and every range."""

from __future__ import annotations

import math

import numpy as np
import pytest

from imunoise.core.units import DEG, G0
from imunoise.daq.clock import VirtualClock
from imunoise.daq.devices import open_device
from imunoise.daq.drivers import adis16350 as adis
from imunoise.daq.errors import PermanentDeviceError
from imunoise.daq.sim.adis16350 import Adis16350Sim
from imunoise.daq.sim.buspirate_pty import BusPirateEmulator
from imunoise.daq.transports.buspirate import BusPirateSPI
from tests.daq_testing import constant, record


def test_gyro_scale_datasheet_example():
    # +80 deg/s = 0x0444 at +-300 deg/s; ND and EA flags do not leak into the value.
    gyro = adis.REGISTERS["XGYRO_OUT"]
    assert gyro.counts(0x0444) == 1092
    assert gyro.counts(0xC444) == 1092
    assert gyro.decode(0x0444) / DEG == pytest.approx(80.0, abs=0.01)
    assert gyro.counts(0x3FFF) == -1 and gyro.counts(0x2000) == -8192
    assert adis.gyro_field("YGYRO_OUT", 150).scale / DEG == pytest.approx(0.07326 / 2, rel=1e-3)
    assert adis.gyro_field("ZGYRO_OUT", 75).scale / DEG == pytest.approx(0.07326 / 4, rel=1e-3)
    # what the simulator presents decodes back: encode and counts are inverses
    assert gyro.encode(gyro.from_si(80.0 * DEG)) == 0x0444
    assert gyro.from_si(1e3) == 8191  # saturates at 14 bits


def test_accel_temperature_supply_scales():
    # 1 g = 397 LSB (0x018D).
    r = adis.REGISTERS
    assert r["XACCL_OUT"].decode(0x018D) / G0 == pytest.approx(1.0, abs=0.0025)
    assert r["XTEMP_OUT"].decode(0x0000) == 25.0
    assert r["YTEMP_OUT"].decode(0x0FFF) == pytest.approx(25.0 - 0.1453)
    assert r["SUPPLY_OUT"].decode(2730) == pytest.approx(5.0, abs=0.002)
    assert r["SUPPLY_OUT"].decode(0xF000 | 2730) == r["SUPPLY_OUT"].decode(2730)


def test_command_words_match_datasheet_examples():
    # ZGYRO_OFF = -10 LSB: "write 0xF6 to 0x1E, then 0x1F to 0x1F".
    assert adis.write_commands("ZGYRO_OFF", (-10) & 0x1FFF) == [0x9EF6, 0x9F1F]
    # +-150 deg/s with 8 taps, range byte first: 0xB902 then 0xB803.
    value = adis.sens_avg_value(150, 8)
    assert value == 0x0203
    assert adis.write_commands("SENS_AVG", value, upper_first=True) == [0xB902, 0xB803]
    assert adis.read_command("XGYRO_OUT") == 0x0400


def test_sample_period_table():
    assert adis.sample_rate_hz(0x01) == pytest.approx(819.2)
    assert adis.sample_rate_hz(0x07) == pytest.approx(204.8)
    assert adis.sample_rate_hz(0x09) == pytest.approx(163.84)
    assert adis.sample_rate_hz(0x0A) == pytest.approx(148.945, abs=1e-3)
    assert adis.sample_rate_hz(0xFF) == pytest.approx(0.413, abs=1e-3)
    assert adis.sclk_max_hz(0x09) == 2e6 and adis.sclk_max_hz(0x0A) == 300e3
    assert adis.sclk_max_hz(0x81) == 300e3
    assert adis.smpl_prd_for_rate(100) == 0x0F  # 102.4 Hz is the nearest
    with pytest.raises(ValueError, match="out of range"):
        adis.smpl_prd_for_rate(1000)


def test_range_and_taps_rules():
    assert adis.sens_avg_value(300, 4) == adis.SENS_AVG_DEFAULT
    with pytest.raises(ValueError, match="at least 16 filter taps"):
        adis.sens_avg_value(75, 4)
    with pytest.raises(ValueError, match="power of two"):
        adis.sens_avg_value(300, 3)
    with pytest.raises(ValueError, match="choose one of"):
        adis.sens_avg_value(200, 4)
    assert adis.decode_sens_avg(0x0104) == (75, 16)


def test_status_decoding():
    assert adis.decode_status(0) == []
    assert adis.decode_status((1 << 12) | (1 << 4)) == ["sensor over-range",
                                                         "Z gyro self-diagnostic error"]


GYRO = (0.3, -0.2, 0.1)  # rad/s
ACCEL = (0.5, -1.0, G0)  # m/s^2

RATES = [
    (0x01, 300), (0x02, 150), (0x07, 75), (0x09, 300), (0x0A, 150), (0x0F, 300),
    (0x3F, 75), (0x7F, 300), (0x85, 150), (0x8F, 300),
]


@pytest.mark.parametrize(("smpl_prd", "range_dps"), RATES)
def test_driver_against_simulator(smpl_prd, range_dps):
    rate = adis.sample_rate_hz(smpl_prd)
    n_expected = 120
    duration = n_expected / rate
    acq = open_device("sim:adis16350", rate_hz=rate, realtime=False, range_dps=range_dps,
                      gyro=constant(GYRO), accel=constant(ACCEL))
    sim = acq.simulator
    rec = record(acq, duration)
    imu = rec["/adis16350/imu"]
    assert abs(len(imu["t"]) - n_expected) <= 2
    assert acq.stats.dropped == 0 and acq.stats.gaps == 0
    assert acq.config["smpl_prd"] == f"0x{smpl_prd:04X}"
    assert acq.config["self_test"] == "passed"
    assert float(acq.config["rate_hz"]) == pytest.approx(rate, rel=1e-5)
    # Configuration landed in the chip's registers, SPI clock within the mode's limit.
    assert sim.words[adis.ADDR["SMPL_PRD"]] == smpl_prd
    assert adis.decode_sens_avg(sim.words[adis.ADDR["SENS_AVG"]])[0] == range_dps
    assert sim.emulator.slave is sim
    assert float(acq.config["transport"].split(",")[-1].split()[0]) * 1e3 <= \
        adis.sclk_max_hz(smpl_prd)
    # Values: quantized to this range's LSB.
    lsb = adis.gyro_field("XGYRO_OUT", range_dps).scale
    for k, axis in enumerate("xyz"):
        assert np.allclose(imu["ch"][f"gyro_{axis}"], GYRO[k], atol=lsb / 2 + 1e-12)
        assert np.allclose(imu["ch"][f"accel_{axis}"], ACCEL[k],
                           atol=adis.REGISTERS["XACCL_OUT"].scale / 2 + 1e-12)
    assert np.allclose(np.diff(imu["t"]), 1 / rate, rtol=0, atol=1e-6)
    assert sim.undefined_writes == 0  # never clocked 0xFFFF
    assert sim.frames >= 7 * len(imu["t"])  # pipelined single reads, no burst


def test_temperature_stream_and_stale_reads_are_not_samples():
    acq = open_device("sim:adis16350", rate_hz=102.4, realtime=False,
                      gyro=constant(GYRO), accel=constant(ACCEL))
    rec = record(acq, 5.0)
    temp = rec["/adis16350/temperature"]
    assert len(temp["t"]) == pytest.approx(5, abs=1)
    assert np.all((temp["ch"]["temp"] > 20) & (temp["ch"]["temp"] < 30))
    assert np.all(temp["raw"]["supply"] == 2730)
    # The host polls 2 % faster than the part: some reads find no new data and are dropped.
    assert acq.driver.stale_reads > 0
    assert len(rec["/adis16350/imu"]["t"]) == pytest.approx(512, abs=2)


def test_over_range_is_flagged_through_status():
    acq = open_device("sim:adis16350", rate_hz=102.4, realtime=False, range_dps=75,
                      gyro=constant((3.0, 0.0, 0.0)), accel=constant(ACCEL))
    rec = record(acq, 0.5)
    gx = rec["/adis16350/imu"]["raw"]["gyro_x"]
    assert np.all(gx == 8191)
    assert acq.driver.status_seen.get("sensor over-range", 0) > 0


def _bench_driver(sim_kwargs=None, slave_present=True):
    clock = VirtualClock()
    sim = Adis16350Sim(clock, constant(GYRO), constant(ACCEL), source_rate_hz=819.2,
                       **(sim_kwargs or {}))
    emu = BusPirateEmulator(sim if slave_present else None).start()
    spi = BusPirateSPI(emu.port, timeout_s=0.2, opener=emu.serial_opener(clock))
    drv = adis.Adis16350(spi, rate_hz=102.4, clock=clock)
    return clock, sim, emu, drv


def test_self_test_pass_and_fail():
    clock, sim, emu, drv = _bench_driver()
    try:
        drv.open()
        assert drv.self_test() == []
        sim.self_test_fails = True
        flags = drv.self_test()
        assert "self-test failed" in flags and "X gyro self-diagnostic error" in flags
        assert drv.read_status() == []  # STATUS clears on read
    finally:
        drv.close()
        emu.close()


def test_identification_rejects_wrong_parts():
    clock, sim, emu, drv = _bench_driver({"supply_v": 3.3})
    try:
        with pytest.raises(PermanentDeviceError, match=r"not an ADIS16350.*3\.30 V"):
            drv.open()
    finally:
        drv.close()
        emu.close()
    clock, sim, emu, drv = _bench_driver(slave_present=False)
    try:
        with pytest.raises(PermanentDeviceError, match="no answer on SPI.*0xFFFF"):
            drv.open()
    finally:
        drv.close()
        emu.close()


def test_wrong_spi_mode_is_caught_by_the_answer_pattern():
    clock, sim, emu, drv = _bench_driver()
    try:
        drv.spi.open()
        drv.spi.configure(250e3, mode=0)
        with pytest.raises(PermanentDeviceError):
            drv.identify()
    finally:
        drv.close()
        emu.close()


def test_rate_resolution_reported():
    assert math.isclose(adis.sample_rate_hz(adis.smpl_prd_for_rate(819.2)), 819.2)
    assert len(adis.supported_rates_hz()) == 254


def test_model_new_data_flag_pipelining_and_status_clear():
    clock, sim, emu, drv = _bench_driver()
    try:
        drv.open()
        clock.advance(1 / 102.4)
        x = adis.read_command("XGYRO_OUT")
        miso = drv.spi.transfer_frames([x, x, adis.read_command("STATUS"), 0x0000])
        # Frame 1 answers the command before it; frame 2 carries ND, frame 3 has it cleared.
        assert miso[1] & adis.FLAG_ND and not miso[2] & adis.FLAG_ND
        gyro = adis.REGISTERS["XGYRO_OUT"]
        assert gyro.counts(miso[1]) == gyro.counts(miso[2])
        assert miso[3] == 0  # STATUS clean
        sim.supply_v = 5.4  # over-voltage: STATUS bit 1 and EA on the outputs
        clock.advance(1 / 102.4)
        miso = drv.spi.transfer_frames([x, adis.read_command("STATUS"),
                                        adis.read_command("STATUS"), 0x0000])
        assert miso[1] & adis.FLAG_EA
        assert adis.decode_status(int(miso[2])) == ["supply above 5.25 V"]
        assert miso[3] == 0  # cleared by the read
    finally:
        drv.close()
        emu.close()
