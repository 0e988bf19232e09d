"""``analyze`` of a recording too long to hold in memory: two passes over an MCAP file.

A 32 h, six-channel, 100 Hz log is 550 MB of float64 samples before any estimator has made a
copy; loading it is what made the analysis's memory grow with the record's length. Above
:data:`STREAM_ABOVE_BYTES` of samples an MCAP file is therefore read twice, a batch of chunks
at a time, and never held:

1. the first pass finds each IMU topic's sampling (rate, gaps, backward steps, jitter), the
   motion windows (:class:`imunoise.analysis.motion.MotionWindows`, exactly the statistics of the
   in-memory detection) and the temperature record (small: one sample a second);
2. the second pass feeds the selected channels' samples inside the still stretches to
   bounded-memory estimators: :class:`imunoise.analysis.streaming_allan.StreamingAllan` on the
   octave
   grid and :class:`imunoise.analysis.psd.StreamingPsd` (the in-memory PSD is the same estimator).

The numbers equal the in-memory analysis except in three documented ways: the Allan deviation
is exact up to ``m = 4096`` and beyond that uses every ``d``-th start index (``d`` at most
1/64 of ``m`` on a 32 h record, see :mod:`imunoise.analysis.streaming_allan`), its noise
identification looks at the last segment instead of the longest, and the rate is the
end-to-end one (samples, missing samples included, over the span) instead of the
least-squares grid period. Memory is a few MB per channel plus the motion windows (two floats
per axis and second), whatever the record's length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from imunoise.core.record import Record
from imunoise.core.series import ChannelSeries

STREAM_ABOVE_BYTES = 160_000_000
"""float64 bytes of IMU samples (all channels) above which ``analyze`` streams an MCAP file:
about 9 h of six channels at 100 Hz. Below it the in-memory path is as fast and exact
everywhere."""

_OCTAVES = 1 << np.arange(41, dtype=np.int64)  # averaging factors 1 .. 2^40, cut per channel


@dataclass
class SeriesSummary:
    """What the reports need of a channel that was never held: the shape of
    :class:`imunoise.core.series.ChannelSeries` without ``values``.

    Attributes:
        name: channel key.
        units: SI units of the samples.
        fs_hz: sampling rate, Hz.
        n_samples: samples analysed (still stretches, finite values).
        segment_starts: where each analysed gap-free segment begins, counted in analysed
            samples (always starts with 0).
        t0_s: time of the first analysed sample, s.
    """

    name: str
    units: str
    fs_hz: float
    n_samples: int = 0
    segment_starts: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    t0_s: float = 0.0

    @property
    def duration_s(self) -> float:
        """Analysed duration in seconds (gaps excluded)."""
        return self.n_samples / self.fs_hz


def _open_streamable(path: str):
    """The opened MCAP file (``imunoise.daq.readers.mcap.McapSource``) when the bulk reader takes
    it,
    else None (another format, or a file the loader reads and explains)."""
    p = Path(path)
    if not (p.is_file() and p.suffix.lower() == ".mcap"):
        return None
    from imunoise.daq.mcap_layout import McapFormatError
    from imunoise.daq.readers.mcap import UnsupportedLayout, open_mcap

    try:
        return open_mcap(p)
    except (UnsupportedLayout, McapFormatError, OSError, ValueError):
        return None


def imu_sample_bytes(src) -> int:
    """float64 bytes the IMU channels of an opened MCAP file take once loaded (from its
    message index counts)."""
    total = 0
    for tp in src.topics.values():
        if tp.kind == "imu":
            total += tp.count * 3 * (int(tp.has_gyro) + int(tp.has_accel))
    return 8 * total


def stream_source(path: str, mode: str):
    """The opened file when ``analyze`` streams ``path``, else None: ``mode`` ``"auto"``
    (above :data:`STREAM_ABOVE_BYTES`), ``"always"`` (any MCAP file the bulk reader takes) or
    ``"never"``. The file is scanned once, for this choice and for the analysis."""
    if mode == "never":
        return None
    src = _open_streamable(path)
    if src is None or (mode != "always" and imu_sample_bytes(src) <= STREAM_ABOVE_BYTES):
        return None
    return src


@dataclass
class _TopicScan:
    """First-pass findings for one IMU topic."""

    prefix: str
    columns: list[str]
    fs_block: float = 0.0
    n: int = 0
    t_first: float = math.nan
    t_last: float = math.nan
    starts: list[int] = field(default_factory=lambda: [0])  # stream index of each segment
    missing: int = 0
    backward: int = 0
    widest_gap_s: float = 0.0
    widest_before: int = 0  # 1-based number of the first sample after the widest gap
    first_backward: int = 0  # likewise for the first backward step
    jitter_sq: float = 0.0
    jitter_max: float = 0.0
    nonfinite: dict[str, int] = field(default_factory=dict)
    windows: Any = None  # imunoise.analysis.motion.MotionWindows
    last_finite: dict[str, float] = field(default_factory=dict)


def _ffill(name: str, v: np.ndarray, scan: _TopicScan) -> np.ndarray:
    """The axis with non-finite samples replaced by the previous finite one (for the motion
    windows only: a dropped sample must not look like motion)."""
    bad = ~np.isfinite(v)
    if not bad.any():
        scan.last_finite[name] = float(v[-1])
        return v
    scan.nonfinite[name] = scan.nonfinite.get(name, 0) + int(bad.sum())
    idx = np.where(bad, 0, np.arange(v.size))
    np.maximum.accumulate(idx, out=idx)
    out = v[idx]
    lead = ~np.isfinite(out)
    out[lead] = scan.last_finite.get(name, 0.0)
    scan.last_finite[name] = float(out[-1])
    return out


def _scan_block(scan: _TopicScan, block) -> None:
    n = len(block)
    if scan.n == 0:
        scan.t_first = float(block.t[0])
        scan.fs_block = block.fs_hz
    elif block.gap_before:
        scan.starts.append(scan.n)
        if block.gap_before > 0:
            scan.missing += block.gap_before
            if float(block.t[0]) - scan.t_last > scan.widest_gap_s:
                scan.widest_gap_s = float(block.t[0]) - scan.t_last
                scan.widest_before = scan.n + 1
        else:
            scan.backward += 1
            scan.first_backward = scan.first_backward or scan.n + 1
    # jitter around the block's own grid at the topic's rate (the stamps of a block are one
    # gap-free run, so this is the in-memory definition taken a run at a time)
    r = block.t - block.t[0] - np.arange(n) / block.fs_hz
    r -= np.median(r)
    scan.jitter_sq += float(np.dot(r, r))
    scan.jitter_max = max(scan.jitter_max, float(np.max(np.abs(r))))
    scan.t_last = float(block.t[-1])
    scan.n += n
    cols = {c: _ffill(c, block.channels[c], scan) for c in scan.columns}
    scan.windows.update([cols[c] for c in scan.columns if c.startswith("gyro")],
                        [cols[c] for c in scan.columns if c.startswith("accel")])


def _rate(scan: _TopicScan, rate_hz: float | None) -> float:
    if rate_hz:
        return float(rate_hz)
    steps = scan.n - 1 + scan.missing
    span = scan.t_last - scan.t_first
    if steps > 0 and span > 0:
        return float(f"{steps / span:.9g}")
    return scan.fs_block


def _timing_facts(scan: _TopicScan, fs: float, topic: str, warnings: list[str]) -> dict:
    label = f"{topic}: " if topic else ""
    if scan.missing:
        gaps = sum(1 for _ in scan.starts[1:]) - scan.backward
        warnings.append(f"{label}{scan.missing} sample(s) missing in {gaps} gap(s) (largest "
                        f"{scan.widest_gap_s:.3g} s, before sample {scan.widest_before}); "
                        "segments are analysed separately")
    if scan.backward:
        warnings.append(f"{label}time goes backwards or repeats at {scan.backward} place(s) "
                        f"(first before sample {scan.first_backward}); treated as segment "
                        "boundaries, samples kept")
    rms = math.sqrt(scan.jitter_sq / scan.n) if scan.n else 0.0
    return {"fs_hz": fs, "segments": len(scan.starts), "missing_samples": scan.missing,
            "jitter_rms_s": rms, "jitter_max_s": scan.jitter_max,
            "backward_steps": scan.backward}


@dataclass
class _Feed:
    """Second-pass state of one selected channel."""

    key: str
    name: str
    summary: SeriesSummary
    allan: Any  # imunoise.analysis.streaming_allan.StreamingAllan
    psd: Any  # imunoise.analysis.psd.StreamingPsd
    next_index: int = -1  # stream index that continues the current segment
    starts: list[int] = field(default_factory=list)
    held: Any = None  # imunoise.analysis.evidence.held.HeldCounter

    def __post_init__(self) -> None:
        from imunoise.analysis.evidence.held import HeldCounter

        self.held = HeldCounter()

    def feed(self, values: np.ndarray, first: int, t_first: float) -> None:
        """Finite runs of ``values`` (stream indices from ``first``), a new segment whenever
        they do not continue the last one."""
        finite = np.isfinite(values)
        if finite.all():
            runs = [(0, values.size)]
        else:
            edges = np.flatnonzero(np.diff(np.concatenate(([0], finite.view(np.int8), [0]))))
            runs = list(zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True))
        for a, b in runs:
            if first + a != self.next_index:
                if self.summary.n_samples == 0:
                    self.summary.t0_s = t_first + a / self.summary.fs_hz
                else:
                    self.allan.new_segment()
                    self.psd.new_segment()
                self.held.new_segment()
                self.starts.append(self.summary.n_samples)
            part = values[a:b]
            self.allan.update(part)
            self.psd.update(part)
            self.held.update(part)
            self.summary.n_samples += b - a
            self.next_index = first + b


def _longest(starts: list[int], n: int, ranges: list[tuple[int, int]]) -> int:
    """Longest gap-free run inside ``ranges`` (stream indices)."""
    bounds = np.asarray(starts + [n], dtype=np.int64)
    best = 0
    for a, b in ranges:
        inner = bounds[(bounds > a) & (bounds < b)]
        edges = np.concatenate(([a], inner, [b]))
        best = max(best, int(np.max(np.diff(edges))))
    return best


def _first_pass(path: str, src, scans: dict[str, _TopicScan], temp_topic: str | None,
                advance, warnings: list[str]) -> ChannelSeries | None:
    """Scan every IMU topic; return the temperature series (small enough to hold)."""
    from imunoise.analysis.motion import MotionWindows
    from imunoise.daq.readers.mcap import iter_blocks, make_series, topic_timing

    temp_t: list[np.ndarray] = []
    temp_v: list[np.ndarray] = []
    for block in iter_blocks(path, src):
        if block.stream == temp_topic:
            temp_t.append(block.t)
            temp_v.append(block.channels["temp"])
            continue
        scan = scans.get(block.stream)
        if scan is None:
            continue
        if scan.windows is None:
            scan.windows = MotionWindows(
                block.fs_hz, sum(c.startswith("gyro") for c in scan.columns),
                sum(c.startswith("accel") for c in scan.columns))
        _scan_block(scan, block)
        advance(len(block))
    if not temp_t:
        return None
    t = np.concatenate(temp_t)
    timing = topic_timing(t, temp_topic or "temperature", {"rate_hz": "1.0"})
    return make_series("temp", t, np.concatenate(temp_v), timing, warnings, "degC")


def _plan(record: Record, scans: dict[str, _TopicScan], keys: list[str],
          rate_hz: float | None, static: str) -> tuple[dict[str, _Feed],
                                                       dict[str, list[tuple[int, int]]]]:
    """After the first pass: each topic's rate, timing and motion facts (into ``record``),
    the stream ranges to analyse and the estimators of the selected channels."""
    from imunoise.analysis.psd import StreamingPsd, default_nperseg
    from imunoise.analysis.streaming_allan import StreamingAllan
    from imunoise.pipeline.reading import motion_verdict

    timings, motions, feeds = {}, {}, {}
    ranges: dict[str, list[tuple[int, int]]] = {}
    for topic, scan in scans.items():
        fs = _rate(scan, rate_hz)
        timings[topic] = _timing_facts(scan, fs, topic, record.warnings)
        for c, bad in scan.nonfinite.items():
            record.warnings.append(f"{scan.prefix}{c}: {bad} non-finite samples dropped "
                                   "(treated as gaps)")
        keep = [(0, scan.n)]
        if scan.windows is not None and scan.n:
            doc, still = motion_verdict(scan.prefix, scan.windows.motion(), static,
                                        record.warnings)
            motions[scan.prefix.rstrip(":") or "imu"] = doc
            keep = still if still is not None else keep
        ranges[topic] = keep
        nperseg = default_nperseg(_longest(scan.starts, scan.n, keep))
        for c in scan.columns:
            key = scan.prefix + c
            record.channels[key].fs_hz = fs
            if key in keys:
                # the record of a streamed file holds SeriesSummary, never samples
                feeds[key] = _Feed(key, c, record.channels[key],  # type: ignore[arg-type]
                                   StreamingAllan(fs, ("oadev",), m_grid=_OCTAVES),
                                   StreamingPsd(fs, nperseg=nperseg))
    record.facts["timing"] = timings
    if motions:
        record.facts["motion"] = motions
    return feeds, ranges


def _second_pass(path: str, src, scans: dict[str, _TopicScan], feeds: dict[str, _Feed],
                 ranges: dict[str, list[tuple[int, int]]], advance) -> None:
    """Feed the analysed ranges of the selected channels to their estimators."""
    from imunoise.daq.readers.mcap import iter_blocks

    at: dict[str, int] = dict.fromkeys(scans, 0)
    for block in iter_blocks(path, src):
        scan = scans.get(block.stream)
        if scan is None:
            continue
        first = at[block.stream]
        stop = first + len(block)
        at[block.stream] = stop
        mine = [f for c in scan.columns if (f := feeds.get(scan.prefix + c)) is not None]
        if block.gap_before:
            for f in mine:  # a gap ends the segment even inside a still range
                f.next_index = -1
        for a, b in ranges[block.stream]:
            lo, hi = max(a, first), min(b, stop)
            if hi > lo:
                for f in mine:
                    f.feed(block.channels[f.name][lo - first:hi - first], lo,
                           float(block.t[lo - first]))
        advance(len(block))


def _result(f: _Feed):
    """The ``analyze`` result of one fed channel."""
    from imunoise.analysis.evidence.held import warning_text
    from imunoise.core.units import CI95
    from imunoise.pipeline.channel_analysis import ChannelAnalysis, _fit

    f.summary.segment_starts = np.asarray(f.starts or [0], dtype=np.int64)
    # a summary stands for the series: the reports read its shape, never its samples
    out = ChannelAnalysis(key=f.key, series=f.summary)  # type: ignore[arg-type]
    warning = warning_text(f.held.finding(f.summary.fs_hz, units=f.summary.units))
    if warning:
        out.warnings.append(warning)
    try:
        if f.summary.n_samples < 4:
            raise ValueError(f"need at least 4 samples, the channel has {f.summary.n_samples}")
        out.allan = f.allan.curve("oadev", ci=CI95)
        if not out.allan.m.size:
            out.allan = None
            raise ValueError("no averaging factor has a term")
    except ValueError as exc:
        out.warnings.append(f"no Allan deviation: {exc}")
    _fit(out)
    try:
        out.psd = f.psd.estimate(ci=CI95)
    except ValueError as exc:
        out.warnings.append(f"no PSD: {exc}")
    return out


def _held(record: Record, key: str):
    """The ``analyze`` result of a series held in memory (the temperature, one sample a
    second)."""
    from imunoise.pipeline.channel_analysis import analyze_record

    return analyze_record(record, [key], show_progress=False)[0]


def analyze_streamed(path: str, selectors: list[str], rate_hz: float | None = None,
                     static: str = "auto", show_progress: bool | None = None, src=None):
    """Read and analyse ``path`` in two bounded-memory passes (``src``: the file already
    opened by :func:`stream_source`).

    Returns:
        (record, results): a :class:`imunoise.core.record.Record` whose channels are
        :class:`SeriesSummary` objects (temperature, metadata, warnings and ``timing`` /
        ``motion`` facts as the in-memory reader gives them) and the ``analyze`` results
        (:class:`imunoise.pipeline.channel_analysis.ChannelAnalysis`) of the selected channels.
    """
    from imunoise.daq.readers.mcap import open_mcap
    from imunoise.daq.readers.mcap_decode import _columns
    from imunoise.pipeline.reading import select
    from imunoise.progress import progress_bar

    src = open_mcap(path) if src is None else src
    imu = [tp for tp in src.topics.values() if tp.kind == "imu" and tp.count]
    temps = [tp for tp in src.topics.values() if tp.kind == "temperature" and tp.count]
    if not imu:
        from imunoise.daq.errors import ReadError

        raise ReadError(f"{Path(path).name}: no Imu messages")
    scans: dict[str, _TopicScan] = {}
    channels: dict[str, Any] = {}
    for tp in imu:
        prefix = f"{tp.topic}:" if len(imu) > 1 else ""
        cols = [c for c in _columns(tp) if c != "t"]
        scans[tp.topic] = _TopicScan(prefix, cols)
        for c in cols:
            channels[prefix + c] = SeriesSummary(
                prefix + c, "rad/s" if c.startswith("gyro") else "m/s^2", 0.0)
    # a Record of summaries (the samples are streamed, never held): duck-typed series
    record = Record(source=str(path), channels=channels, metadata=dict(src.metadata),
                    warnings=list(src.warnings),
                    temperature=SeriesSummary("temp", "degC", 1.0) if temps  # type: ignore[arg-type]
                    else None)
    keys = select(record, selectors)
    total = sum(tp.count for tp in imu)
    if show_progress is None:
        show_progress = total * 6 > 2_000_000
    with progress_bar(show_progress) as bar:
        task = bar.add_task("scanning (pass 1 of 2)", total=2 * total)

        def advance(n: int) -> None:
            bar.advance(task, n)

        record.temperature = _first_pass(path, src, scans, temps[0].topic if temps else None,
                                         advance, record.warnings)
        feeds, ranges = _plan(record, scans, keys, rate_hz, static)
        bar.update(task, description="analysing (pass 2 of 2)")
        _second_pass(path, src, scans, feeds, ranges, advance)
    seen = set(record.warnings)
    record.warnings.extend(w for w in dict.fromkeys(src.warnings) if w not in seen)
    results = [_result(feeds[key]) if key in feeds else _held(record, key) for key in keys]
    meta = record.metadata
    meta["format"] = "mcap"
    meta["fs_hz"] = f"{next(iter(channels.values())).fs_hz:.9g}"
    meta["topics"] = ",".join(tp.topic for tp in src.topics.values())
    return record, results
