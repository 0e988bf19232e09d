"""Device errors, split by what the acquisition loop should do about them."""

from __future__ import annotations

from imunoise.core.errors import ImunoiseError, InputError


class DeviceError(ImunoiseError):
    """A device or its transport failed; the message names the port or bus and the reason."""


class TransientDeviceError(DeviceError):
    """Worth retrying: timeout, garbage on the line, NACK burst, unplugged cable, stuck flag."""


class PermanentDeviceError(DeviceError):
    """Retrying will not help: wrong chip, no permission, bad configuration."""


class AcquisitionFailed(DeviceError):
    """The acquisition loop gave up; ``str()`` is the reason shown to the user."""


class ReadError(InputError):
    """An input file cannot be read: missing, unsupported, empty or malformed. The base of
    every reader's error (MCAP layout, rosbag2, ROS 1); one-line message."""


def quoted(text: str | bytes, limit: int = 40) -> str:
    """User data for an error message: quoted, on one line, cut to ``limit`` characters."""
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    cut = len(text) > limit
    shown = repr(text[:limit])
    return f"{shown}... ({len(text)} characters)" if cut else shown
