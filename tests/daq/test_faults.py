"""Faults injected by the simulators, through the real pyserial / smbus2 stacks and the
acquisition loop: transient ones are survived with the gap marked, permanent ones stop the
loop with a clear message."""

from __future__ import annotations

import math

import numpy as np
import pytest

from imunoise.core.units import G0
from imunoise.daq.devices import open_device
from imunoise.daq.drivers.common import PolledSampleClock
from imunoise.daq.errors import AcquisitionFailed, DeviceError, PermanentDeviceError
from imunoise.daq.transports.i2c import I2CBus
from tests.daq_testing import constant

GYRO = (0.01, 0.02, -0.03)
ACCEL = (0.0, 0.0, G0)


def adis(**kw):
    return open_device("sim:adis16350", rate_hz=102.4, realtime=False, timeout_s=0.1,
                       gyro=constant(GYRO), accel=constant(ACCEL), **kw)


def run(acq, duration, fault_at_s, inject):
    """Record ``duration`` s of device time; call ``inject(acq)`` once at ``fault_at_s``."""
    blocks = []
    done = False
    t0 = None
    with acq:
        for b in acq.blocks(duration):
            t0 = b.t[0] if t0 is None else t0
            blocks.append(b)
            if not done and b.t[-1] - t0 >= fault_at_s:
                inject(acq)
                done = True
    return blocks


def imu_count(blocks, stream_suffix="/imu"):
    n = sum(len(b) for b in blocks if b.stream.endswith(stream_suffix))
    dropped = sum(b.gap_before for b in blocks if b.stream.endswith(stream_suffix))
    return n, dropped


def assert_accounted(acq, blocks, duration, rate, slack=3):
    """Delivered plus flagged-missing samples cover the whole run; times stay on the grid."""
    n, dropped = imu_count(blocks)
    assert dropped == acq.stats.dropped
    assert abs(n + dropped - duration * rate) <= slack
    imu = [b for b in blocks if b.stream.endswith("/imu")]
    for prev, b in zip(imu[:-1], imu[1:], strict=True):
        steps = round((b.t[0] - prev.t[-1]) * rate)
        assert steps == b.gap_before + 1


def test_serial_garbage_reconnects_and_marks_the_gap():
    acq = adis()
    blocks = run(acq, 6.0, 2.0, lambda a: a.simulator.emulator.inject_garbage(5))
    assert acq.stats.reconnects == 1 and acq.stats.gaps == 1
    assert "garbage" in acq.stats.last_error
    assert acq.stats.dropped > 10  # reset and restart of the part take a few tenths of a s
    assert_accounted(acq, blocks, 6.0, 102.4)
    assert acq.stats.state == "stopped"


def test_bridge_that_stops_answering_for_a_while():
    acq = adis()

    def inject(a):
        a.simulator.emulator.mute = True
        a.clock.call_at(a.clock.now() + 1.0,
                        lambda: setattr(a.simulator.emulator, "mute", False))

    blocks = run(acq, 8.0, 1.0, inject)
    assert acq.stats.reconnects == 1
    assert "no answer" in acq.stats.last_error
    assert acq.stats.dropped > 0
    assert_accounted(acq, blocks, 8.0, 102.4)


def test_dead_bridge_fails_with_a_clear_message():
    acq = adis(max_outage_s=1.0)
    with pytest.raises(AcquisitionFailed, match=r"no answer.*gave up after 1 s") as exc:
        run(acq, 30.0, 1.0, lambda a: setattr(a.simulator.emulator, "mute", True))
    assert acq.simulator.emulator.port in str(exc.value)
    assert acq.stats.state.startswith("failed: ")
    assert acq.stats.reconnects == 0


def test_unplug_and_replug_of_the_tty():
    acq = adis()

    def inject(a):
        a.simulator.emulator.unplug()
        a.clock.call_at(a.clock.now() + 1.0, a.simulator.emulator.replug)

    blocks = run(acq, 8.0, 2.0, inject)
    assert acq.stats.reconnects == 1
    assert_accounted(acq, blocks, 8.0, 102.4)


def test_adis_stuck_data_ready_is_cured_by_a_reset():
    acq = adis()
    blocks = run(acq, 8.0, 2.0, lambda a: setattr(a.simulator, "stuck_data", True))
    assert acq.stats.reconnects == 1
    assert "data-ready stuck" in acq.stats.last_error
    n, dropped = imu_count(blocks)
    assert dropped >= 0.5 * 102.4  # at least the stale timeout
    assert_accounted(acq, blocks, 8.0, 102.4)


def itg(**kw):
    return open_device("sim:itg3200", rate_hz=100, realtime=False, gyro=constant(GYRO), **kw)


def test_short_nack_burst_is_absorbed_by_retries():
    acq = itg()
    blocks = run(acq, 3.0, 1.0, lambda a: a.simulator.adapter.nack_burst(2))
    assert acq.driver.bus.retried == 2
    assert acq.stats.reconnects == 0 and acq.stats.dropped == 0
    assert_accounted(acq, blocks, 3.0, 100.0)


@pytest.mark.parametrize("kind", ["nack_burst", "io_error_burst"])
def test_long_i2c_error_burst_reconnects(kind):
    acq = itg()
    blocks = run(acq, 4.0, 1.0, lambda a: getattr(a.simulator.adapter, kind)(10))
    assert acq.stats.reconnects == 1
    reason = "no answer (NACK)" if kind == "nack_burst" else "I/O error"
    assert reason in acq.stats.last_error and "device 0x68" in acq.stats.last_error
    assert acq.stats.dropped > 0
    assert_accounted(acq, blocks, 4.0, 100.0)


