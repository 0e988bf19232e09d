"""A Bus Pirate (binary SPI mode) emulated on a pseudo-terminal, in a thread.

The real driver opens the pty's path with the real pyserial and speaks the real byte protocol;
behind the emulated bridge sits a register-level SPI chip model (:class:`SpiSlave`). Faults
can be switched on at any time: garbage bytes on the line, a bridge that stops answering, and
unplug/replug of the tty (the path disappears and comes back, as a USB adapter would).
"""

from __future__ import annotations

import os
import select
import tempfile
import threading
import tty
from typing import Protocol

import numpy as np

from daq.transports.buspirate import (
    ACK,
    BBIO_ENTER_SPI,
    BBIO_EXIT_TO_TERMINAL,
    BBIO_RESET,
    BBIO_SIGNATURE,
    SPI_BULK,
    SPI_CONFIG,
    SPI_CS_HIGH,
    SPI_CS_LOW,
    SPI_MODE_BITS,
    SPI_PERIPHERALS,
    SPI_SIGNATURE,
    SPI_SPEED,
    SPI_SPEEDS_HZ,
    SPI_WRITE_THEN_READ,
)

# Power-on SPI settings of the firmware: speed index 1, CKP=0, CKE=1 (mode 0).
POWER_ON_SPEED_INDEX = 1
POWER_ON_MODE = 0
ZEROS_TO_ENTER_BINARY = 20


class SpiSlave(Protocol):
    """What the emulated bridge needs from a chip on its SPI bus."""

    def select(self) -> None: ...

    def deselect(self) -> None: ...

    def exchange(self, mosi: int, *, mode: int, speed_hz: float) -> int: ...


def _mode_from_config(byte: int) -> int:
    ckp, cke = (byte >> 2) & 1, (byte >> 1) & 1
    for mode, bits in SPI_MODE_BITS.items():
        if bits == (ckp, cke):
            return mode
    raise AssertionError("unreachable")


