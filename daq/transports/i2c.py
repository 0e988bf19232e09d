"""I2C register access with smbus2: bounded retries with backoff and errors that name the bus.

The bus object is a real :class:`smbus2.SMBus` (for simulators, one whose ioctl calls land in
a chip model, so smbus2's own message marshalling always runs).
"""

from __future__ import annotations

import errno
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import smbus2

from imunoise.daq.clock import Clock, RealClock
from imunoise.daq.errors import PermanentDeviceError, TransientDeviceError

T = TypeVar("T")
BLOCK_MAX = 32  # smbus2 / Linux SMBus block limit

# errno -> what it means on an I2C adapter.
I2C_ERRNO_TEXT: dict[int, str] = {
    errno.EREMOTEIO: "no answer (NACK)",
    errno.ENXIO: "no answer (NACK)",
    errno.EIO: "I/O error",
    errno.ETIMEDOUT: "bus timeout",
    errno.EAGAIN: "arbitration lost",
    errno.EBUSY: "bus busy",
    errno.ENODEV: "adapter gone",
}


def _bus_path(bus: int | str) -> str:
    return f"/dev/i2c-{bus}" if isinstance(bus, int) else str(bus)


class I2CBus:
    """One I2C adapter.

    Args:
        bus: bus number (``/dev/i2c-N``) or device path.
        retries: extra tries per transaction after a NACK or I/O error.
        backoff_s: wait before the first retry; doubled for each further one.
        clock: time source for the backoff waits.
        opener: makes the smbus2 bus object (simulators inject theirs here).
        label: how messages name the bus (default ``I2C bus N (/dev/i2c-N)``).
    """

    def __init__(self, bus: int | str, *, retries: int = 3, backoff_s: float = 0.001,
                 clock: Clock | None = None,
                 opener: Callable[[int | str], smbus2.SMBus] | None = None,
                 label: str | None = None) -> None:
        self.bus = bus
        self.label = label
        self.retries = retries
        self.backoff_s = backoff_s
        self.clock = clock or RealClock()
        self._opener = opener or (lambda b: smbus2.SMBus(b))
        self._smbus: smbus2.SMBus | None = None
        self.transactions = 0
        self.retried = 0

    @property
    def name(self) -> str:
        return self.label or f"I2C bus {self.bus} ({_bus_path(self.bus)})"

    def open(self) -> None:
        if self._smbus is not None:
            return
        try:
            self._smbus = self._opener(self.bus)
        except FileNotFoundError as exc:
            raise TransientDeviceError(f"{self.name}: not found (load i2c-dev, check the bus "
                                       "number with i2cdetect -l)") from exc
        except PermissionError as exc:
            raise PermanentDeviceError(f"{self.name}: permission denied (add the user to the "
                                       "i2c group)") from exc
        except OSError as exc:
            raise TransientDeviceError(f"{self.name}: cannot open ({exc})") from exc

    def close(self) -> None:
        bus, self._smbus = self._smbus, None
        if bus is not None:
            try:
                bus.close()
            except OSError:
                pass

    def _do(self, addr: int, what: str, fn: Callable[[smbus2.SMBus], T]) -> T:
        if self._smbus is None:
            self.open()
        assert self._smbus is not None
        delay = self.backoff_s
        for attempt in range(self.retries + 1):
            try:
                self.transactions += 1
                return fn(self._smbus)
            except OSError as exc:
                reason = I2C_ERRNO_TEXT.get(exc.errno or 0, f"error {exc}")
                if attempt == self.retries:
                    raise TransientDeviceError(
                        f"{self.name}, device 0x{addr:02X}: {reason} ({what}, "
                        f"{self.retries + 1} tries)") from exc
                self.retried += 1
                self.clock.sleep(delay)
                delay *= 2
        raise AssertionError("unreachable")

    def read_u8(self, addr: int, reg: int) -> int:
        return self._do(addr, f"read 0x{reg:02X}", lambda b: b.read_byte_data(addr, reg))

    def write_u8(self, addr: int, reg: int, value: int) -> None:
        self._do(addr, f"write 0x{reg:02X}",
                 lambda b: b.write_byte_data(addr, reg, value & 0xFF))

    def read_block(self, addr: int, reg: int, length: int) -> list[int]:
        """``length`` bytes from ``reg`` on in one transaction (auto-increment)."""
        if not 1 <= length <= BLOCK_MAX:
            raise ValueError(f"I2C block length {length}: must be 1..{BLOCK_MAX}")
        return self._do(addr, f"read {length} bytes at 0x{reg:02X}",
                        lambda b: b.read_i2c_block_data(addr, reg, length))

    def write_block(self, addr: int, reg: int, data: Sequence[int]) -> None:
        self._do(addr, f"write {len(data)} bytes at 0x{reg:02X}",
                 lambda b: b.write_i2c_block_data(addr, reg, list(data)))

    def __enter__(self) -> I2CBus:
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
