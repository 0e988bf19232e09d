"""Bus Pirate binary SPI transport against the emulated bridge on a real pseudo-terminal."""

from __future__ import annotations

import errno
import time

import numpy as np
import pytest
import serial

from imunoise.daq.clock import VirtualClock
from imunoise.daq.errors import PermanentDeviceError, TransientDeviceError
from imunoise.daq.sim.buspirate_pty import BusPirateEmulator
from imunoise.daq.transports.buspirate import (
    BusPirateSPI,
    config_byte,
    decode_frames,
    encode_frames,
    speed_index,
)


class EchoSlave:
    """Answers each 16-bit frame with the previous frame's word; records CS edges."""

    def __init__(self) -> None:
        self.selects = 0
        self.deselects = 0
        self.modes: set[int] = set()
        self.speeds: set[float] = set()
        self._prev = 0x1234
        self._cur: list[int] = []
        self._out = 0

    def select(self) -> None:
        self.selects += 1
        self._cur = []
        self._out = self._prev

    def deselect(self) -> None:
        self.deselects += 1

    def exchange(self, mosi: int, *, mode: int, speed_hz: float) -> int:
        self.modes.add(mode)
        self.speeds.add(speed_hz)
        out = (self._out >> 8) if not self._cur else self._out & 0xFF
        self._cur.append(mosi)
        if len(self._cur) == 2:
            self._prev = (self._cur[0] << 8) | self._cur[1]
        return out


@pytest.fixture
def bridge():
    slave = EchoSlave()
    emu = BusPirateEmulator(slave).start()
    spi = BusPirateSPI(emu.port, timeout_s=0.2, opener=emu.serial_opener())
    yield emu, slave, spi
    spi.close()
    emu.close()


def test_protocol_bytes_match_the_firmware_table():
    assert config_byte(3) == 0x8C  # push-pull, idle high, CKE = 0: SPI mode 3
    assert config_byte(0) == 0x8A  # flashrom's mode-0 value
    assert speed_index(300e3) == 2  # 250 kHz: ADIS normal mode limit is 300 kHz
    assert speed_index(2e6) == 4
    assert speed_index(1e6) == 3
    with pytest.raises(ValueError, match="no Bus Pirate SPI speed"):
        speed_index(10e3)
    raw = encode_frames([0x3E00, 0x0400])
    assert raw == bytes([0x02, 0x11, 0x3E, 0x00, 0x03, 0x02, 0x11, 0x04, 0x00, 0x03])
    reply = bytes([1, 1, 0xAB, 0xCD, 1, 1, 1, 0x12, 0x34, 1])
    assert decode_frames(reply, 2).tolist() == [0xABCD, 0x1234]
    assert decode_frames(reply[:-1], 2) is None
    assert decode_frames(bytes([1, 0, 0xAB, 0xCD, 1]), 1) is None


def test_enters_spi_mode_from_the_terminal_and_frames_each_word(bridge):
    emu, slave, spi = bridge
    spi.open()
    spi.configure(300e3, mode=3)
    assert emu._state == "spi"
    words = np.arange(0x0100, 0x0100 + 300, dtype=np.uint16)
    miso = spi.transfer_frames(words)
    # Full duplex, pipelined: each frame returns the previous frame's word.
    assert miso[0] == 0x1234
    assert np.array_equal(miso[1:], words[:-1])
    assert slave.selects == 300 and slave.deselects == 301  # CS per frame (+ one at open)
    assert slave.modes == {3} and slave.speeds == {250e3}
    spi.close()
    deadline = time.monotonic() + 2
    while emu._state != "terminal" and time.monotonic() < deadline:
        time.sleep(0.005)
    assert emu._state == "terminal"  # left binary mode on close


def test_reopen_while_bridge_is_still_in_spi_mode(bridge):
    emu, slave, spi = bridge
    spi.open()
    spi._ser.close()  # host crashed without leaving binary mode
    spi._ser = None
    assert emu._state == "spi"
    spi.open()
    spi.configure(2e6, mode=3)
    assert spi.transfer_frames([0xBEEF, 0x0000]).tolist()[1] == 0xBEEF


def test_write_only_frame_uses_firmware_chip_select(bridge):
    emu, slave, spi = bridge
    spi.open()
    spi.configure(300e3)
    before = slave.selects
    spi.write_only(0xBA06)
    assert slave.selects == before + 1
    assert spi.transfer_frames([0x0000]).tolist() == [0xBA06]


