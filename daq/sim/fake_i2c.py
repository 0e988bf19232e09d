"""Simulated I2C adapter beneath the real smbus2.

:class:`SimulatedSMBus` is a :class:`smbus2.SMBus` whose file descriptor belongs to a
:class:`SimulatedI2CAdapter`: smbus2 builds its ``i2c_smbus_ioctl_data`` / ``i2c_rdwr`` ctypes
structures exactly as on hardware and calls ``ioctl``; the call lands here and is played out
as bytes on the wire to the chip models (register pointer write, then reads with
auto-increment). Fault switches reproduce NACK and I/O-error bursts and missing chips.
Transfers also cost bus time: on a virtual clock each transaction advances it by its bit count
at the bus speed, so a simulated 400 kHz bus is as slow as a real one.
"""

from __future__ import annotations

import ctypes
import errno
import os
import threading
from typing import Protocol

import smbus2
import smbus2.smbus2 as smb

from imunoise.daq.clock import Clock

I2C_FUNCS_SUPPORTED = 0x0EFF0001  # I2C, SMBus byte/word/block, I2C block
BITS_PER_BYTE = 9  # 8 data bits and the acknowledge
BITS_START_STOP = 2


class I2CChip(Protocol):
    """A chip as seen from the wire: writes set the pointer and data, reads auto-increment."""

    def i2c_write(self, data: bytes) -> None: ...

    def i2c_read(self, n: int) -> bytes: ...


_adapters: dict[int, SimulatedI2CAdapter] = {}
_real_ioctl = smb.ioctl
_install_lock = threading.Lock()


def _dispatch_ioctl(fd: int, request: int, arg: object = 0, *rest: object) -> object:
    adapter = _adapters.get(fd)
    if adapter is None:
        return _real_ioctl(fd, request, arg, *rest)
    return adapter.ioctl(request, arg)


def _install() -> None:
    with _install_lock:
        if smb.ioctl is not _dispatch_ioctl:
            smb.ioctl = _dispatch_ioctl


