"""ITG-3200: scaling and rate tables; the driver against its register-level model under the
real smbus2 (ioctl layer simulated) at every rate class."""

from __future__ import annotations

import numpy as np
import pytest
import smbus2

from imunoise.core.units import DEG
from imunoise.daq.clock import VirtualClock
from imunoise.daq.devices import open_device
from imunoise.daq.drivers import itg3200 as itg
from imunoise.daq.errors import PermanentDeviceError
from imunoise.daq.sim.fake_i2c import SimulatedI2CAdapter, SimulatedSMBus
from imunoise.daq.sim.itg3200 import Itg3200Sim
from imunoise.daq.transports.i2c import I2CBus
from tests.daq_testing import constant, record


def test_scaling_datasheet_values():
    assert itg.REGISTERS["GYRO_XOUT"].to_si(14.375) / DEG == pytest.approx(1.0)
    assert itg.REGISTERS["GYRO_YOUT"].to_si(-28.75) / DEG == pytest.approx(-2.0)
    # -13200 LSB at 35 degC, 280 LSB per degC.
    assert itg.REGISTERS["TEMP_OUT"].to_si(-13200) == pytest.approx(35.0)
    assert itg.REGISTERS["TEMP_OUT"].to_si(-13200 + 280) == pytest.approx(36.0)
    # Linux's (raw + 23000) / 280 form
    assert itg.REGISTERS["TEMP_OUT"].to_si(-23000) == pytest.approx(0.0)
    b = np.array([0xCC, 0x70, 0x00, 0x0E, 0xFF, 0xF2, 0x80, 0x00])
    assert itg.decode_data(b).tolist() == [[-13200, 14, -14, -32768]]


def test_who_am_i_check():
    assert itg.is_itg3200_id(0x68) and itg.is_itg3200_id(0x69)
    assert itg.is_itg3200_id(0xE9)  # bits 7 and 0 are undefined
    assert not itg.is_itg3200_id(0x00) and not itg.is_itg3200_id(0xE5)


def test_rate_settings_table():
    assert itg.rate_settings(8000) == (0, 0, 8000.0)
    assert itg.rate_settings(4000) == (0, 1, 4000.0)
    assert itg.rate_settings(1000) == (1, 0, 1000.0)
    assert itg.rate_settings(500) == (1, 1, 500.0)  # 188 Hz filter below 250 Hz Nyquist
    assert itg.rate_settings(200) == (2, 4, 200.0)
    assert itg.rate_settings(100) == (3, 9, 100.0)
    assert itg.rate_settings(50) == (4, 19, 50.0)
    assert itg.rate_settings(125) == (3, 7, 125.0)  # datasheet example: 1 kHz / 8
    assert itg.rate_settings(3.90625) == (6, 255, 3.90625)
    with pytest.raises(ValueError, match="out of range"):
        itg.rate_settings(9000)


def test_simulated_bus_runs_smbus2_marshalling():
    clock = VirtualClock()
    sim = Itg3200Sim(clock, constant((0.0, 0.0, 0.0)))
    adapter = SimulatedI2CAdapter({0x68: sim}, clock=clock)
    bus = adapter.open_bus()
    assert isinstance(bus, smbus2.SMBus) and isinstance(bus, SimulatedSMBus)
    assert bus.read_byte_data(0x68, itg.REG["WHO_AM_I"]) == 0x68
    bus.write_i2c_block_data(0x68, itg.REG["SMPLRT_DIV"], [7, 0x1B])  # auto-increment
    assert bus.read_i2c_block_data(0x68, itg.REG["SMPLRT_DIV"], 2) == [7, 0x1B]
    w = smbus2.i2c_msg.write(0x68, [itg.REG["DLPF_FS"]])
    r = smbus2.i2c_msg.read(0x68, 1)
    bus.i2c_rdwr(w, r)
    assert list(r) == [0x1B]
    with pytest.raises(OSError):
        bus.read_byte_data(0x50, 0)  # nobody at 0x50: NACK
    bus.close()


RATES = [8000, 4000, 2000, 1000, 500, 200, 100, 50, 10, 3.90625]


