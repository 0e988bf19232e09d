"""The unit of data between acquisition, recorder, readers and analyzer: a block of samples."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class SampleBlock:
    """Consecutive samples of one stream (one device topic).

    Attributes:
        stream: stream name, e.g. ``"/adis16350/imu"`` or ``"/adis16350/temperature"``.
        t: sample times in seconds (float64), the sensor's time base (``header.stamp``).
        channels: SI values per channel name (``gyro_x`` ... ``accel_z`` in rad/s and m/s^2,
            ``temp`` in degC), each float64 of the same length as ``t``.
        raw: raw register counts per channel (int), when the source has them.
        gap_before: samples known to be missing just before this block (0: contiguous with the
            previous block of the stream; -1: unknown, treat as a new segment).
        fs_hz: nominal sampling rate of the stream in Hz.
    """

    stream: str
    t: np.ndarray
    channels: dict[str, np.ndarray]
    fs_hz: float
    raw: dict[str, np.ndarray] = field(default_factory=dict)
    gap_before: int = 0

    def __len__(self) -> int:
        return int(len(self.t))