class SimulatedI2CAdapter:
    """An I2C adapter with chip models at 7-bit addresses.

    Args:
        chips: address -> chip model.
        clock: advanced by the bus time of each transaction when it is virtual.
        bus_hz: SCL frequency used for that bus time (400 kHz fast mode by default).
    """

    def __init__(self, chips: dict[int, I2CChip], *, clock: Clock | None = None,
                 bus_hz: float = 400e3) -> None:
        self.chips = dict(chips)
        self.clock = clock
        self.bus_hz = bus_hz
        self.address: int | None = None
        self.bits = 0
        self.transactions = 0
        self._nack_left = 0
        self._eio_left = 0
        self.present = True
        _install()

    # -- faults ----------------------------------------------------------------------------
    def nack_burst(self, n: int) -> None:
        """The next ``n`` transactions are not acknowledged (EREMOTEIO)."""
        self._nack_left += n

    def io_error_burst(self, n: int) -> None:
        """The next ``n`` transactions fail with EIO (bus glitch)."""
        self._eio_left += n

    # -- smbus2 side -----------------------------------------------------------------------
    def open_bus(self, bus: int | str = 0) -> SimulatedSMBus:
        return SimulatedSMBus(self)

    def ioctl(self, request: int, arg: object) -> int:
        # ``arg`` is what the kernel's ioctl takes for ``request``: an address (int), a
        # ctypes word or an smbus2 message structure; each branch knows which, mypy cannot
        if request in (smb.I2C_SLAVE, smb.I2C_SLAVE_FORCE):
            self.address = int(arg)  # type: ignore[call-overload]
            return 0
        if request == smb.I2C_FUNCS:
            arg.value = I2C_FUNCS_SUPPORTED  # type: ignore[attr-defined]
            return 0
        if request == smb.I2C_PEC:
            return 0
        if request == smb.I2C_SMBUS:
            self._smbus(arg)  # type: ignore[arg-type]
            return 0
        if request == smb.I2C_RDWR:
            self._rdwr(arg)  # type: ignore[arg-type]
            return 0
        raise OSError(errno.ENOTTY, "inappropriate ioctl for device")

    def _chip(self, addr: int | None, nbytes: int) -> I2CChip:
        self.transactions += 1
        self.bits += BITS_START_STOP + BITS_PER_BYTE * (nbytes + 1)
        if self.clock is not None and not self.clock.realtime:
            self.clock.advance((BITS_START_STOP + BITS_PER_BYTE * (nbytes + 1)) / self.bus_hz)
        if self._eio_left > 0:
            self._eio_left -= 1
            raise OSError(errno.EIO, os.strerror(errno.EIO))
        if self._nack_left > 0 or not self.present or addr not in self.chips:
            self._nack_left = max(0, self._nack_left - 1)
            raise OSError(errno.EREMOTEIO, os.strerror(errno.EREMOTEIO))
        return self.chips[addr]

    def _smbus(self, msg: smb.i2c_smbus_ioctl_data) -> None:
        data = msg.data.contents
        size, cmd, rw = msg.size, msg.command, msg.read_write
        if size == smb.I2C_SMBUS_QUICK:
            self._chip(self.address, 0)
            return
        if size == smb.I2C_SMBUS_BYTE:
            chip = self._chip(self.address, 1)
            if rw == smb.I2C_SMBUS_READ:
                data.byte = chip.i2c_read(1)[0]
            else:
                chip.i2c_write(bytes([cmd]))
            return
        if size == smb.I2C_SMBUS_BYTE_DATA:
            chip = self._chip(self.address, 2 + (rw == smb.I2C_SMBUS_READ))
            if rw == smb.I2C_SMBUS_READ:
                chip.i2c_write(bytes([cmd]))
                data.byte = chip.i2c_read(1)[0]
            else:
                chip.i2c_write(bytes([cmd, data.byte]))
            return
        if size == smb.I2C_SMBUS_WORD_DATA:
            chip = self._chip(self.address, 3 + (rw == smb.I2C_SMBUS_READ))
            if rw == smb.I2C_SMBUS_READ:
                chip.i2c_write(bytes([cmd]))
                lo, hi = chip.i2c_read(2)
                data.word = lo | (hi << 8)
            else:
                chip.i2c_write(bytes([cmd, data.word & 0xFF, data.word >> 8]))
            return
        if size == smb.I2C_SMBUS_I2C_BLOCK_DATA:
            if rw == smb.I2C_SMBUS_READ:
                n = data.byte
                chip = self._chip(self.address, 2 + n)
                chip.i2c_write(bytes([cmd]))
                got = chip.i2c_read(n)
                data.block[0] = n
                data.block[1:n + 1] = list(got)
            else:
                n = data.block[0]
                chip = self._chip(self.address, 1 + n)
                chip.i2c_write(bytes([cmd]) + bytes(data.block[1:n + 1]))
            return
        raise OSError(errno.EOPNOTSUPP, f"SMBus transaction size {size} not supported")

    def _rdwr(self, ioctl_data: smb.i2c_rdwr_ioctl_data) -> None:
        for i in range(ioctl_data.nmsgs):
            m = ioctl_data.msgs[i]
            chip = self._chip(m.addr, m.len)
            if m.flags & smb.I2C_M_RD:
                got = chip.i2c_read(m.len)
                ctypes.memmove(m.buf, got, m.len)
            else:
                chip.i2c_write(ctypes.string_at(m.buf, m.len))


class SimulatedSMBus(smbus2.SMBus):
    """The real smbus2.SMBus, opened on a simulated adapter instead of ``/dev/i2c-N``."""

    def __init__(self, adapter: SimulatedI2CAdapter) -> None:
        self._adapter = adapter
        super().__init__(None)
        self.fd = os.open(os.devnull, os.O_RDWR)
        _adapters[self.fd] = adapter
        self.funcs = self._get_funcs()

    def close(self) -> None:
        if self.fd:
            _adapters.pop(self.fd, None)
        super().close()
