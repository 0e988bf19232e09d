"""Live cross-channel coherence: the Welch cross-spectral matrix of each stream's IMU channels,
fed block by block by the service, published as the ``coherence`` document of
:mod:`imunoise.analysis.coherence` (pairs, log-frequency points, exact intervals, threshold).

Channels of one stream share its time base; the temperature, a stream of its own at another
rate, is not included live (``analyze`` interpolates it onto the IMU's time base).
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from imunoise.analysis.coherence import CrossSpectralAccumulator, log_coherence
from imunoise.core.series import channel_units

SEGMENT_S = 10.0
"""Welch segment length in seconds (rounded to a power of two of samples): 0.1 Hz resolution
from 0.2 Hz up."""

MIN_SEGMENTS = 4
"""Segments needed before a coherence is published."""


def _nperseg(fs_hz: float, seconds: float) -> int:
    n = max(int(fs_hz * seconds), 64)
    return int(min(1 << int(round(math.log2(n))), 1 << 15))


class LiveCoherence:
    """Coherence of every pair of a stream's gyro and accelerometer channels, updated live.

    Args:
        segment_s: Welch segment length in seconds.
        points_per_decade: log-frequency points per decade of the published document.
    """

    def __init__(self, segment_s: float = SEGMENT_S, points_per_decade: float = 10.0) -> None:
        self.segment_s = float(segment_s)
        self.points_per_decade = float(points_per_decade)
        self._lock = threading.Lock()
        self._acc: dict[str, CrossSpectralAccumulator] = {}
        self._cache: dict[str, tuple[int, dict[str, Any]]] = {}

    def update(self, block: Any) -> None:
        """Add a block (``stream``, ``channels``, ``fs_hz``, ``gap_before``)."""
        names = [n for n in block.channels if channel_units(n) in ("rad/s", "m/s^2")]
        if len(names) < 2:
            return
        with self._lock:
            acc = self._acc.get(block.stream)
            if acc is None or list(acc.channels) != names:
                acc = CrossSpectralAccumulator(names, block.fs_hz,
                                               _nperseg(block.fs_hz, self.segment_s))
                self._acc[block.stream] = acc
            elif getattr(block, "gap_before", 0) != 0:
                acc.new_segment()
            x = np.column_stack([np.asarray(block.channels[n], dtype=np.float64)
                                 for n in names])
            finite = np.all(np.isfinite(x), axis=1)
            if not np.all(finite):  # a bad sample is a gap
                acc.new_segment()
                x = x[finite]
            if len(x):
                acc.add(x)

    @property
    def streams(self) -> list[str]:
        with self._lock:
            return list(self._acc)

    def document(self, stream: str | None = None) -> dict[str, Any]:
        """The coherence document of ``stream`` (default: the first), or ``{"ready": False,
        "reason": ...}`` until enough segments have arrived. Raises ``KeyError`` naming the
        valid streams for an unknown one."""
        with self._lock:
            if not self._acc:
                return {"ready": False, "reason": "no stream with two IMU channels yet",
                        "streams": []}
            key = stream if stream is not None else next(iter(self._acc))
            if key not in self._acc:
                raise KeyError(f"unknown stream {key!r}; valid streams: "
                               f"{', '.join(self._acc)}")
            acc = self._acc[key]
            n = acc.n_segments
            cached = self._cache.get(key)
            if cached is not None and cached[0] == n:
                return cached[1]
            if n < MIN_SEGMENTS:
                return {"ready": False, "streams": list(self._acc), "stream": key,
                        "reason": f"{n} of {MIN_SEGMENTS} segments of {acc.nperseg} samples "
                                  f"so far"}
            cs = acc.result()
        doc = log_coherence(cs, points_per_decade=self.points_per_decade).to_dict()
        doc.update({"ready": True, "stream": key, "streams": self.streams,
                    "n_segments": cs.n_segments})
        with self._lock:
            self._cache[key] = (n, doc)
        return doc
