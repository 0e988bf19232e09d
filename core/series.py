"""Evenly sampled channel data split into gap-free segments.

The Allan and PSD estimators never bridge a gap: a record is a list of contiguous segments of
one sampling rate. This module turns sample times into such segments.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

SAMPLE_LIMIT = 1e15
"""Largest magnitude of a sample value (SI units) that the readers keep and the estimators take.

No inertial sensor reads within many decades of it (nor do raw register counts), and sums of
squares of up to 10^12 such samples stay far from float64 overflow. A value beyond it, or not
finite (NaN, infinity), is a failed reading or damaged bytes: every reader removes that sample
from its channel as a lost sample (the segment splits around it) and says how many in a
warning; the estimators raise ValueError on such a value (docs/damaged-files.md)."""

TIME_LIMIT_S = 1e12
"""Largest magnitude of a time stamp (s) that the readers take: about 31,700 years from the
epoch. A row or message whose time is beyond it, or not finite, cannot be placed in time and is
dropped with its values (a warning counts them)."""


def usable_samples(values: np.ndarray) -> np.ndarray:
    """Boolean mask of the values that are finite and within :data:`SAMPLE_LIMIT`."""
    values = np.asarray(values)
    return np.isfinite(values) & (np.abs(values) <= SAMPLE_LIMIT)


def usable_times(t_s: np.ndarray) -> np.ndarray:
    """Boolean mask of the time stamps (s) that are finite and within :data:`TIME_LIMIT_S`."""
    t_s = np.asarray(t_s)
    return np.isfinite(t_s) & (np.abs(t_s) <= TIME_LIMIT_S)


@dataclass
class ChannelSeries:
    """One channel of an evenly sampled record.

    Attributes:
        name: channel name, e.g. ``"gyro_x"``.
        units: SI units of ``values``, e.g. ``"rad/s"`` or ``"m/s^2"``.
        fs_hz: nominal sampling rate in Hz.
        values: samples (float64), all segments concatenated.
        segment_starts: index into ``values`` where each contiguous segment begins; always
            starts with 0. A gap (missing samples, time going backwards) lies before each start
            but the first.
        t0_s: time of the first sample in seconds (epoch or record-relative).
        segment_t0_s: time of each segment's first sample (s, as ``t0_s``), when the reader
            knows it (what lies in the gaps); None: each segment follows the one before
            without a gap in time (:meth:`segment_times`).
    """

    name: str
    units: str
    fs_hz: float
    values: np.ndarray
    segment_starts: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    t0_s: float = 0.0
    segment_t0_s: np.ndarray | None = None

    def segment_times(self) -> np.ndarray:
        """Time (s) of each segment's first sample: :attr:`segment_t0_s`, or counted in
        samples from ``t0_s`` when the gaps' lengths are not known."""
        if self.segment_t0_s is not None and len(self.segment_t0_s) == len(self.segment_starts):
            return np.asarray(self.segment_t0_s, dtype=np.float64)
        return self.t0_s + np.asarray(self.segment_starts, dtype=np.float64) / self.fs_hz

    def time_of(self, index: np.ndarray) -> np.ndarray:
        """Time (s) of the samples at ``index`` (nominal: each segment on its rate's grid)."""
        idx = np.asarray(index, dtype=np.int64)
        k = np.searchsorted(self.segment_starts, idx, side="right") - 1
        return self.segment_times()[k] + (idx - self.segment_starts[k]) / self.fs_hz

    def segments(self) -> list[np.ndarray]:
        """The contiguous segments as views into ``values``."""
        bounds = np.append(self.segment_starts, len(self.values))
        return [self.values[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]

    def restricted(self, ranges: list[tuple[int, int]]) -> ChannelSeries:
        """The samples in ``ranges`` (``[start, stop)`` indices, increasing, not overlapping),
        each range its own segment besides the gaps already inside it; ``t0_s`` moves to the
        first range's start (counted in samples, so gaps before it are not included)."""
        bounds = np.append(self.segment_starts, self.n_samples)
        parts, starts, old, at = [], [], [], 0
        for a, b in ranges:
            a, b = max(0, int(a)), min(self.n_samples, int(b))
            if b <= a:
                continue
            parts.append(self.values[a:b])
            inner = bounds[(bounds > a) & (bounds < b)]
            starts.extend([at] + [at + int(i) - a for i in inner])
            old.extend([a] + [int(i) for i in inner])
            at += b - a
        if not parts:
            raise ValueError(f"{self.name}: no samples in the selected ranges")
        first = next(int(a) for a, b in ranges if min(self.n_samples, int(b)) > max(0, int(a)))
        times = None if self.segment_t0_s is None else self.time_of(np.asarray(old))
        return ChannelSeries(name=self.name, units=self.units, fs_hz=self.fs_hz,
                             values=np.concatenate(parts),
                             segment_starts=np.asarray(starts, dtype=np.int64),
                             t0_s=self.t0_s + first / self.fs_hz, segment_t0_s=times)

    def windowed(self, skip_s: float = 0.0, split_s: list[float] | tuple[float, ...] = ()
                 ) -> ChannelSeries:
        """The series without its first ``skip_s`` seconds (a warm-up) and cut into separate
        segments at ``split_s`` (seconds from the first sample; a bias step). Times count
        samples (``round(t * fs_hz)``), as the diagnosis states them.

        Raises:
            ValueError: nothing left after the skip.
        """
        n = self.n_samples
        first = self._first_kept(skip_s)
        if first >= n:
            raise ValueError(f"{self.name}: --skip {skip_s:g} s leaves no samples (the channel "
                             f"has {n / self.fs_hz:.6g} s)")
        cuts = sorted({self._sample_at(t) for t in split_s if self._cuts(skip_s, t)})
        edges = [first, *cuts, n]
        if first == 0 and not cuts:
            return self
        return self.restricted(list(zip(edges[:-1], edges[1:], strict=True)))

    def idle_splits(self, skip_s: float, split_s: list[float] | tuple[float, ...]
                    ) -> list[float]:
        """The times of ``split_s`` that :meth:`windowed` leaves out: at or before the end of
        the skip, or at or beyond the last sample (they would cut nothing)."""
        return [float(t) for t in split_s if not self._cuts(skip_s, t)]

    def _first_kept(self, skip_s: float) -> int:
        """Index of the first sample after a skip of ``skip_s`` seconds."""
        return int(round(max(float(skip_s), 0.0) * self.fs_hz))

    def _sample_at(self, t_s: float) -> int:
        """Index of the sample at ``t_s`` seconds from the first one."""
        return int(round(float(t_s) * self.fs_hz))

    def _cuts(self, skip_s: float, t_s: float) -> bool:
        """Whether a split at ``t_s`` falls strictly inside the samples a skip leaves."""
        return self._first_kept(skip_s) < self._sample_at(t_s) < self.n_samples

    @property
    def n_samples(self) -> int:
        return int(len(self.values))

    @property
    def duration_s(self) -> float:
        """Sampled duration in seconds (sum over segments, gaps excluded)."""
        return self.n_samples / self.fs_hz


def channel_units(name: str) -> str:
    """SI units of a standard channel name (``gyro_*``, ``accel_*``, ``temp``)."""
    base = name.split(":")[-1]
    if base.startswith("gyro"):
        return "rad/s"
    if base.startswith("accel"):
        return "m/s^2"
    if base.startswith("temp"):
        return "degC"
    return ""
