"""Feed a recording to a consumer block by block, as if it were arriving live.

``replay`` paces the blocks on the sample clock (``speed`` times real time, or as fast as
possible) and reports progress; the consumer is any callable taking a
:class:`imunoise.core.blocks.SampleBlock`, e.g. ``RollingAnalyzer.update``.
"""

from __future__ import annotations

import heapq
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from imunoise.core.blocks import SampleBlock
from imunoise.core.series import ChannelSeries
from imunoise.daq.readers import ReadError, open_record

PACE_S = 0.1  # sample-time length of the pieces a paced replay hands over
CHUNK_S = 1.0  # sample-time length of the blocks a record read whole is cut into


def _series_blocks(topic: str, chans: dict[str, ChannelSeries]) -> Iterator[SampleBlock]:
    """Blocks of at most ``CHUNK_S`` of channels that share one timing (rate, start and
    segments); the first block after a gap carries ``gap_before=-1``."""
    first = next(iter(chans.values()))
    step = max(1, int(round(first.fs_hz * CHUNK_S)))
    bounds = np.append(first.segment_starts, first.n_samples)
    for k, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
        for c in range(int(a), int(b), step):
            d = min(c + step, int(b))
            t = first.t0_s + np.arange(c, d) / first.fs_hz
            yield SampleBlock(topic, t, {n: s.values[c:d] for n, s in chans.items()},
                              first.fs_hz, gap_before=-1 if k and c == a else 0)


def _record_blocks(path: Path, warnings: list[str] | None = None
                   ) -> tuple[Iterator[SampleBlock], int]:
    """Blocks of a record read whole (CSV, rosbag2), in time order across topics.

    Channels of one topic go in one block only where they share their timing: a channel with
    samples removed (NaN, empty cells) has segments of its own and is sent in its own blocks,
    so no other channel loses or shifts samples."""
    record = open_record(path)
    if warnings is not None:
        warnings.extend(record.warnings)
    total = max((s.n_samples for s in record.channels.values()), default=0)
    groups: dict[tuple, dict[str, ChannelSeries]] = {}
    for key, s in record.channels.items():
        topic, _, name = key.rpartition(":")
        timing = (topic or "/imu", s.fs_hz, s.t0_s, s.n_samples, tuple(s.segment_starts))
        groups.setdefault(timing, {})[name] = s
    if record.temperature is not None:
        s = record.temperature
        groups[("/temperature", s.fs_hz, s.t0_s, s.n_samples, tuple(s.segment_starts))] = {
            "temp": s}
    streams = [_series_blocks(timing[0], chans) for timing, chans in groups.items()]
    return heapq.merge(*streams, key=lambda b: float(b.t[0])), total


def open_blocks(path: str | Path, warnings: list[str] | None = None
                ) -> tuple[Iterator[SampleBlock], int]:
    """Blocks of a recording with bounded memory where possible, and the number of inertial
    samples to expect (for progress). MCAP files stream; other inputs are loaded first. What
    the reader repaired (a damaged chunk left out ...) is appended to ``warnings``, for a
    streamed file as the blocks are read."""
    path = Path(path)
    warnings = [] if warnings is None else warnings
    if path.is_file() and path.suffix.lower() == ".mcap":
        from imunoise.daq.mcap_layout import McapFormatError
        from imunoise.daq.readers.mcap import UnsupportedLayout, iter_blocks, open_mcap

        try:
            src = open_mcap(path)
        except UnsupportedLayout:
            return _record_blocks(path, warnings)
        except (McapFormatError, OSError) as exc:
            raise ReadError(f"{path.name}: {exc}") from exc
        if not src.topics:
            raise ReadError(f"{path.name}: no sensor_msgs/msg/Imu or Temperature channel")
        total = max((tp.count for tp in src.topics.values() if tp.kind == "imu"), default=0)
        warnings.extend(src.warnings)
        src.warnings = warnings  # the reader appends what it finds while streaming
        return iter_blocks(path, src=src), total
    return _record_blocks(path, warnings)