def test_adxl_reconnect_counts_the_samples_missed_while_away():
    acq = open_device("sim:adxl345", rate_hz=400, realtime=False,
                      accel=constant((0.0, 0.0, G0)))
    blocks = run(acq, 4.0, 1.0, lambda a: a.simulator.adapter.nack_burst(12))
    assert acq.stats.reconnects == 1 and acq.stats.gaps == 1
    assert acq.stats.dropped > 5
    # Up to a FIFO's worth of samples is still unread when the run ends.
    assert_accounted(acq, blocks, 4.0, 400.0, slack=35)


def test_itg_stuck_data_ready_reconnects_with_a_reset():
    acq = itg()
    blocks = run(acq, 5.0, 1.0, lambda a: setattr(a.simulator.itg, "stuck_ready", True))
    assert acq.stats.reconnects == 1
    assert "no data-ready" in acq.stats.last_error
    assert acq.stats.dropped >= 50
    assert_accounted(acq, blocks, 5.0, 100.0)


def test_wrong_chip_after_reconnect_stops_the_loop():
    acq = open_device("sim:razor", rate_hz=100, realtime=False)

    def inject(a):
        a.simulator.itg.who_am_i = 0x00
        a.simulator.adapter.nack_burst(10)

    with pytest.raises(AcquisitionFailed, match="WHO_AM_I reads 0x00"):
        run(acq, 10.0, 1.0, inject)
    assert acq.stats.state.startswith("failed: ITG-3200 at 0x68")


def test_wrong_chip_at_start_is_an_error_not_a_retry():
    acq = open_device("sim:adxl345", rate_hz=100, realtime=False)
    acq.simulator.adxl.devid = 0x1F
    with pytest.raises(PermanentDeviceError, match="DEVID reads 0x1F"):
        acq.open()
    acq.close()


def test_missing_bus_and_no_permission_name_the_bus():
    acq = open_device("itg3200", bus=97)
    with pytest.raises(DeviceError, match=r"I2C bus 97 \(/dev/i2c-97\): not found"):
        acq.open()

    def denied(bus):
        raise PermissionError(13, "Permission denied")

    i2c = I2CBus(5, opener=denied)
    with pytest.raises(PermanentDeviceError, match=r"I2C bus 5 .*permission denied.*i2c group"):
        i2c.open()


def test_missing_serial_port_is_named():
    acq = open_device("adis16350", port="/dev/ttyNOPE0")
    with pytest.raises(DeviceError, match="/dev/ttyNOPE0: not found"):
        acq.open()


def test_record_command_reports_a_missing_device_in_one_line(tmp_path, capsys):
    from imunoise.cli import main

    code = main(["record", "--device", "itg3200", "--bus", "97", "--duration", "2",
                 "--out", str(tmp_path)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert len(err) == 1 and "I2C bus 97 (/dev/i2c-97): not found" in err[0]


@pytest.mark.parametrize("offset", [0.1, 0.3, 0.5, 0.7, 0.9])
def test_reconnect_to_a_reset_device_adopts_its_new_sampling_phase(offset):
    """Polling a device that restarted on a new phase: the samples lost while away are
    counted once, and no spurious gap follows while the phase estimate settles."""
    fs = 100.0
    period = 1.0 / (1.02 * fs)  # the drivers poll 2 % faster than the part samples
    phase = PolledSampleClock(fs)
    next_index = 0
    missed_log = []

    def poll_from(t_start, t_stop, device_t0):
        nonlocal next_index
        seen = None
        for t in t_start + period * np.arange(int((t_stop - t_start) / period)):
            newest = math.floor((t - device_t0) * fs)
            if newest < 0 or newest == seen:
                phase.stale(t, next_index - 1)
                continue
            seen = newest
            missed = phase.fresh(t, next_index)
            missed_log.append(missed)
            next_index += missed + 1

    poll_from(0.0, 1.0, device_t0=0.0021)
    phase.reconnected()
    poll_from(1.05, 3.0, device_t0=1.29 + offset / fs)  # reset: 290 ms, then a new phase
    gaps = [m for m in missed_log if m > 0]
    assert len(gaps) == 1
    # Away from the last sample read before the fault to the first one after it.
    assert gaps[0] == pytest.approx((1.29 + offset / fs - 1.0) * fs, abs=1.5)


def test_razor_accelerometer_keeps_draining_while_the_gyro_stalls():
    """The gyro delivers nothing for 0.4 s (under its 0.5 s stuck timeout); the accelerometer
    FIFO (32 entries, 40 ms at 800 Hz) is drained all the same and loses nothing."""
    acq = open_device("sim:razor", rate_hz=1000, realtime=False)
    clock = acq.clock

    def stall_gyro(a):
        sim = a.simulator.itg
        sim.stuck_ready = True
        clock.call_at(clock.now() + 0.4, lambda: setattr(sim, "stuck_ready", False))

    blocks = run(acq, 3.0, 1.0, stall_gyro)
    accel = [b for b in blocks if b.stream == "/razor/adxl345/imu"]
    gyro_gaps = sum(b.gap_before for b in blocks if b.stream == "/razor/itg3200/imu")
    assert gyro_gaps >= 350  # the stall itself
    assert sum(b.gap_before for b in accel) == 0
    assert acq.driver.adxl.overruns == 0
    assert sum(len(b) for b in accel) == pytest.approx(2400, abs=35)
