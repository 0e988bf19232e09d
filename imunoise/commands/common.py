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

from core.record import TEMPERATURE_KEY, ChannelSelectionError, Record, select_channels
from daq.readers import ReadError, open_record
from imunoise.errors import RuntimeFailure, UsageError

if TYPE_CHECKING:
    from analysis.fit import FitResult

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


def add_rate_option(parser: argparse.ArgumentParser) -> None:
    """``--rate HZ`` with the shared check and help."""
    parser.add_argument("--rate", type=positive_rate, metavar="HZ", help=RATE_HELP)


def read_record(path: str, rate_hz: float | None = None) -> Record:
    """:func:`daq.readers.open_record`, a read error becoming a usage error (exit 2)."""
    try:
        return open_record(path, rate_hz=rate_hz)
    except ReadError as exc:
        raise UsageError(str(exc)) from None


def select(record: Record, selectors: Sequence[str]) -> list[str]:
    """Resolve channel selectors (``gyro_x``, ``TOPIC:gyro_x``); unknown ones are usage errors
    whose message lists the valid channels."""
    try:
        return select_channels(record, list(selectors))
    except ChannelSelectionError as exc:
        raise UsageError(str(exc)) from None


def open_imu_channel(path: str, rate_hz: float | None, selector: str,
                     command: str) -> tuple[Record, str]:
    """Read a recording and resolve one inertial channel: ``(record, key)``.

    Raises UsageError for unreadable input, an unknown channel or the temperature."""
    record = read_record(path, rate_hz)
    key = select(record, [selector])[0]
    if key == TEMPERATURE_KEY:
        raise UsageError(f"{command}: choose an IMU channel (gyro_* or accel_*), "
                         "not the temperature")
    return record, key


# Amplitude parameters: zero means the term is absent, so an interval reaching zero leaves the
# amplitude unresolved (a time constant or frequency interval is shown as it is).
AMPLITUDES = ("N", "Q", "B", "K", "R", "sigma", "A", "coef")


def model_lines(result: FitResult | Any, units: str) -> list[str]:
    """The fitted model with its 95 % intervals (one line per parameter, units labelled) and
    the error line."""
    from analysis.terms import get_term, param_unit

    lines = ["  model (95 % intervals)"]
    for t in result.terms:
        for p in get_term(t.term).params:
            v = t.params[p.name]
            lo, hi = t.ci95[p.name]
            unit = param_unit(p, units)
            if p.name in AMPLITUDES and not lo > 0.0:  # an interval reaching zero: no estimate
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
    from analysis.terms import TermError, parse_model

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
    from analysis.terms import TermError

    try:
        yield
    except TermError as exc:
        raise UsageError(str(exc)) from None
    except ValueError as exc:
        raise UsageError(f"{key}: {exc}") from None
    except np.linalg.LinAlgError as exc:
        raise RuntimeFailure(f"{key}: the fit failed numerically ({exc})") from None