def _pieces(block: SampleBlock, n: int) -> Iterator[SampleBlock]:
    if len(block) <= n:
        yield block
        return
    for a in range(0, len(block), n):
        yield SampleBlock(block.stream, block.t[a:a + n],
                          {k: v[a:a + n] for k, v in block.channels.items()}, block.fs_hz,
                          raw={k: v[a:a + n] for k, v in block.raw.items()},
                          gap_before=block.gap_before if a == 0 else 0)


def paced(blocks: Iterator[SampleBlock], speed: float | None = 1.0,
          sleep: Callable[[float], None] = time.sleep,
          clock: Callable[[], float] = time.monotonic) -> Iterator[SampleBlock]:
    """The blocks, each released when the sample clock says: ``speed`` times real time, in
    pieces of ``PACE_S`` seconds of samples; unpaced when ``speed`` is None or not positive."""
    speed_x = float(speed) if speed is not None and speed > 0 else None
    t_start: float | None = None
    wall_start = clock()
    for block in blocks:
        if not len(block):
            continue
        if speed_x is None:
            yield block
            continue
        for piece in _pieces(block, max(1, int(block.fs_hz * PACE_S * speed_x))):
            if t_start is None:
                t_start = float(piece.t[0])
            wait = wall_start + (float(piece.t[-1]) - t_start) / speed_x - clock()
            if wait > 0:
                sleep(wait)
            yield piece


def replay(blocks: Iterator[SampleBlock], consumer: Callable[[SampleBlock], None],
           speed: float | None = 1.0, progress: Callable[[SampleBlock], None] | None = None,
           sleep: Callable[[float], None] = time.sleep,
           clock: Callable[[], float] = time.monotonic) -> None:
    """Hand every block to ``consumer``; ``speed`` times real time, or as fast as possible
    when ``speed`` is None or not positive."""
    for piece in paced(blocks, speed, sleep=sleep, clock=clock):
        consumer(piece)
        if progress is not None:
            progress(piece)


@dataclass
class _ChannelSummary:
    samples: int = 0
    gaps: int = 0
    sum_d2: float = 0.0
    n_d: int = 0
    last: float | None = None
    fs_hz: float = 0.0
    units: str = ""


@dataclass
class ReplaySummary:
    """Per channel: samples, sampled duration, gaps and a white-noise density estimate from
    first differences (N = std(diff) / sqrt(2 fs), in units/sqrt(Hz); a drift or random walk
    barely affects differences, quantization and correlated noise do)."""

    channels: dict[str, _ChannelSummary] = field(default_factory=dict)

    def __call__(self, block: SampleBlock) -> None:
        multi = block.stream
        for name, values in block.channels.items():
            key = f"{multi}:{name}"
            s = self.channels.get(key)
            if s is None:
                from imunoise.core.series import channel_units

                s = self.channels[key] = _ChannelSummary(fs_hz=block.fs_hz,
                                                         units=channel_units(name))
            v = np.asarray(values, dtype=np.float64)
            v = v[np.isfinite(v)]
            if not v.size:
                continue
            if block.gap_before != 0:
                s.gaps += 1
                s.last = None
            if s.last is not None:
                v = np.concatenate(([s.last], v))
                s.samples -= 1
            d = np.diff(v)
            s.sum_d2 += float(d @ d)
            s.n_d += d.size
            s.samples += v.size
            s.last = float(v[-1])

    def rows(self) -> list[dict[str, object]]:
        out = []
        for key, s in self.channels.items():
            n_white = (np.sqrt(s.sum_d2 / s.n_d / 2.0 / s.fs_hz) if s.n_d and s.fs_hz
                       else float("nan"))
            out.append({"channel": key, "units": s.units, "samples": s.samples,
                        "duration_s": s.samples / s.fs_hz if s.fs_hz else 0.0,
                        "gaps": s.gaps, "white_noise_density": n_white})
        return out