@pytest.mark.parametrize("rate", RATES)
def test_driver_against_simulator(rate):
    gyro = (0.5, -0.25, 1.0)
    n_target = 150
    acq = open_device("sim:itg3200", rate_hz=rate, realtime=False, gyro=constant(gyro))
    sim = acq.simulator.itg
    rec = record(acq, n_target / rate)
    imu = rec["/itg3200/imu"]
    got = len(imu["t"])
    # Clock from the X-gyro PLL (the internal oscillator would run 3 % slow), FS_SEL = 3.
    assert sim.regs[itg.REG["PWR_MGM"]] & 0x07 == itg.CLK_PLL_X
    assert sim.regs[itg.REG["DLPF_FS"]] >> 3 == 3
    assert float(acq.config["rate_hz"]) == pytest.approx(rate)
    lsb = itg.REGISTERS["GYRO_ZOUT"].scale
    for k, axis in enumerate("xyz"):
        assert np.allclose(imu["ch"][f"gyro_{axis}"], gyro[k], atol=lsb / 2)
    # Every sample the chip made since acquisition started is either delivered or counted
    # as missing: gaps are flagged, never hidden.
    total = got + acq.stats.dropped
    assert abs(total - n_target) <= 3
    if rate <= 2000:
        assert acq.stats.dropped == 0
    else:
        # A 400 kHz bus cannot poll INT_STATUS and read 8 bytes 4000 times a second.
        assert acq.stats.dropped > 0 and acq.stats.gaps > 0
    t = imu["t"]
    idx = np.round((t - t[0]) * rate)
    assert np.allclose(t - t[0], idx / rate, rtol=0, atol=1e-6)  # from the sample count


def test_wrong_chip_is_refused():
    clock = VirtualClock()
    sim = Itg3200Sim(clock, constant((0, 0, 0)))
    sim.who_am_i = 0x00
    adapter = SimulatedI2CAdapter({0x68: sim}, clock=clock)
    drv = itg.Itg3200(I2CBus(3, opener=adapter.open_bus, clock=clock), clock=clock)
    with pytest.raises(PermanentDeviceError,
                       match=r"ITG-3200 at 0x68 on I2C bus 3 \(/dev/i2c-3\): WHO_AM_I reads 0x00"):
        drv.open()
    drv.close()


def test_temperature_stream():
    acq = open_device("sim:itg3200", rate_hz=100, realtime=False, gyro=constant((0, 0, 0)),
                      temperature=lambda t: 30.0 + 0.0 * t)
    rec = record(acq, 5.0)
    temp = rec["/itg3200/temperature"]
    assert len(temp["t"]) == pytest.approx(5, abs=1)
    assert np.allclose(temp["ch"]["temp"], 30.0, atol=1 / 280)


def test_model_power_up_state_and_data_ready_rules():
    clock = VirtualClock()
    sim = Itg3200Sim(clock, constant((0.0, 0.0, 0.0)))
    bus = SimulatedI2CAdapter({0x68: sim}, clock=clock).open_bus()
    assert bus.read_byte_data(0x68, itg.REG["DLPF_FS"]) == 0  # FS_SEL = 0 at power-up
    assert bus.read_byte_data(0x68, itg.REG["PWR_MGM"]) & 0x07 == itg.CLK_INTERNAL
    clock.advance(0.05)
    # New data exists, but INT_STATUS shows only what INT_CFG enables.
    assert bus.read_byte_data(0x68, itg.REG["INT_STATUS"]) == 0
    bus.write_byte_data(0x68, itg.REG["INT_CFG"], itg.INT_CFG_RAW_RDY_EN)
    clock.advance(0.002)
    assert bus.read_byte_data(0x68, itg.REG["INT_STATUS"]) == itg.INT_RAW_DATA_RDY
    assert bus.read_byte_data(0x68, itg.REG["INT_STATUS"]) == 0  # cleared by reading it
    clock.advance(0.002)
    bus.read_i2c_block_data(0x68, itg.REG["TEMP_OUT"], 8)  # a data read does not clear
    assert bus.read_byte_data(0x68, itg.REG["INT_STATUS"]) == itg.INT_RAW_DATA_RDY
    bus.write_byte_data(0x68, itg.REG["INT_CFG"],
                        itg.INT_CFG_RAW_RDY_EN | itg.INT_CFG_ANYRD_2CLEAR)
    clock.advance(0.002)
    bus.read_i2c_block_data(0x68, itg.REG["TEMP_OUT"], 8)  # now any read clears
    assert bus.read_byte_data(0x68, itg.REG["INT_STATUS"]) == 0
    # Burst reads stop in the reserved area after GYRO_ZOUT_L.
    tail = bus.read_i2c_block_data(0x68, itg.REG["GYRO_ZOUT"] + 1, 4)
    assert tail[1:] == [0, 0, 0]
    bus.close()