def test_garbage_is_detected_and_the_next_transfer_is_clean(bridge):
    emu, slave, spi = bridge
    spi.open()
    spi.configure(300e3)
    emu.inject_garbage(3)
    with pytest.raises(TransientDeviceError, match="garbage"):
        spi.transfer_frames([0x0102, 0x0304])
    assert spi.transfer_frames([0x0506, 0x0708]).tolist()[1] == 0x0506


def test_silent_bridge_times_out_with_the_port_named(bridge):
    emu, slave, spi = bridge
    spi.open()
    emu.mute = True
    with pytest.raises(TransientDeviceError, match=r"no answer.*got 0 of 10 bytes") as exc:
        spi.transfer_frames([1, 2])
    assert emu.port in str(exc.value)


def test_missing_port_and_no_permission_are_named():
    spi = BusPirateSPI("/nonexistent/ttyUSB9", timeout_s=0.1)
    with pytest.raises(TransientDeviceError, match=r"/nonexistent/ttyUSB9: not found"):
        spi.open()
    exc = serial.SerialException(errno.EACCES, "could not open port x: Permission denied")
    err = spi._open_error(exc)
    assert isinstance(err, PermanentDeviceError) and "dialout" in str(err)


def test_unplug_fails_and_replug_at_the_same_path_works(bridge):
    emu, slave, spi = bridge
    spi.open()
    emu.unplug()
    with pytest.raises(TransientDeviceError):
        spi.transfer_frames([1, 2, 3])
    spi.close()
    with pytest.raises(TransientDeviceError, match="not found"):
        spi.open()
    emu.replug()
    spi.open()
    spi.configure(300e3)
    assert spi.transfer_frames([0x4242, 0]).tolist()[1] == 0x4242


def test_empty_bus_reads_ones(bridge):
    emu, slave, spi = bridge
    emu.slave = None
    spi.open()
    assert spi.transfer_frames([0x0200, 0x0000]).tolist() == [0xFFFF, 0xFFFF]


class SlowSlave(EchoSlave):
    """An echo slave whose first exchange stalls, as an emulator thread starved of CPU would."""

    def __init__(self, stall_s: float) -> None:
        super().__init__()
        self.stall_s = stall_s

    def exchange(self, mosi: int, *, mode: int, speed_hz: float) -> int:
        if self.stall_s:
            time.sleep(self.stall_s)
            self.stall_s = 0.0
        return super().exchange(mosi, mode=mode, speed_hz=speed_hz)


def test_a_stalled_emulator_is_not_taken_for_a_silent_bridge():
    with BusPirateEmulator(SlowSlave(0.3)) as emu:
        spi = BusPirateSPI(emu.port, timeout_s=0.1, opener=emu.serial_opener())
        spi.open()
        assert spi.transfer_frames([0xCAFE, 0]).tolist() == [0x1234, 0xCAFE]
        spi.close()
    # The same stall through a plain pyserial port is a timeout: what the emulated port's
    # accounting saves the simulated runs from on a busy host.
    with BusPirateEmulator(SlowSlave(0.3)) as emu:
        spi = BusPirateSPI(emu.port, timeout_s=5.0)
        spi.open()
        spi._ser.timeout = 0.1
        with pytest.raises(TransientDeviceError, match="no answer"):
            spi.transfer_frames([0xCAFE, 0])
        spi.close()


def test_silence_costs_the_timeout_on_the_simulation_clock():
    clock = VirtualClock(start=5.0)
    with BusPirateEmulator(EchoSlave()) as emu:
        spi = BusPirateSPI(emu.port, timeout_s=0.25, opener=emu.serial_opener(clock))
        spi.open()
        assert clock.now() == 5.0  # a bridge that answers costs no simulated time
        emu.mute = True
        with pytest.raises(TransientDeviceError, match=r"got 0 of 10 bytes in 0.25 s"):
            spi.transfer_frames([1, 2])
        assert clock.now() == pytest.approx(5.25, abs=1e-12)
        emu.mute = False
        spi.open()  # leftovers of the silent exchange do not confuse the next session
        assert spi.transfer_frames([0x0BAD, 0]).tolist()[1] == 0x0BAD
        spi.close()
