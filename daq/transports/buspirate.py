"""Serial-to-SPI bridge: a Bus Pirate v3 in binary ("raw") SPI mode, driven through pyserial.

Every 16-bit SPI frame gets its own chip-select window (``CS low, bulk 2 bytes, CS high``), as
the ADIS16350 timing diagram asks; frames are queued back to back in one serial write and their
replies checked in one vectorised pass, so the USB round trip is paid once per batch.
"""

from __future__ import annotations

import errno
import time
from collections.abc import Callable, Sequence

import numpy as np
import serial

from imunoise.daq.errors import PermanentDeviceError, TransientDeviceError

# Bitbang-mode commands and replies (Bus Pirate firmware binIO.c / SPI.c).
BBIO_RESET = 0x00
BBIO_ENTER_SPI = 0x01
BBIO_EXIT_TO_TERMINAL = 0x0F
BBIO_SIGNATURE = b"BBIO1"
SPI_SIGNATURE = b"SPI1"
ENTER_ATTEMPTS = 20

# Raw SPI mode commands.
SPI_CS_LOW = 0x02
SPI_CS_HIGH = 0x03
SPI_WRITE_THEN_READ = 0x04
SPI_BULK = 0x10  # | (n - 1), n = 1..16 bytes, full duplex
SPI_PERIPHERALS = 0x40  # | power << 3 | pullups << 2 | aux << 1 | cs
SPI_SPEED = 0x60  # | index into SPI_SPEEDS_HZ
SPI_CONFIG = 0x80  # | push_pull << 3 | ckp << 2 | cke << 1 | smp
ACK = 0x01

# Speed index -> SCLK in Hz. Index 7 (8 MHz) shares its prescaler with 125 kHz in the
# firmware, so it is left out.
SPI_SPEEDS_HZ: dict[int, float] = {
    0: 30e3, 1: 125e3, 2: 250e3, 3: 1e6, 4: 2e6, 5: 2.6e6, 6: 4e6,
}

# SPI mode -> (CKP idle level, CKE). The PIC's CKE=1 changes data on the active-to-idle edge;
# mode 3 (idle high, sample on rising edge) therefore needs CKE=0.
SPI_MODE_BITS: dict[int, tuple[int, int]] = {0: (0, 1), 1: (0, 0), 2: (1, 1), 3: (1, 0)}

FRAME_BYTES = 5  # CS low, bulk(2), hi, lo, CS high
FRAMES_PER_WRITE = 200
# Most bytes read while looking for a mode signature (20 echoed BBIO1s plus leftovers of an
# earlier session) before the bridge counts as talking garbage.
SIGNATURE_SEARCH_LIMIT = 4096

SerialOpener = Callable[[str, int, float], serial.Serial]
"""Opens a port: ``opener(port, baudrate, timeout_s)`` -> an open :class:`serial.Serial`."""


def open_serial(port: str, baudrate: int, timeout_s: float) -> serial.Serial:
    """The port as a plain pyserial :class:`serial.Serial` with read and write timeouts."""
    return serial.Serial(port, baudrate, timeout=timeout_s, write_timeout=timeout_s)


def config_byte(mode: int, push_pull: bool = True) -> int:
    """The ``1000wxyz`` configuration byte for SPI ``mode`` (3.3 V push-pull by default)."""
    ckp, cke = SPI_MODE_BITS[mode]
    return SPI_CONFIG | (int(push_pull) << 3) | (ckp << 2) | (cke << 1)


def speed_index(max_hz: float) -> int:
    """The fastest Bus Pirate SPI speed index not above ``max_hz``."""
    ok = [i for i, hz in SPI_SPEEDS_HZ.items() if hz <= max_hz]
    if not ok:
        raise ValueError(f"no Bus Pirate SPI speed at or below {max_hz:g} Hz")
    return max(ok, key=lambda i: SPI_SPEEDS_HZ[i])


def encode_frames(words: Sequence[int] | np.ndarray) -> bytes:
    """Serial bytes for one CS-framed 16-bit transfer per word (MSB first)."""
    w = np.asarray(words, dtype=np.uint16)
    out = np.empty((w.size, FRAME_BYTES), dtype=np.uint8)
    out[:, 0] = SPI_CS_LOW
    out[:, 1] = SPI_BULK | 1
    out[:, 2] = w >> 8
    out[:, 3] = w & 0xFF
    out[:, 4] = SPI_CS_HIGH
    return out.tobytes()


