"""Pieces the analysis commands (``analyze``, ``fit``, ``diagnose``) share: the ``--rate``
option, reading a recording and resolving channel selectors into usage errors, and the
text block of a fitted model with its intervals."""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np

from imunoise.core.record import TEMPERATURE_KEY, ChannelSelectionError, Record, select_channels
from imunoise.daq.readers import ReadError, open_record
from imunoise.errors import RuntimeFailure, UsageError

if TYPE_CHECKING:
    from imunoise.analysis.fit import FitResult

RATE_HELP = ("sampling rate in Hz (needed for a CSV without a time column 't'; otherwise it "
             "overrides the rate found from the time stamps)")


def positive_rate(text: str) -> float:
    """argparse type of ``--rate HZ``: a finite positive number of Hz."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"bad rate {text!r}: give Hz, e.g. 100") from None
    if not value > 0 or not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"bad rate {text!r}: must be positive")
    return value


STATIC_HELP = ("which samples to analyse: 'auto' (default) finds where the sensor moved and "
               "uses only the still stretches; 'all' uses everything (numbers from moving data "
               "are not noise)")
STATIC_CHOICES = ("auto", "all")


def add_rate_option(parser: argparse.ArgumentParser) -> None:
    """``--rate HZ`` and ``--static auto|all``: the options of every command that reads a
    recording for its noise."""
    parser.add_argument("--rate", type=positive_rate, metavar="HZ", help=RATE_HELP)
    parser.add_argument("--static", choices=STATIC_CHOICES, default="auto", help=STATIC_HELP)


def nonnegative_seconds(text: str) -> float:
    """argparse type: a time in seconds, zero or more."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not (value >= 0 and np.isfinite(value)):
        raise argparse.ArgumentTypeError(f"expected seconds >= 0, got {text!r}")
    return value


def split_times(text: str) -> list[float]:
    """argparse type: comma-separated times in seconds."""
    return [nonnegative_seconds(t) for t in text.split(",") if t.strip()]


def add_window_options(parser: argparse.ArgumentParser) -> None:
    """``--skip S`` and ``--split T[,T...]``: the remedies the diagnosis states for a warm-up
    and a bias step (its ``apply.args``)."""
    parser.add_argument("--skip", type=nonnegative_seconds, default=0.0, metavar="S",
                        help="leave out the first S seconds of the channel, counted in samples "
                             "from its first one (a warm-up transient; default 0)")
    parser.add_argument("--split", type=split_times, default=[], metavar="T[,T...]",
                        help="cut the channel into separate segments at these times (s from "
                             "its first sample): no Allan difference spans a bias step "
                             "(default: no cut)")


def apply_window(record: Record, key: str, skip_s: float, split_s: list[float]) -> None:
    """Channel ``key`` of ``record`` cut by ``--skip`` and ``--split`` (in place); a skip that
    leaves nothing is a usage error."""
    if not skip_s and not split_s:
        return
    try:
        record.channels[key] = record.channels[key].windowed(skip_s, split_s)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


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
                           "moving": st.moving,
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


def model_lines(result: FitResult | Any, units: str) -> list[str]:
    """The fitted model with its 95 % intervals (one line per parameter, units labelled) and
    the error line."""
    from imunoise.analysis.terms import get_term, param_unit

    lines = ["  model (95 % intervals)"]
    for t in result.terms:
        for p in get_term(t.term).params:
            v = t.params[p.name]
            lo, hi = t.ci95[p.name]
            unit = param_unit(p, units)
            if not get_term(t.term).resolved(p.name, (lo, hi)):  # an interval reaching zero
                lines.append(f"    {t.term:17s} {p.name:5s} = not resolved (95 % upper bound "
                             f"{hi:.4g}) {unit}")
                continue
            lines.append(f"    {t.term:17s} {p.name:5s} = {v:11.4g}  [{lo:.4g}, {hi:.4g}] {unit}")
    lines.append(f"  error: chi2/dof = {result.chi2_per_dof:.3g}   max |z| = "
                 f"{result.max_abs_z:.2f}   (flag |z| > {result.misfit.threshold:.2f})")
    return lines


def failure_lines(result: FitResult | Any) -> list[str]:
    """The tau ranges where the measurement leaves the model's band, or that there are none."""
    if not result.failures:
        return ["  the model explains the curve at every tau"]
    lines = ["  the model fails at:"]
    for f in result.failures:
        lo, hi = f["tau_s"]
        lines.append(f"    tau {lo:.4g} .. {hi:.4g} s: {f['direction']} "
                     f"(max |z| {f['max_abs_z']:.1f})")
    return lines


def parse_model(text: str) -> tuple[list[str], dict[str, float]]:
    """Term names and held parameters of ``--model TERMS``; an unknown term, a bad or
    out-of-range parameter or an empty model is a usage error naming the valid terms."""
    from imunoise.analysis.terms import TermError, parse_model

    if not text.strip(" ,"):
        raise UsageError(f"--model {text!r} names no term")
    try:
        spec = parse_model(text)
    except TermError as exc:
        raise UsageError(str(exc)) from None
    return spec.names, spec.fixed


@contextmanager
def fit_errors(key: str) -> Iterator[None]:
    """Turn a fit's exceptions into the command line's: a bad model or a record the fit
    cannot use is a usage error (exit 2), a numerical breakdown a runtime failure (exit 1)."""
    from imunoise.analysis.terms import TermError

    try:
        yield
    except TermError as exc:
        raise UsageError(str(exc)) from None
    except ValueError as exc:
        raise UsageError(f"{key}: {exc}") from None
    except np.linalg.LinAlgError as exc:
        raise RuntimeFailure(f"{key}: the fit failed numerically ({exc})") from None