class BusPirateEmulator:
    """Bus Pirate v3 binary SPI protocol on a pty whose path is :attr:`port`.

    Args:
        slave: the chip on the SPI bus, or None for an empty bus (MISO reads 0xFF).
        seed: seed for the garbage fault's random bytes.
    """

    def __init__(self, slave: SpiSlave | None, *, seed: int = 0) -> None:
        self.slave = slave
        self._dir = tempfile.mkdtemp(prefix="imunoise-bp-")
        self.port = os.path.join(self._dir, "ttyBP0")
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._master: int | None = None
        self._slave_fd: int | None = None
        self._thread: threading.Thread | None = None
        # Fault switches.
        self.mute = False
        self._garbage_pending = 0
        self._reset_protocol()
        self.frames = 0

    # -- lifecycle -------------------------------------------------------------------------
    def start(self) -> BusPirateEmulator:
        self._plug()
        self._thread = threading.Thread(target=self._run, name="buspirate-emulator",
                                        daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._unplug_fds()
        try:
            os.unlink(self.port)
        except FileNotFoundError:
            pass
        try:
            os.rmdir(self._dir)
        except OSError:
            pass

    def __enter__(self) -> BusPirateEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _plug(self) -> None:
        master, slave_fd = os.openpty()
        tty.setraw(slave_fd)
        with self._lock:
            self._master, self._slave_fd = master, slave_fd
            self._reset_protocol()
        tmp = self.port + ".new"
        os.symlink(os.ttyname(slave_fd), tmp)
        os.replace(tmp, self.port)

    def _unplug_fds(self) -> None:
        with self._lock:
            fds = (self._master, self._slave_fd)
            self._master = self._slave_fd = None
        for fd in fds:
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    # -- faults ----------------------------------------------------------------------------
    def unplug(self) -> None:
        """The USB cable is pulled: the tty vanishes and open handles fail."""
        self._unplug_fds()
        try:
            os.unlink(self.port)
        except FileNotFoundError:
            pass

    def replug(self) -> None:
        """The cable is plugged back in: the same path works again, bridge in terminal mode."""
        if self._master is None:
            self._plug()

    def inject_garbage(self, nbytes: int = 7) -> None:
        """Send ``nbytes`` random bytes before the next reply."""
        with self._lock:
            self._garbage_pending += nbytes

    # -- protocol --------------------------------------------------------------------------
    def _reset_protocol(self) -> None:
        self._state = "terminal"
        self._zeros = 0
        self._buf = bytearray()
        self._speed_index = POWER_ON_SPEED_INDEX
        self._mode = POWER_ON_MODE

    def _run(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                master = self._master
            if master is None:
                self._stop.wait(0.01)
                continue
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
            except (OSError, ValueError):
                continue
            if not ready:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:
                self._stop.wait(0.005)
                continue
            if self.mute or not data:
                continue
            with self._lock:
                self._buf += data
                reply = self._process()
                if reply and self._garbage_pending:
                    reply = self._rng.integers(0, 256, self._garbage_pending,
                                               dtype=np.uint8).tobytes() + reply
                    self._garbage_pending = 0
            if reply:
                self._write_all(master, reply)

    def _write_all(self, fd: int, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(fd, view)
            except BlockingIOError:
                select.select([], [fd], [], 0.05)
                continue
            except OSError:
                return
            view = view[n:]

    def _process(self) -> bytes:
        out = bytearray()
        buf = self._buf
        i = 0
        while i < len(buf):
            b = buf[i]
            if self._state == "terminal":
                i += 1
                if b == BBIO_RESET:
                    self._zeros += 1
                    if self._zeros >= ZEROS_TO_ENTER_BINARY:
                        self._state = "bbio"
                        out += BBIO_SIGNATURE
                else:
                    self._zeros = 0
            elif self._state == "bbio":
                i += 1
                if b == BBIO_RESET:
                    out += BBIO_SIGNATURE
                elif b == BBIO_ENTER_SPI:
                    self._state = "spi"
                    self._speed_index = POWER_ON_SPEED_INDEX
                    self._mode = POWER_ON_MODE
                    out += SPI_SIGNATURE
                elif b == BBIO_EXIT_TO_TERMINAL:
                    self._state = "terminal"
                    self._zeros = 0
                    out.append(ACK)
                else:
                    out.append(0x00)
            else:
                used = self._spi_command(buf, i, out)
                if used == 0:
                    break
                i += used
        del buf[:i]
        return bytes(out)

    def _spi_command(self, buf: bytearray, i: int, out: bytearray) -> int:
        """Execute one raw-SPI command at ``buf[i]``; bytes consumed (0 = need more)."""
        b = buf[i]
        slave = self.slave
        speed = SPI_SPEEDS_HZ.get(self._speed_index, 125e3)
        if b == BBIO_RESET:
            self._state = "bbio"
            out += BBIO_SIGNATURE
            return 1
        if b == 0x01:
            out += SPI_SIGNATURE
            return 1
        if b == SPI_CS_LOW:
            if slave is not None:
                slave.select()
            out.append(ACK)
            return 1
        if b == SPI_CS_HIGH:
            if slave is not None:
                slave.deselect()
            out.append(ACK)
            return 1
        if b in (SPI_WRITE_THEN_READ, SPI_WRITE_THEN_READ + 1):
            if len(buf) - i < 5:
                return 0
            n_w = (buf[i + 1] << 8) | buf[i + 2]
            n_r = (buf[i + 3] << 8) | buf[i + 4]
            if len(buf) - i < 5 + n_w:
                return 0
            with_cs = b == SPI_WRITE_THEN_READ
            if slave is not None and with_cs:
                slave.select()
            for k in range(n_w):
                self._xfer(buf[i + 5 + k], speed)
            read = bytes(self._xfer(0xFF, speed) for _ in range(n_r))
            if slave is not None and with_cs:
                slave.deselect()
            out.append(ACK)
            out += read
            return 5 + n_w
        if SPI_BULK <= b <= SPI_BULK + 0x0F:
            n = (b & 0x0F) + 1
            if len(buf) - i < 1 + n:
                return 0
            out.append(ACK)
            for k in range(n):
                out.append(self._xfer(buf[i + 1 + k], speed))
            self.frames += 1
            return 1 + n
        if SPI_PERIPHERALS <= b <= SPI_PERIPHERALS + 0x0F:
            out.append(ACK)
            return 1
        if SPI_SPEED <= b <= SPI_SPEED + 0x07:
            self._speed_index = b & 0x07
            out.append(ACK)
            return 1
        if SPI_CONFIG <= b <= SPI_CONFIG + 0x0F:
            self._mode = _mode_from_config(b)
            out.append(ACK)
            return 1
        out.append(0x00)
        return 1

    def _xfer(self, mosi: int, speed: float) -> int:
        if self.slave is None:
            return 0xFF
        return self.slave.exchange(mosi, mode=self._mode, speed_hz=speed) & 0xFF
