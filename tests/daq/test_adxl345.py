"""ADXL345: scaling and rate codes; FIFO behaviour of the model; the driver against the model
under the real smbus2 at every rate code and every range."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.core.units import G0
from imunoise.daq.clock import VirtualClock
from imunoise.daq.devices import open_device
from imunoise.daq.drivers import adxl345 as ax
from imunoise.daq.errors import PermanentDeviceError
from imunoise.daq.sim.adxl345 import Adxl345Sim
from imunoise.daq.sim.fake_i2c import SimulatedI2CAdapter
from imunoise.daq.transports.i2c import I2CBus
from tests.daq_testing import constant, record


def test_scaling_and_byte_order():
    assert ax.REGISTERS["DATAX"].to_si(256) == pytest.approx(G0)  # 256 LSB/g
    assert ax.REGISTERS["DATAZ"].to_si(1) / G0 * 1e3 == pytest.approx(3.9, abs=0.01)  # 3.9 mg/LSB
    b = np.array([0x00, 0x01, 0x00, 0xFF, 0x01, 0x00])  # little-endian
    assert ax.decode_data(b).tolist() == [[256, -256, 1]]


def test_rate_codes():
    assert ax.odr_hz(0x0F) == 3200 and ax.odr_hz(0x0A) == 100
    assert ax.odr_hz(0x00) == pytest.approx(0.1, rel=0.03)  # table rounds 0.0977 Hz
    assert ax.rate_code(100) == 0x0A and ax.rate_code(3200) == 0x0F
    assert ax.rate_code(0.1) == 0x00 and ax.rate_code(12.5) == 0x07
    assert ax.data_format(2) == 0x08 and ax.data_format(16) == 0x0B
    with pytest.raises(ValueError, match="choose one of"):
        ax.data_format(3)


def _chip():
    clock = VirtualClock()
    sim = Adxl345Sim(clock, constant((0.0, 0.0, G0)))
    bus = SimulatedI2CAdapter({0x53: sim}, clock=clock).open_bus()
    return clock, sim, bus


def test_power_up_state_and_standby():
    clock, sim, bus = _chip()
    assert bus.read_byte_data(0x53, ax.REG["DEVID"]) == 0xE5
    assert bus.read_byte_data(0x53, ax.REG["BW_RATE"]) == 0x0A
    clock.advance(1.0)
    assert bus.read_byte_data(0x53, ax.REG["FIFO_STATUS"]) == 0  # standby: no data
    assert sim.samples_made == 0


def test_fifo_stream_mode_overrun_and_pop():
    clock, sim, bus = _chip()
    bus.write_byte_data(0x53, ax.REG["DATA_FORMAT"], 0x08)
    bus.write_byte_data(0x53, ax.REG["FIFO_CTL"], (ax.FIFO_STREAM << 6) | 16)
    bus.write_byte_data(0x53, ax.REG["POWER_CTL"], 0x08)
    clock.advance(0.1001)  # 10 samples at 100 Hz
    assert bus.read_byte_data(0x53, ax.REG["FIFO_STATUS"]) & 0x3F == 10
    src = bus.read_byte_data(0x53, ax.REG["INT_SOURCE"])
    assert src & ax.INT_DATA_READY and not src & ax.INT_WATERMARK
    row = bus.read_i2c_block_data(0x53, ax.REG["DATAX"], 6)
    assert ax.decode_data(np.array(row)).tolist() == [[0, 0, 256]]
    assert bus.read_byte_data(0x53, ax.REG["FIFO_STATUS"]) & 0x3F == 9  # popped one
    clock.advance(1.0)  # 100 more: stream mode keeps the newest 33
    assert bus.read_byte_data(0x53, ax.REG["FIFO_STATUS"]) & 0x3F == 33
    assert bus.read_byte_data(0x53, ax.REG["INT_SOURCE"]) & ax.INT_OVERRUN
    assert sim.samples_lost == 109 - 33
    bus.read_i2c_block_data(0x53, ax.REG["DATAX"], 6)
    assert not bus.read_byte_data(0x53, ax.REG["INT_SOURCE"]) & ax.INT_OVERRUN


ACCEL = (0.7, -1.2, G0)


@pytest.mark.parametrize("code", range(16))
def test_driver_against_simulator_every_rate(code):
    rate = ax.odr_hz(code)
    n_target = 100
    acq = open_device("sim:adxl345", rate_hz=rate, realtime=False, accel=constant(ACCEL))
    sim = acq.simulator.adxl
    rec = record(acq, n_target / rate)
    imu = rec["/adxl345/imu"]
    assert acq.config["bw_rate"] == f"0x{code:02X}"
    assert acq.stats.dropped == 0
    assert abs(len(imu["t"]) - n_target) <= max(3, 0.1 * rate / 10 + 1) + 33
    # Whatever was made and not read is still in the FIFO: nothing vanished.
    assert len(imu["t"]) + len(sim.fifo) == sim.samples_made
    lsb = G0 / 256
    tol = lsb * (1.0 if code >= 0x0E else 0.5) + 1e-12  # LSB forced to 0 at 1600/3200 Hz
    for k, axis in enumerate("xyz"):
        assert np.allclose(imu["ch"][f"accel_{axis}"], ACCEL[k], atol=tol)
    t = imu["t"]
    assert np.allclose(np.diff(t), 1 / rate, rtol=0, atol=1e-6)


@pytest.mark.parametrize("range_g", [2, 4, 8, 16])
def test_driver_every_range_full_resolution(range_g):
    accel = (1.5 * G0, -1.9 * G0, 3.0 * G0)
    acq = open_device("sim:adxl345", rate_hz=100, realtime=False, range_g=range_g,
                      accel=constant(accel))
    rec = record(acq, 0.5)
    raw = rec["/adxl345/imu"]["raw"]
    assert np.all(raw["accel_x"] == 384)  # 1.5 g at 256 LSB/g, any range
    assert np.all(raw["accel_y"] == round(-1.9 * 256))
    top = 2 ** (ax.full_res_bits(range_g) - 1) - 1
    assert np.all(raw["accel_z"] == min(768, top))  # 3 g clips at +-2 g (10 bits)


def test_fifo_overrun_becomes_a_gap_of_the_right_length():
    acq = open_device("sim:adxl345", rate_hz=400, realtime=False, accel=constant(ACCEL))
    sim = acq.simulator.adxl
    n = 0
    gaps = []
    with acq:
        for b in acq.blocks(3.0):
            n += len(b)
            gaps.append(b.gap_before)
            if n > 400 and not sim.samples_lost:
                acq.clock.advance(0.5)  # the host stalls for half a second
    assert sim.samples_lost > 100
    assert sum(gaps) == pytest.approx(sim.samples_lost, abs=2)
    assert acq.driver.overruns == 1


def test_wrong_devid_is_refused():
    clock = VirtualClock()
    sim = Adxl345Sim(clock, constant((0, 0, 0)))
    sim.devid = 0x00
    drv = ax.Adxl345(I2CBus(1, opener=SimulatedI2CAdapter({0x53: sim}).open_bus), clock=clock)
    with pytest.raises(PermanentDeviceError, match="DEVID reads 0x00, expected 0xE5"):
        drv.open()


def _drained_by_hand(rate_hz: float = 800.0):
    """The driver on the model at ``rate_hz`` (virtual clock, opened, first drain done) and the
    list of registers it reads with single-byte reads (the status reads) from now on."""
    acq = open_device("sim:adxl345", rate_hz=rate_hz, realtime=False, accel=constant(ACCEL))
    acq.open()
    drv = acq.driver
    drv.poll()
    status: list[int] = []
    read_u8 = drv.bus.read_u8
    drv.bus.read_u8 = lambda addr, reg: status.append(reg) or read_u8(addr, reg)
    return acq, drv, status


def _read_and_gaps(drv) -> tuple[int, int]:
    blocks = drv.take_blocks()
    return sum(len(b) for b in blocks), sum(max(0, b.gap_before) for b in blocks)


def test_a_drain_cut_short_goes_on_without_the_status_reads_and_loses_nothing():
    acq, drv, status = _drained_by_hand()
    sim, clock = acq.simulator.adxl, acq.clock
    clock.advance(0.02)  # 16 entries at 800 Hz
    assert drv.poll(deadline=clock.now()) == 1  # cut short after the first entry
    left = drv.fifo_left
    assert left >= 14
    status.clear()
    clock.advance(0.005)  # 4 more come meanwhile
    assert drv.poll() == left  # those left, read on...
    assert status == []  # ...without INT_SOURCE and FIFO_STATUS first
    assert drv.fifo_left == 0
    # the bound still counts what came since the status read, though none was left over
    assert len(sim.fifo) >= 4
    assert drv.entries_at_most(clock.now()) >= len(sim.fifo)
    clock.advance(0.01)
    drv.poll()  # nothing left over: the next drain reads the status again
    assert status == [ax.REG["INT_SOURCE"], ax.REG["FIFO_STATUS"]]
    n, gaps = _read_and_gaps(drv)
    assert gaps == 0 and sim.samples_lost == 0
    assert n + len(sim.fifo) == sim.samples_made  # every sample made was read or waits


def test_a_drain_after_a_long_pause_reads_the_status_and_finds_the_overrun():
    acq, drv, status = _drained_by_hand()
    sim, clock = acq.simulator.adxl, acq.clock
    clock.advance(0.02)
    drv.poll(deadline=clock.now())
    assert drv.fifo_left >= 14
    clock.advance(0.1)  # 80 more: the FIFO could have filled, so the entries left say little
    status.clear()
    drv.poll()
    assert status == [ax.REG["INT_SOURCE"], ax.REG["FIFO_STATUS"]]
    assert sim.samples_lost > 50 and drv.overruns == 1
    n, gaps = _read_and_gaps(drv)
    assert gaps == pytest.approx(sim.samples_lost, abs=2)
