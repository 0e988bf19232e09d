"""Live cross-channel coherence: the Welch cross-spectral matrix of each stream's IMU channels,
fed block by block by the service, published as the ``coherence`` document of
:mod:`imunoise.analysis.coherence` (pairs, log-frequency points, exact intervals, threshold).

Channels of one stream share its time base; the temperature, a stream of its own at another
rate, is not included live (``analyze`` interpolates it onto the IMU's time base).

With several devices (one stream each, sampled at its own instants) a further document,
:data:`DEVICES`, holds the coherence between every IMU channel of every device: the other
streams' recent samples are interpolated (band-limited, :mod:`imunoise.analysis.alignment`) at
the first stream's sample times, chunk by chunk, as their samples arrive.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np

from imunoise.analysis.alignment import HALF_TAPS, interpolate
from imunoise.analysis.coherence import CrossSpectralAccumulator, log_coherence
from imunoise.core.series import channel_units

SEGMENT_S = 10.0
"""Welch segment length in seconds (rounded to a power of two of samples): 0.1 Hz resolution
from 0.2 Hz up."""

MIN_SEGMENTS = 4
"""Segments needed before a coherence is published."""

DEVICES = "devices"
"""The name of the document across every device's stream."""

KEEP_S = 30.0
"""Seconds of each stream kept for the interpolation across devices."""


def _nperseg(fs_hz: float, seconds: float) -> int:
    n = max(int(fs_hz * seconds), 64)
    return int(min(1 << int(round(math.log2(n))), 1 << 15))


class _AcrossDevices:
    """The cross-spectral matrix of every IMU channel of several streams: each other stream
    interpolated at the first stream's sample times, one chunk of the first stream at a time
    (once every other stream has samples on both sides of it)."""

    def __init__(self, segment_s: float) -> None:
        self.segment_s = segment_s
        self.recent: dict[str, tuple[np.ndarray, np.ndarray, float, list[str]]] = {}
        self.acc: CrossSpectralAccumulator | None = None
        self.next_t: float | None = None  # first reference time not yet fed

    def add(self, stream: str, t: np.ndarray, x: np.ndarray, fs: float, names: list[str],
            gap: bool) -> None:
        old = self.recent.get(stream)
        if old is None or old[3] != names or gap:
            tt, xx = t, x
        else:
            tt, xx = np.concatenate([old[0], t]), np.vstack([old[1], x])
        keep = tt >= tt[-1] - KEEP_S
        self.recent[stream] = (tt[keep], xx[keep], fs, names)
        if len(self.recent) >= 2:
            self._feed()

    def _feed(self) -> None:
        streams = list(self.recent)
        t_ref, x_ref, fs, _ = self.recent[streams[0]]
        channels = [f"{s}:{n}" for s in streams for n in self.recent[s][3]]
        if self.acc is None or list(self.acc.channels) != channels:
            self.acc = CrossSpectralAccumulator(channels, fs, _nperseg(fs, self.segment_s))
            self.next_t = None
        chunk = max(self.acc.nperseg // 4, 16)
        if self.next_t is not None and t_ref[0] > self.next_t + 1.0 / fs:
            self.acc.new_segment()  # the reference ran past what is kept: a gap in the feed
            self.next_t = None
        while True:
            start = 0 if self.next_t is None else int(np.searchsorted(t_ref, self.next_t))
            if start + chunk > t_ref.size:
                return
            tc = t_ref[start:start + chunk]
            if np.any(np.diff(tc) > 1.5 / fs):  # a gap in the reference: start after it
                self.acc.new_segment()
                self.next_t = float(tc[np.flatnonzero(np.diff(tc) > 1.5 / fs)[-1] + 1])
                continue
            parts = [x_ref[start:start + chunk]]
            for s in streams[1:]:
                t_o, x_o, fs_o, _ = self.recent[s]
                if t_o.size < 2 * HALF_TAPS or t_o[-1] < tc[-1] + HALF_TAPS / fs_o:
                    return  # that device's samples for this chunk have not all come yet
                u = np.interp(tc, t_o, np.arange(t_o.size, dtype=np.float64))
                lo, hi = int(np.floor(u[0])) - HALF_TAPS, int(np.ceil(u[-1])) + HALF_TAPS
                if t_o[0] > tc[0] or lo < 0 or np.any(
                        np.diff(t_o[max(lo, 0):hi + 1]) > 1.5 / fs_o):
                    parts = []  # that device has a gap here (or lost the start): skip it
                    break
                cutoff = min(1.0, fs / fs_o)
                parts.append(np.column_stack([interpolate(x_o[:, k], u, cutoff)
                                              for k in range(x_o.shape[1])]))
            self.next_t = float(tc[-1]) + 0.5 / fs
            if not parts or not all(np.isfinite(p).all() for p in parts):
                self.acc.new_segment()
                continue
            self.acc.add(np.hstack(parts))


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
        self._across = _AcrossDevices(self.segment_s)

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
                t = np.asarray(block.t, dtype=np.float64)
                t = t[finite] if t.shape[0] == finite.shape[0] else t[:len(x)]
                self._across.add(block.stream, t, x, float(block.fs_hz), names,
                                 bool(getattr(block, "gap_before", 0)) or not np.all(finite))

    @property
    def streams(self) -> list[str]:
        with self._lock:
            return self._streams()

    def _streams(self) -> list[str]:
        out = list(self._acc)
        if len(self._across.recent) >= 2:
            out.append(DEVICES)
        return out

    def _accumulator(self, key: str) -> CrossSpectralAccumulator | None:
        if key == DEVICES and len(self._across.recent) >= 2:
            return self._across.acc
        return self._acc.get(key)

    def document(self, stream: str | None = None) -> dict[str, Any]:
        """The coherence document of ``stream`` (default: the first), or ``{"ready": False,
        "reason": ...}`` until enough segments have arrived. Raises ``KeyError`` naming the
        valid streams for an unknown one."""
        with self._lock:
            if not self._acc:
                return {"ready": False, "reason": "no stream with two IMU channels yet",
                        "streams": []}
            key = stream if stream is not None else next(iter(self._acc))
            if key not in self._streams():
                raise KeyError(f"unknown stream {key!r}; valid streams: "
                               f"{', '.join(self._streams())}")
            acc = self._accumulator(key)
            n = acc.n_segments if acc is not None else 0
            cached = self._cache.get(key)
            if cached is not None and cached[0] == n:
                return cached[1]
            if acc is None or n < MIN_SEGMENTS:
                return {"ready": False, "streams": self._streams(), "stream": key,
                        "reason": f"{n} of {MIN_SEGMENTS} segments of "
                                  f"{acc.nperseg if acc is not None else '?'} samples so far"}
            cs = acc.result()
        doc = log_coherence(cs, points_per_decade=self.points_per_decade).to_dict()
        doc.update({"ready": True, "stream": key, "streams": self.streams,
                    "n_segments": cs.n_segments})
        with self._lock:
            self._cache[key] = (n, doc)
        return doc
