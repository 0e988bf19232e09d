"""Pieces the analysis commands (``analyze``, ``fit``, ``diagnose``) share: the ``--rate``,
``--static``, ``--skip`` and ``--split`` options, and the text block of a fitted model with its
intervals. Reading and fitting themselves are in :mod:`imunoise.pipeline`."""

from __future__ import annotations

import argparse
import math
from typing import TYPE_CHECKING, Any

import numpy as np

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
                             "its first sample): no Allan difference spans a bias step; a "
                             "time outside the samples analysed cuts nothing and is named "
                             "in a warning (default: no cut)")


def model_lines(result: FitResult | Any, units: str) -> list[str]:
    """The fitted model with its 95 % intervals (one line per parameter, units labelled) and
    the error line."""
    from imunoise.analysis.terms import get_term, param_unit

    lines = ["  model (95 % intervals)"]
    for label, t in zip(result.labels, result.terms, strict=True):
        for p in get_term(t.term).params:
            v = t.params[p.name]
            lo, hi = t.ci95[p.name]
            unit = param_unit(p, units)
            if not get_term(t.term).resolved(p.name, (lo, hi)):  # an interval reaching zero
                lines.append(f"    {label:17s} {p.name:5s} = not resolved (95 % upper bound "
                             f"{hi:.4g}) {unit}")
                continue
            lines.append(f"    {label:17s} {p.name:5s} = {v:11.4g}  [{lo:.4g}, {hi:.4g}] {unit}")
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


