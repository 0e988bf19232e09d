"""Bulk numpy reader for ROS 2 MCAP files with ``sensor_msgs/msg/Imu`` and ``Temperature``.

The Imu and Temperature CDR layouts are fixed once ``header.frame_id`` is fixed, so instead of
decoding message by message the reader decompresses a batch of chunks, takes the message
offsets from the MessageIndex records (or walks the chunk when a file has none), checks every
message (opcode, record length, XCDR1 little-endian encapsulation, frame_id length) and gathers
the stamp, angular velocity, linear acceleration and temperature fields with one vectorised
indexing operation per field. Memory stays bounded: the file is read one batch of chunks at a
time with ``pread``; :func:`read_mcap` preallocates its output from the index counts.

Topics are chosen by schema name. A file this reader cannot take (message records outside
chunks, frame_id length changing within a topic, big-endian or XCDR2 payloads) raises
:class:`UnsupportedLayout`, and :func:`imunoise.daq.readers.open_record` falls back to rosbags.
Crashed or truncated files are read up to the last complete chunk, with a warning.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from imunoise.core.blocks import SampleBlock
from imunoise.core.record import Record
from imunoise.core.series import SAMPLE_LIMIT, ChannelSeries, usable_samples
from imunoise.core.timing import Timing, analyse_stamps, relative_seconds, segment_starts_from_times
from imunoise.daq import mcap_layout as ml
from imunoise.daq.errors import ReadError
from imunoise.daq.readers.mcap_decode import ACCEL, GYRO, _columns, iter_decoded, read_ahead
from imunoise.daq.readers.mcap_scan import McapSource, UnsupportedLayout, _Topic, open_mcap

__all__ = ["ACCEL", "GYRO", "McapSource", "UnsupportedLayout", "iter_blocks", "iter_decoded",
           "make_series", "open_mcap", "raw_counts", "read_ahead", "read_mcap", "topic_timing"]

def _split(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {k: v for k, v in data.items() if k != "t"}


def topic_timing(ns: np.ndarray, name: str, metadata: dict[str, str] | None = None,
                 rate_hz: float | None = None) -> Timing:
    """Timing of one topic's int64 nanosecond stamps (:func:`imunoise.core.timing.analyse_stamps`);
    with fewer than two increasing stamps the rate comes from the ``rate_hz`` metadata, else
    a ReadError naming the topic. A given ``rate_hz`` replaces the inferred rate."""
    try:
        return analyse_stamps(ns, rate_hz=rate_hz, name=name)
    except ValueError as exc:
        try:
            fs = float((metadata or {}).get("rate_hz", "nan"))
        except ValueError:
            fs = float("nan")
        if not np.isfinite(fs) or fs <= 0:
            raise ReadError(f"{name}: {exc}") from None
        return analyse_stamps(ns, rate_hz=fs, name=name)


def make_series(name: str, t: np.ndarray, values: np.ndarray, timing: Timing,
                warnings: list[str], units: str) -> ChannelSeries:
    """A ChannelSeries from stamps (int64 ns), values and the topic's timing. Samples that are
    not finite or beyond :data:`imunoise.core.series.SAMPLE_LIMIT` are dropped with a warning;
    the hole they leave becomes a segment boundary."""
    finite = usable_samples(values)
    if finite.all():
        starts = timing.segment_starts
        if timing.segment_t0_s is None:  # once per topic, not per channel
            timing.segment_t0_s = _stamp_seconds(t, starts, timing.t0_s, timing.fs_hz)
        return ChannelSeries(name=name, units=units, fs_hz=timing.fs_hz,
                             values=np.ascontiguousarray(values, dtype=np.float64),
                             segment_starts=starts, t0_s=timing.t0_s,
                             segment_t0_s=timing.segment_t0_s)
    warnings.append(dropped_samples_note(name, values, finite))
    t, values = t[finite], np.ascontiguousarray(values[finite], dtype=np.float64)
    rel, t0 = relative_seconds(t)
    starts = segment_starts_from_times(rel, timing.fs_hz) if t.size else np.zeros(1, np.int64)
    return ChannelSeries(name=name, units=units, fs_hz=timing.fs_hz, values=values,
                         segment_starts=starts, t0_s=t0,
                         segment_t0_s=_stamp_seconds(t, starts, t0, timing.fs_hz))


def _stamp_seconds(t: np.ndarray, starts: np.ndarray, t0_s: float, fs_hz: float
                   ) -> np.ndarray | None:
    """Where each segment's sample grid lies (s, as ``t0_s``): the mean over the segment of
    each stamp less its place on the grid, so that the jitter of a first stamp does not
    shift a whole segment; what lies in the gaps, for putting several topics on one time
    base."""
    if t.size == 0 or starts.size == 0 or int(starts[-1]) >= t.size or not fs_hz > 0:
        return None
    rel, _ = relative_seconds(t)
    within = np.arange(t.size, dtype=np.float64)
    within -= np.repeat(starts, np.diff(np.append(starts, t.size))).astype(np.float64)
    within /= fs_hz
    rel -= within
    counts = np.diff(np.append(starts, t.size)).astype(np.float64)
    return t0_s + np.add.reduceat(rel, starts) / counts


def dropped_samples_note(name: str, values: np.ndarray, usable: np.ndarray) -> str:
    """The warning for the samples of ``values`` outside the ``usable`` mask."""
    bad = int((~usable).sum())
    if np.isfinite(values[~usable]).any():
        return (f"{name}: {bad} non-finite or out-of-range (beyond {SAMPLE_LIMIT:g}) samples "
                "dropped (treated as gaps)")
    return f"{name}: {bad} non-finite samples dropped (treated as gaps)"


def read_mcap(path: str | Path, rate_hz: float | None = None) -> Record:
    """Read every Imu and Temperature channel of a ROS 2 MCAP file into a Record
    (``rate_hz``: nominal rate overriding the one inferred from the stamps)."""
    src = open_mcap(path)
    if not src.topics:
        raise ml.McapFormatError("no sensor_msgs/msg/Imu or Temperature channel")
    arrays: dict[int, dict[str, np.ndarray]] = {}
    fill: dict[int, int] = dict.fromkeys(src.topics, 0)

    def sink(tp: _Topic, n: int) -> dict[str, np.ndarray]:
        """Slices of the output arrays, allocated once from the index counts."""
        have = arrays.get(tp.cid)
        k = fill[tp.cid]
        if have is None:
            cap = max(tp.count, n)
            have = arrays[tp.cid] = {c: np.empty(cap, np.int64 if c == "t" else np.float64)
                                     for c in _columns(tp)}
        cap = len(have["t"])
        if k + n > cap:  # chunks without message indexes: counts were not known
            for c, v in have.items():
                grown = np.empty(max(k + n, 2 * cap), v.dtype)
                grown[:k] = v[:k]
                have[c] = grown
        fill[tp.cid] = k + n
        return {c: v[k:k + n] for c, v in have.items()}

    for _decoded in iter_decoded(src, sink):
        pass
    warnings = list(src.warnings)
    channels: dict[str, ChannelSeries] = {}
    temperature: ChannelSeries | None = None
    imu_topics = [tp for tp in src.topics.values() if tp.kind == "imu" and fill[tp.cid]]
    temp_topics = [tp for tp in src.topics.values()
                   if tp.kind == "temperature" and fill[tp.cid]]
    if not imu_topics and not temp_topics:
        raise ml.McapFormatError("no Imu or Temperature messages in the file")
    timings: dict[str, dict] = {}
    for tp in imu_topics:
        n = fill[tp.cid]
        cols = {k: v[:n] for k, v in arrays.pop(tp.cid).items()}
        t = cols.pop("t")
        timing = topic_timing(t, tp.topic, src.metadata, rate_hz)
        timings[tp.topic] = timing.facts()
        warnings.extend(timing.notes)
        label = tp.topic if len(imu_topics) > 1 else ""
        for name, v in cols.items():
            key = f"{label}:{name}" if label else name
            channels[key] = make_series(key, t, v, timing, warnings,
                                        "rad/s" if name.startswith("gyro") else "m/s^2")
        del t, cols
    if temp_topics:
        tp = temp_topics[0]
        n = fill[tp.cid]
        cols = arrays.pop(tp.cid)
        t = cols["t"][:n]
        if len(temp_topics) > 1:
            warnings.append(f"several temperature topics: using {tp.topic}")
        timing = topic_timing(t, tp.topic, {"rate_hz": "1.0"})
        temperature = make_series("temp", t, cols["temp"][:n], timing, warnings, "degC")
    meta = dict(src.metadata)
    meta["format"] = "mcap"
    if imu_topics:
        meta["fs_hz"] = f"{next(iter(channels.values())).fs_hz:.9g}"
    meta["topics"] = ",".join(tp.topic for tp in src.topics.values())
    return Record(source=str(path), channels=channels, temperature=temperature, metadata=meta,
                  warnings=warnings, facts={"timing": timings} if timings else {})


def raw_counts(values: np.ndarray, metadata: dict[str, str], channel: str) -> np.ndarray | None:
    """Raw register counts of a channel recorded by imunoise (``value = offset + scale *
    count``, scale and offset in the metadata record), or None when the file has no scale
    or a value is not finite."""
    base = channel if f"scale.{channel}" in metadata else channel.split(":")[-1]
    try:  # a file of several devices keys its scales by topic: scale.TOPIC:gyro_x
        scale = float(metadata[f"scale.{base}"])
        offset = float(metadata.get(f"offset.{base}", "0"))
    except (KeyError, ValueError):
        return None
    values = np.asarray(values, dtype=np.float64)
    if not (np.isfinite(scale) and scale != 0 and np.isfinite(offset)
            and np.all(usable_samples(values))):
        return None
    with np.errstate(all="ignore"):
        counts = np.rint((values - offset) / scale)
    if not np.all(np.abs(counts) < 2.0**53):  # not counts of a register: leave them out
        return None
    return counts.astype(np.int64)


def _lost_as_nan(values: np.ndarray) -> np.ndarray:
    """A block's channel with the samples that are not finite or beyond
    :data:`imunoise.core.series.SAMPLE_LIMIT` as NaN (lost samples to every consumer)."""
    out = np.ascontiguousarray(values, dtype=np.float64)
    usable = usable_samples(out)
    if not usable.all():
        out = np.where(usable, out, np.nan)
    return out


def iter_blocks(path: str | Path, src: McapSource | None = None) -> Iterator[SampleBlock]:
    """Stream a file as SampleBlocks (one per topic, batch and gap-free run), bounded memory.

    Each block is contiguous in time; ``gap_before`` counts the samples missing before it
    (-1 when time went backwards or the rate is unknown). Raw counts are attached when the
    file carries scale factors. ``src`` may be passed when the file is already opened.
    """
    src = open_mcap(path) if src is None else src
    last_t: dict[int, float] = {}
    rates: dict[int, float] = {}
    for decoded in iter_decoded(src):
        for cid, data in decoded.items():
            tp = src.topics[cid]
            ns = data["t"]
            if ns.size == 0:
                continue
            fs = rates.get(cid)
            if fs is None:
                try:
                    fs = topic_timing(ns, tp.topic, src.metadata).fs_hz
                except ValueError:
                    fs = 1.0
                rates[cid] = fs
            cols = _split(data)
            rel, t_first = relative_seconds(ns)
            t = rel + t_first
            timing = (analyse_stamps(ns, rate_hz=fs) if ns.size > 1 and np.any(np.diff(ns) > 0)
                      else None)
            starts = timing.segment_starts if timing else np.zeros(1, np.int64)
            inner = dict(zip(starts[1:].tolist(), timing.gaps.tolist(), strict=True)) \
                if timing else {}
            # jitter is no gap here either (imunoise.core.timing)
            bounds = np.append(starts, t.size)
            for a, b in zip(bounds[:-1], bounds[1:], strict=True):
                if b <= a:
                    continue
                prev = last_t.get(cid)
                gap = int(inner.get(int(a), 0))
                if a == 0 and prev is not None:
                    steps = (t[a] - prev) * fs
                    if steps > 1.5:
                        gap = int(round(steps)) - 1
                    elif steps < 0.5:
                        gap = -1
                chans = {k: _lost_as_nan(v[a:b]) for k, v in cols.items()}
                raw = {}
                for k, v in chans.items():
                    counts = raw_counts(v, src.metadata, k)
                    if counts is not None:
                        raw[k] = counts
                yield SampleBlock(stream=tp.topic, t=t[a:b].copy(), channels=chans, fs_hz=fs,
                                  raw=raw, gap_before=gap)
                last_t[cid] = float(t[b - 1])
