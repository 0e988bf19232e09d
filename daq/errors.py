"""Device errors, split by what the acquisition loop should do about them."""

from __future__ import annotations

from core.errors import ImunoiseError


class DeviceError(ImunoiseError):
    """A device or its transport failed; the message names the port or bus and the reason."""


class TransientDeviceError(DeviceError):
    """Worth retrying: timeout, garbage on the line, NACK burst, unplugged cable, stuck flag."""


class PermanentDeviceError(DeviceError):
    """Retrying will not help: wrong chip, no permission, bad configuration."""


class AcquisitionFailed(DeviceError):
    """The acquisition loop gave up; ``str()`` is the reason shown to the user."""
