"""A recording loaded into memory: channels as gap-aware series plus metadata and warnings."""

from __future__ import annotations

from dataclasses import dataclass, field

from analysis.series import ChannelSeries


@dataclass
class Record:
    """Everything a reader got from one input.

    Attributes:
        source: the path the record was read from.
        channels: inertial channels by name (``gyro_x`` ... ``accel_z``, or ``TOPIC:gyro_x``
            when the input has several IMU topics), SI units.
        temperature: the temperature record in degC, if the input has one.
        metadata: free-form key/value facts about the recording (device, rate, ...).
        warnings: recoveries the reader made (truncated file, dropped NaN samples, ...).
    """

    source: str
    channels: dict[str, ChannelSeries]
    temperature: ChannelSeries | None = None
    metadata: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