def decode_frames(reply: bytes, n: int) -> np.ndarray | None:
    """MISO words from the reply to :func:`encode_frames`, or None if the acks are wrong."""
    a = np.frombuffer(reply, dtype=np.uint8)
    if a.size != n * FRAME_BYTES:
        return None
    a = a.reshape(n, FRAME_BYTES)
    if not (np.all(a[:, 0] == ACK) and np.all(a[:, 1] == ACK) and np.all(a[:, 4] == ACK)):
        return None
    return (a[:, 2].astype(np.uint16) << 8) | a[:, 3]


class BusPirateSPI:
    """A Bus Pirate in binary SPI mode on a serial port.

    Args:
        port: serial device, e.g. ``/dev/ttyUSB0``.
        baudrate: host link speed (the Bus Pirate v3 binary modes use 115200 8N1).
        timeout_s: how long to wait for a reply before declaring "no answer" (s). The
            default suits a Bus Pirate on USB, whose replies take milliseconds.
        power: switch on the Bus Pirate's own supplies (leave off when the sensor has its own).
        opener: opens the port (default :func:`open_serial`); simulators pass one whose
            timeouts follow the emulated bridge instead of the host's scheduler.
    """

    def __init__(self, port: str, *, baudrate: int = 115200, timeout_s: float = 0.5,
                 power: bool = False, opener: SerialOpener | None = None) -> None:
        self.port = port
        self.baudrate = baudrate
        self.timeout_s = timeout_s
        self.power = power
        self._opener = opener or open_serial
        self.speed_hz: float | None = None
        self.mode: int | None = None
        self._ser: serial.Serial | None = None
        self.bytes_out = 0
        self.bytes_in = 0

    # -- connection ------------------------------------------------------------------------
    def open(self) -> None:
        """Open the port, enter binary SPI mode, set CS high and outputs to a safe state."""
        self.close()
        try:
            self._ser = self._opener(self.port, self.baudrate, self.timeout_s)
        except serial.SerialException as exc:
            raise self._open_error(exc) from exc
        self._enter_binary()
        # Everything the bridge says before SPI1 answers bytes sent earlier (the echoes of the
        # extra zeros), so finding the signature leaves the reply stream in step.
        self._write(bytes([BBIO_ENTER_SPI]))
        got = self._read_until(SPI_SIGNATURE)
        if not got.endswith(SPI_SIGNATURE):
            self._resync()
            raise TransientDeviceError(f"Bus Pirate on {self.port}: enter SPI mode: expected "
                                       f"{SPI_SIGNATURE!r}, got {bytes(got[-16:])!r}")
        periph = SPI_PERIPHERALS | (int(self.power) << 3) | 0x01
        self._command(periph, what="set peripherals")
        self._command(SPI_CS_HIGH, what="raise CS")

    def _open_error(self, exc: serial.SerialException) -> Exception:
        code = getattr(exc, "errno", None)
        text = str(exc)
        if code == errno.ENOENT or "No such file" in text:
            return TransientDeviceError(f"serial port {self.port}: not found (is the Bus Pirate "
                                        "plugged in?)")
        if code == errno.EACCES or "Permission denied" in text:
            return PermanentDeviceError(f"serial port {self.port}: permission denied (add the "
                                        "user to the dialout group)")
        if code == errno.EBUSY or "busy" in text.lower():
            return TransientDeviceError(f"serial port {self.port}: busy (used by another "
                                        "program)")
        return TransientDeviceError(f"serial port {self.port}: cannot open ({text})")

    def _enter_binary(self) -> None:
        """Send twenty 0x00 and wait for ``BBIO1``.

        From the user terminal it takes twenty zeros; a bridge already in a binary mode answers
        each of them with ``BBIO1``. The extra echoes are skipped by :meth:`open`, which looks
        for the SPI signature, so no timing decides what belongs to which command.
        """
        self._drain(self._require())
        self._write(bytes([BBIO_RESET]) * ENTER_ATTEMPTS)
        got = self._read_until(BBIO_SIGNATURE)
        if got.endswith(BBIO_SIGNATURE):
            return
        if got:
            raise TransientDeviceError(f"Bus Pirate on {self.port}: garbage instead of "
                                       f"BBIO1 ({bytes(got[-16:])!r})")
        raise TransientDeviceError(f"Bus Pirate on {self.port}: no answer to binary-mode "
                                   "entry (wrong port or bridge hung)")

    def configure(self, speed_max_hz: float, mode: int = 3) -> None:
        """Set SPI clock (fastest at or below ``speed_max_hz``) and SPI ``mode``."""
        idx = speed_index(speed_max_hz)
        self._command(SPI_SPEED | idx, what="set SPI speed")
        self._command(config_byte(mode), what="set SPI mode")
        self.speed_hz = SPI_SPEEDS_HZ[idx]
        self.mode = mode

    def close(self) -> None:
        """Leave binary mode (back to the user terminal) and close the port; never raises."""
        ser, self._ser = self._ser, None
        if ser is None:
            return
        try:
            if ser.is_open:
                ser.write(bytes([SPI_CS_HIGH, BBIO_RESET, BBIO_EXIT_TO_TERMINAL]))
                ser.flush()
        except (serial.SerialException, OSError):
            pass
        try:
            ser.close()
        except (serial.SerialException, OSError):
            pass

    @property
    def is_open(self) -> bool:
        return self._ser is not None

    # -- transfers -------------------------------------------------------------------------
    def transfer_frames(self, words: Sequence[int] | np.ndarray) -> np.ndarray:
        """Clock each 16-bit word out in its own CS window; return the MISO words (uint16)."""
        words = np.asarray(words, dtype=np.uint16)
        out = np.empty(words.size, dtype=np.uint16)
        for a in range(0, words.size, FRAMES_PER_WRITE):
            chunk = words[a:a + FRAMES_PER_WRITE]
            self._write(encode_frames(chunk))
            reply = self._read_exact(chunk.size * FRAME_BYTES, what="SPI frames")
            decoded = decode_frames(reply, chunk.size)
            if decoded is None:
                self._resync()
                raise TransientDeviceError(f"Bus Pirate on {self.port}: garbage in SPI reply "
                                           f"({reply[:10].hex(' ')} ...)")
            out[a:a + chunk.size] = decoded
        return out

    def write_only(self, word: int) -> None:
        """One 16-bit frame with CS handled by the firmware (write-then-read, read count 0)."""
        self._write(bytes([SPI_WRITE_THEN_READ, 0x00, 0x02, 0x00, 0x00,
                           (word >> 8) & 0xFF, word & 0xFF]))
        reply = self._read_exact(1, what="write-then-read")
        if reply != bytes([ACK]):
            self._resync()
            raise TransientDeviceError(f"Bus Pirate on {self.port}: write-then-read refused "
                                       f"({reply.hex()})")

    # -- low level -------------------------------------------------------------------------
    def _require(self) -> serial.Serial:
        if self._ser is None:
            raise TransientDeviceError(f"serial port {self.port}: not open")
        return self._ser

    def _write(self, data: bytes) -> None:
        ser = self._require()
        try:
            ser.write(data)
        except serial.SerialTimeoutException as exc:
            raise TransientDeviceError(f"serial port {self.port}: write timed out") from exc
        except (serial.SerialException, OSError) as exc:
            raise TransientDeviceError(f"serial port {self.port}: lost ({exc})") from exc
        self.bytes_out += len(data)

    def _read_exact(self, n: int, *, what: str) -> bytes:
        ser = self._require()
        try:
            data = ser.read(n)
        except (serial.SerialException, OSError) as exc:
            raise TransientDeviceError(f"serial port {self.port}: lost ({exc})") from exc
        self.bytes_in += len(data)
        if len(data) < n:
            raise TransientDeviceError(f"Bus Pirate on {self.port}: no answer ({what}: got "
                                       f"{len(data)} of {n} bytes in {self.timeout_s:g} s)")
        return data

    def _read_until(self, marker: bytes) -> bytearray:
        """Bytes up to and including ``marker``; fewer (without it) after a silence of
        ``timeout_s`` or :data:`SIGNATURE_SEARCH_LIMIT` bytes."""
        ser = self._require()
        got = bytearray()
        while not got.endswith(marker) and len(got) < SIGNATURE_SEARCH_LIMIT:
            try:
                chunk = ser.read(1)
            except (serial.SerialException, OSError) as exc:
                raise TransientDeviceError(f"serial port {self.port}: lost ({exc})") from exc
            if not chunk:
                break
            got += chunk
        self.bytes_in += len(got)
        return got

    def _drain(self, ser: serial.Serial) -> None:
        try:
            ser.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise TransientDeviceError(f"serial port {self.port}: lost ({exc})") from exc

    def _resync(self) -> None:
        """After garbage: wait for the line to go quiet and drop whatever arrived."""
        ser = self._ser
        if ser is None:
            return
        try:
            time.sleep(0.02)
            ser.reset_input_buffer()
        except (serial.SerialException, OSError):
            pass

    def _command(self, byte: int, *, expect: bytes = bytes([ACK]), what: str) -> None:
        self._write(bytes([byte]))
        reply = self._read_exact(len(expect), what=what)
        if reply != expect:
            self._resync()
            raise TransientDeviceError(f"Bus Pirate on {self.port}: {what}: expected "
                                       f"{expect!r}, got {reply!r}")
