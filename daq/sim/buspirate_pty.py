"""A Bus Pirate (binary SPI mode) emulated on a pseudo-terminal, in a thread.

The real driver opens the pty's path with the real pyserial and speaks the real byte protocol;
behind the emulated bridge sits a register-level SPI chip model (:class:`SpiSlave`). Faults
can be switched on at any time: garbage bytes on the line, a bridge that stops answering, and
unplug/replug of the tty (the path disappears and comes back, as a USB adapter would).

The emulator runs in a thread, so on a busy host it may get the CPU only long after the
driver's bytes arrive. :meth:`BusPirateEmulator.serial_opener` therefore hands the driver a
pyserial port (:class:`EmulatedBridgePort`) whose reply timeouts run on the simulation's clock:
a read waits for as long as the emulator still has bytes to process or to deliver, and times
out (sleeping ``timeout_s`` on the shared clock) only once the bridge has read everything sent
to it and said all it will. A fault then costs the same, and is counted the same, however
loaded the host is.
"""

from __future__ import annotations

import os
import select
import tempfile
import threading
import time
import tty
from collections.abc import Callable
from typing import Protocol

import numpy as np
import serial

from imunoise.daq.clock import Clock
from imunoise.daq.transports.buspirate import (
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
# Longest a read of an emulated port waits for a busy emulator thread (s, wall clock); only a
# hung emulator ever uses it up.
WALL_PATIENCE_S = 10.0


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


class ChipClock:
    """The clock a chip behind the emulated bridge reads: while the emulator acts on the
    host's bytes, the time the host sent them.

    A USB bridge clocks the bytes out about a millisecond after the host sends them; the
    emulator thread on a busy host may get to them much later, which the chip must not see
    (it would latch a later sample than the host asked for).
    """

    def __init__(self, clock: Clock) -> None:
        self.clock = clock
        self._pinned: float | None = None

    def now(self) -> float:
        pinned = self._pinned
        return self.clock.now() if pinned is None else pinned

    def pin(self, t: float | None) -> None:
        self._pinned = t


class BusPirateEmulator:
    """Bus Pirate v3 binary SPI protocol on a pty whose path is :attr:`port`.

    Args:
        slave: the chip on the SPI bus, or None for an empty bus (MISO reads 0xFF).
        seed: seed for the garbage fault's random bytes.
        chip_clock: the chip's clock, pinned to the host's time of sending while the
            emulator acts on the host's bytes (with ports from :meth:`serial_opener`).
    """

    def __init__(self, slave: SpiSlave | None, *, seed: int = 0,
                 chip_clock: ChipClock | None = None) -> None:
        self.slave = slave
        self.chip_clock = chip_clock
        self._host_write_time: float | None = None
        self._dir = tempfile.mkdtemp(prefix="imunoise-bp-")
        self.port = os.path.join(self._dir, "ttyBP0")
        self._rng = np.random.default_rng(seed)
        self._lock = threading.Lock()
        self._link = threading.Condition(self._lock)
        self._stop = threading.Event()
        self._master: int | None = None
        self._slave_fd: int | None = None
        self._thread: threading.Thread | None = None
        # Fault switches.
        self.mute = False
        self._garbage_pending = 0
        self._reset_protocol()
        self.frames = 0
        # Byte accounting of the current pty (see EmulatedBridgePort).
        self.generation = 0
        self._host_sent = 0  # bytes the host wrote
        self._taken = 0  # of those, bytes the emulator has read and acted on
        self._replied = 0  # bytes the emulator wrote back
        self._host_got = 0  # of those, bytes the host has read or discarded

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
            self._new_generation()
        tmp = self.port + ".new"
        os.symlink(os.ttyname(slave_fd), tmp)
        os.replace(tmp, self.port)

    def _unplug_fds(self) -> None:
        with self._lock:
            fds = (self._master, self._slave_fd)
            self._master = self._slave_fd = None
            self._new_generation()
        for fd in fds:
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass

    # -- byte accounting for EmulatedBridgePort -----------------------------------------------
    def _new_generation(self) -> None:
        """A pty was created or removed (lock held): earlier accounting no longer applies."""
        self.generation += 1
        self._host_sent = self._taken = self._replied = self._host_got = 0
        self._link.notify_all()

    def serial_opener(self, clock: Clock | None = None
                      ) -> Callable[[str, int, float], serial.Serial]:
        """A port opener for :class:`~imunoise.daq.transports.buspirate.BusPirateSPI` whose reply
        timeouts pass on ``clock`` (the host clock when None)."""
        def opener(port: str, baudrate: int, timeout_s: float) -> serial.Serial:
            return EmulatedBridgePort(self, port, baudrate, timeout_s, clock)
        return opener

    def host_writing(self, t: float | None) -> None:
        """The host is about to send bytes at time ``t`` (of the chip clock's source)."""
        with self._link:
            self._host_write_time = t

    def host_wrote(self, generation: int, n: int) -> None:
        with self._link:
            if generation == self.generation:
                self._host_sent += n
            self._link.notify_all()

    def host_took(self, generation: int, n: int) -> None:
        with self._link:
            if generation == self.generation:
                self._host_got += n

    def await_output(self, generation: int, deadline: float) -> tuple[int, bool] | None:
        """Wait until the bridge has bytes for the host or has acted on all it was sent.

        Returns (bytes sent to the host and not yet taken, whether the bridge has acted on
        everything), or None when the pty of ``generation`` is gone.
        """
        def state() -> tuple[int, bool] | None:
            if generation != self.generation or self._master is None:
                return None
            return self._replied - self._host_got, self._taken >= self._host_sent

        with self._link:
            while True:
                st = state()
                if st is None or st[0] > 0 or st[1]:
                    return st
                left = deadline - time.monotonic()
                if left <= 0:
                    return st
                self._link.wait(left)

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
                master, generation = self._master, self.generation
            if master is None:
                self._stop.wait(0.01)
                continue
            try:
                ready, _, _ = select.select([master], [], [], 0.05)
            except (OSError, ValueError):
                continue
            if not ready:
                continue
            reply = b""
            with self._lock:
                # A replug may have reused the fd number: read only from the pty selected on,
                # and never while unplug closes it.
                if self.generation != generation:
                    continue
                try:
                    data = os.read(master, 4096)
                except OSError:
                    data = None
                if data and not self.mute:
                    self._buf += data
                    if self.chip_clock is not None:
                        self.chip_clock.pin(self._host_write_time)
                    try:
                        reply = self._process()
                    finally:
                        if self.chip_clock is not None:
                            self.chip_clock.pin(None)
                    if reply and self._garbage_pending:
                        reply = self._rng.integers(0, 256, self._garbage_pending,
                                                   dtype=np.uint8).tobytes() + reply
                        self._garbage_pending = 0
            if data is None:
                self._stop.wait(0.005)
                continue
            if not data:
                continue
            if reply:
                self._write_all(master, reply, generation)
            with self._link:
                if self.generation == generation:
                    self._taken += len(data)
                self._link.notify_all()

    def _write_all(self, fd: int, data: bytes, generation: int) -> None:
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
            with self._link:  # counted as it goes: a long reply may wait for the host to read
                if self.generation == generation:
                    self._replied += n
                self._link.notify_all()

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
        speed = SPI_SPEEDS_HZ.get(self._speed_index, 125e3)
        if b in (SPI_WRITE_THEN_READ, SPI_WRITE_THEN_READ + 1):
            return self._write_then_read(buf, i, out, speed)
        if SPI_BULK <= b <= SPI_BULK + 0x0F:
            n = (b & 0x0F) + 1
            if len(buf) - i < 1 + n:
                return 0
            out.append(ACK)
            for k in range(n):
                out.append(self._xfer(buf[i + 1 + k], speed))
            self.frames += 1
            return 1 + n
        self._one_byte_command(b, out)
        return 1

    def _one_byte_command(self, b: int, out: bytearray) -> None:
        """The raw-SPI commands of one byte: reset, mode string, chip select, settings."""
        slave = self.slave
        if b == BBIO_RESET:
            self._state = "bbio"
            out += BBIO_SIGNATURE
        elif b == 0x01:
            out += SPI_SIGNATURE
        elif b == SPI_CS_LOW:
            if slave is not None:
                slave.select()
            out.append(ACK)
        elif b == SPI_CS_HIGH:
            if slave is not None:
                slave.deselect()
            out.append(ACK)
        elif SPI_PERIPHERALS <= b <= SPI_PERIPHERALS + 0x0F:
            out.append(ACK)
        elif SPI_SPEED <= b <= SPI_SPEED + 0x07:
            self._speed_index = b & 0x07
            out.append(ACK)
        elif SPI_CONFIG <= b <= SPI_CONFIG + 0x0F:
            self._mode = _mode_from_config(b)
            out.append(ACK)
        else:
            out.append(0x00)

    def _write_then_read(self, buf: bytearray, i: int, out: bytearray, speed: float) -> int:
        """The write-then-read command (with or without chip select); bytes consumed."""
        if len(buf) - i < 5:
            return 0
        n_w = (buf[i + 1] << 8) | buf[i + 2]
        n_r = (buf[i + 3] << 8) | buf[i + 4]
        if len(buf) - i < 5 + n_w:
            return 0
        with_cs = buf[i] == SPI_WRITE_THEN_READ
        if self.slave is not None and with_cs:
            self.slave.select()
        for k in range(n_w):
            self._xfer(buf[i + 5 + k], speed)
        read = bytes(self._xfer(0xFF, speed) for _ in range(n_r))
        if self.slave is not None and with_cs:
            self.slave.deselect()
        out.append(ACK)
        out += read
        return 5 + n_w

    def _xfer(self, mosi: int, speed: float) -> int:
        if self.slave is None:
            return 0xFF
        return self.slave.exchange(mosi, mode=self._mode, speed_hz=speed) & 0xFF


class EmulatedBridgePort(serial.Serial):
    """A real pyserial port on the emulator's pty whose timeouts follow the emulated bridge.

    Reads and writes go through pyserial unchanged; what differs is when a read gives up.
    It waits (up to :data:`WALL_PATIENCE_S` of wall time) while the emulator still has bytes
    to read or replies on their way, and returns short only when the bridge has acted on
    everything and has no more to say, after sleeping ``timeout_s`` on ``clock``: the time
    the host would have waited for a silent bridge. Flushing the input likewise waits for the
    bridge to finish, as a real flush after a quiet line would.
    """

    def __init__(self, emulator: BusPirateEmulator, port: str, baudrate: int,
                 timeout_s: float, clock: Clock | None) -> None:
        self._bridge = emulator
        self._bridge_timeout_s = float(timeout_s)
        self._bridge_clock = clock
        self._generation = emulator.generation
        super().__init__(port, baudrate, timeout=WALL_PATIENCE_S, write_timeout=WALL_PATIENCE_S)

    def open(self) -> None:
        self._generation = self._bridge.generation
        super().open()
        self._reset_input_buffer()  # pyserial's own flush in open() is skipped below

    def write(self, data: bytes) -> int | None:
        clock = self._bridge_clock
        self._bridge.host_writing(clock.now() if clock is not None else None)
        n = super().write(data)
        self._bridge.host_wrote(self._generation, len(data) if n is None else n)
        return n

    def read(self, size: int = 1) -> bytes:
        out = bytearray()
        deadline = time.monotonic() + WALL_PATIENCE_S
        while len(out) < size:
            st = self._bridge.await_output(self._generation, deadline)
            if st is None:  # unplugged: let pyserial meet the dead tty
                out += super().read(size - len(out))
                break
            pending, _ = st
            if pending == 0:
                self._silence()
                break
            chunk = super().read(min(pending, size - len(out)))
            self._bridge.host_took(self._generation, len(chunk))
            out += chunk
            if not chunk:
                break
        return bytes(out)

    def _reset_input_buffer(self) -> None:
        if not self.is_open:
            return
        deadline = time.monotonic() + WALL_PATIENCE_S
        while True:
            st = self._bridge.await_output(self._generation, deadline)
            if st is None:
                super()._reset_input_buffer()
                return
            pending, done = st
            if pending == 0 and (done or time.monotonic() >= deadline):
                return
            if pending:
                chunk = super().read(pending)
                self._bridge.host_took(self._generation, len(chunk))
                if not chunk:
                    return

    def _silence(self) -> None:
        """The host waits out its timeout for a bridge that has nothing to say."""
        if self._bridge_clock is not None:
            self._bridge_clock.sleep(self._bridge_timeout_s)
        else:
            time.sleep(self._bridge_timeout_s)
