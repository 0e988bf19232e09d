"""Reading a recording for its noise: the file, its timing model and the still stretches.

:func:`read_record` is what every analysis command (``analyze``, ``fit``, ``diagnose``,
``plan``, ``export-kalibr``) and :func:`imunoise.read` start from: the reader of the file's
format (:func:`imunoise.daq.readers.open_record`, which finds the sampling grid, gaps and
rate), then, with ``static="auto"``, only the stretches where the sensor rested
(:func:`keep_still`). Bad input raises :class:`imunoise.errors.UsageError` with one line that
says what is wrong.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from imunoise.core.record import TEMPERATURE_KEY, ChannelSelectionError, Record, select_channels
from imunoise.daq.readers import ReadError, open_record
from imunoise.errors import UsageError


def apply_window(record: Record, key: str, skip_s: float, split_s: list[float]) -> None:
    """Channel ``key`` of ``record`` cut by ``--skip`` and ``--split`` (in place); a skip that
    leaves nothing is a usage error, a split time outside what is analysed a warning (it
    cuts nothing)."""
    if not skip_s and not split_s:
        return
    series = record.channels[key]
    try:
        record.channels[key] = series.windowed(skip_s, split_s)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    start = series.duration_s - record.channels[key].duration_s  # the skip, whole samples
    for t in series.idle_splits(skip_s, split_s):
        record.warnings.append(
            f"{key}: --split {t:g} s is outside the samples analysed "
            f"({start:.6g} to {series.duration_s:.6g} s): it cuts nothing")


def read_record(path: str, rate_hz: float | None = None, static: str = "all") -> Record:
    """:func:`imunoise.daq.readers.open_record`, a read error becoming a usage error (exit 2); with
    ``static="auto"`` the IMU channels keep only the stretches where the sensor rested
    (:func:`keep_still`)."""
    try:
        record = open_record(path, rate_hz=rate_hz)
    except ReadError as exc:
        raise UsageError(str(exc)) from None
    return keep_still(record, static)


def _topics(record: Record) -> dict[str, list[str]]:
    """IMU channel keys grouped by topic prefix (``""`` for plain names)."""
    out: dict[str, list[str]] = {}
    for key in record.channels:
        prefix = key.rsplit(":", 1)[0] + ":" if ":" in key else ""
        out.setdefault(prefix, []).append(key)
    return out


def _detect(record: Record, keys: list[str]):
    """Motion of one topic's channels, or None when they cannot be taken together."""
    from imunoise.analysis.motion import detect_motion

    series = [record.channels[k] for k in keys]
    n = series[0].n_samples
    if any(s.n_samples != n for s in series) or n == 0:
        return None

    def axes(kind: str) -> list[np.ndarray] | None:
        # the channels' own arrays: motion detection gathers its windows a chunk at a time
        cols = [record.channels[k].values for k in keys if k.split(":")[-1].startswith(kind)]
        return cols or None

    return detect_motion(series[0].fs_hz, axes("gyro"), axes("accel"))


def _motion_doc(motion, static: str) -> dict[str, Any]:
    return {"static": static, "moved": motion.moved, "still_s": motion.still_seconds(),
            "duration_s": motion.n_samples / motion.fs_hz, "summary": motion.describe(),
            "stretches": [{"start_s": st.start / motion.fs_hz, "stop_s": st.stop / motion.fs_hz,
                           "moving": st.moving, "shock": st.shock,
                           "peak_rate_rad_s": st.peak_rate if math.isfinite(st.peak_rate)
                           else None,
                           "peak_force_m_s2": st.peak_force if math.isfinite(st.peak_force)
                           else None}
                          for st in motion.stretches]}


def motion_verdict(prefix: str, motion, static: str, warnings: list[str]
                   ) -> tuple[dict[str, Any], list[tuple[int, int]] | None]:
    """What one topic's motion means for the analysis: its ``facts["motion"]`` entry and the
    still ``[start, stop)`` sample ranges to keep (None: keep everything). A warning is
    appended when the topic moved."""
    name = prefix.rstrip(":") or "the IMU"
    if static != "auto":
        if motion.moved:
            warnings.append(f"{prefix.rstrip(':') or 'the IMU'}: {motion.describe()}; "
                            "analysing everything as asked (--static all): numbers from "
                            "moving stretches are not noise")
        return {**_motion_doc(motion, "all"), "used": "all"}, None
    doc = _motion_doc(motion, "auto")
    if not motion.moved:
        return doc, None
    still = [(st.start, st.stop) for st in motion.still]
    if not still:
        doc["used"] = "all (no still stretch)"
        warnings.append(f"{name}: {motion.describe()}; there is no still stretch, "
                        "so the noise numbers below come from moving data and are "
                        "not the sensor's noise")
        return doc, None
    doc["used"] = f"{len(still)} still stretch(es), {motion.still_seconds():.0f} s"
    warnings.append(f"{name}: {motion.describe()}; analysing the {len(still)} still "
                    f"stretch(es), {motion.still_seconds():.0f} s (--static all for "
                    "everything)")
    return doc, still


def keep_still(record: Record, static: str = "auto") -> Record:
    """The record with each topic's IMU channels cut to its still stretches (each a segment),
    and ``facts["motion"]`` saying what was found. When a topic never rests, its channels are
    kept whole and a warning says that their numbers are not noise. With ``static="all"``
    nothing is cut; the motion is still found and reported."""
    facts: dict[str, Any] = {}
    for prefix, keys in _topics(record).items():
        motion = _detect(record, keys)
        if motion is None:
            continue
        doc, still = motion_verdict(prefix, motion, static, record.warnings)
        facts[prefix.rstrip(":") or "imu"] = doc
        if still is not None:
            for k in keys:
                record.channels[k] = record.channels[k].restricted(still)
    if facts:
        record.facts["motion"] = facts
    return record


def select(record: Record, selectors: Sequence[str]) -> list[str]:
    """Resolve channel selectors (``gyro_x``, ``TOPIC:gyro_x``); unknown ones are usage errors
    whose message lists the valid channels."""
    try:
        return select_channels(record, list(selectors))
    except ChannelSelectionError as exc:
        raise UsageError(str(exc)) from None


def open_imu_channel(path: str, rate_hz: float | None, selector: str,
                     command: str, static: str = "auto") -> tuple[Record, str]:
    """Read a recording and resolve one inertial channel: ``(record, key)``.

    Raises UsageError for unreadable input, an unknown channel or the temperature."""
    record = read_record(path, rate_hz, static)
    key = select(record, [selector])[0]
    if key == TEMPERATURE_KEY:
        raise UsageError(f"{command}: choose an IMU channel (gyro_* or accel_*), "
                         "not the temperature")
    return record, key
