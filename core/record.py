"""A recording as the analysis sees it: per-channel series plus temperature and metadata."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from imunoise.core.errors import InputError
from imunoise.core.series import ChannelSeries

TEMPERATURE_KEY = "temp"


class ChannelSelectionError(InputError):
    """A channel selector names no channel of the record (the message lists the valid ones)."""


@dataclass
class Record:
    """Everything read from one input file.

    Attributes:
        source: where it came from (path as given).
        channels: IMU channels in SI units, keyed ``gyro_x`` .. ``accel_z``, or ``TOPIC:gyro_x``
            when a file has several IMU topics.
        temperature: the temperature series (degC) on its own time base and rate, if any.
        metadata: free-form facts about the source (format, device, columns ...).
        warnings: one-line notes about what was repaired while reading (gaps, NaN, a truncated
            last line ...), for the user to see.
        facts: JSON-ready findings of steps applied after reading (e.g. ``motion``: where the
            sensor moved and which stretches are analysed).
    """

    source: str
    channels: dict[str, ChannelSeries]
    temperature: ChannelSeries | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    facts: dict[str, Any] = field(default_factory=dict)

    def valid_selectors(self) -> list[str]:
        """Channel keys a selector may name, temperature last."""
        keys = list(self.channels)
        if self.temperature is not None:
            keys.append(TEMPERATURE_KEY)
        return keys

    def series(self, key: str) -> ChannelSeries:
        """The series of a resolved key (``temp`` is the temperature)."""
        if key == TEMPERATURE_KEY and self.temperature is not None:
            return self.temperature
        return self.channels[key]


def select_channels(record: Record, sels: Sequence[str]) -> list[str]:
    """Resolve channel selectors to keys of ``record``, in the order given, without repeats.

    No selector means every IMU channel. A bare name such as ``gyro_x`` also matches
    ``TOPIC:gyro_x`` when exactly one topic has it.

    Raises:
        ChannelSelectionError: unknown or ambiguous selector; the message lists valid channels.
    """
    if not sels:
        return list(record.channels)
    valid = record.valid_selectors()
    out: list[str] = []
    for sel in sels:
        sel = sel.strip()
        if sel in valid:
            key = sel
        else:
            matches = [k for k in valid if k.split(":")[-1] == sel]
            if len(matches) > 1:
                raise ChannelSelectionError(
                    f"channel {sel!r} is ambiguous: use one of {', '.join(matches)}")
            if not matches:
                raise ChannelSelectionError(
                    f"unknown channel {sel!r}; valid channels: {', '.join(valid) or '(none)'}")
            key = matches[0]
        if key not in out:
            out.append(key)
    return out
