"""``imunoise fit``: fit one noise model to a channel and show where it fails.

The model is a comma-separated list of terms (white, quantization, bias_instability,
random_walk, rate_ramp, gauss_markov, sinusoid, temperature). A parameter written after a term
is held at that value (SI units): ``--model white,gauss_markov:T=100,random_walk``.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from imunoise.commands.common import (
    add_rate_option,
    add_window_options,
    apply_window,
    failure_lines,
    fit_errors,
    model_lines,
    open_imu_channel,
    parse_model,
)
from imunoise.core.record import Record
from imunoise.core.units import CI95
from imunoise.web.views.documents import z_on_curve


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit one model, show where it fails", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", help="input recording (.csv, .mcap or rosbag2 folder)")
    p.add_argument("--channel", required=True, metavar="SEL",
                   help="channel to fit, e.g. gyro_x or /imu:gyro_x")
    p.add_argument("--model", required=True, metavar="TERMS",
                   help="comma-separated terms, e.g. white,bias_instability,random_walk")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    add_rate_option(p)
    add_window_options(p)
    p.set_defaults(func=run)


def temperature_at(record: Record, key: str) -> np.ndarray | None:
    """The record's temperature (degC) at each sample of channel ``key``, by linear
    interpolation in time (sample times from each series' start and rate), or None."""
    temp = record.temperature
    if temp is None or temp.n_samples == 0:
        return None
    series = record.series(key)
    t_chan = series.t0_s + np.arange(series.n_samples) / series.fs_hz
    t_temp = temp.t0_s + np.arange(temp.n_samples) / temp.fs_hz
    return np.interp(t_chan, t_temp, temp.values)


def fit_channel(record: Record, key: str, model_text: str) -> tuple[Any, Any]:
    """Fit ``model_text`` to channel ``key`` of ``record``: ``(FitResult, AllanCurve)``.

    Raises UsageError for an unknown term, a bad parameter or a record too short to fit."""
    from imunoise.analysis.fit import fit_series

    names, fixed = parse_model(model_text)
    series = record.series(key)
    temperature = temperature_at(record, key) if "temperature" in names else None
    with fit_errors(key):
        return fit_series(series.values, series.fs_hz, names,
                          segment_starts=series.segment_starts, temperature=temperature,
                          fixed=fixed, ci=CI95)


def fit_json(record: Record, key: str, result: Any, curve: Any) -> dict[str, Any]:
    """The ``fit`` JSON document of one channel (with the reader's ``warnings``, if any)."""
    from imunoise.web.views import documents

    doc = documents.channel_json(record.series(key), curve, channel=key,
                                 warnings=record.warnings, **documents.fit_fields(result, curve))
    for fact in ("timing", "motion"):
        if fact in record.facts:
            doc[fact] = record.facts[fact]
    return doc


def fit_summary(result: Any, units: str) -> str:
    """The fitted model with its intervals, the error and the failing tau ranges."""
    return "\n".join(model_lines(result, units) + failure_lines(result))


def fit_text(key: str, series: Any, result: Any, curve: Any) -> str:
    """Readable report: model with intervals, curve against model, failing ranges, error."""
    lines = [f"{key}  [{series.units}]  fs {series.fs_hz:g} Hz  {series.n_samples:,} samples  "
             f"{series.duration_s:.1f} s"]
    lines += model_lines(result, series.units)
    lines.append(f"    {'tau [s]':>10}  {'adev':>11}  {'low':>11}  {'high':>11}  "
                 f"{'model':>11}  {'z':>6}")
    model_adev = np.sqrt(result.model_avar(curve.tau_s))
    z_all = z_on_curve(result, curve)
    for i, tau in enumerate(curve.tau_s):
        z = z_all[i]
        flag = "  <" if abs(z) > result.misfit.threshold else ""
        lines.append(f"    {tau:10.4g}  {curve.dev[i]:11.4g}  {curve.ci_low[i]:11.4g}  "
                     f"{curve.ci_high[i]:11.4g}  {model_adev[i]:11.4g}  {z:6.2f}{flag}")
    lines += failure_lines(result)
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    parse_model(args.model)  # a misspelt term fails before a long read
    record, key = open_imu_channel(args.file, args.rate, args.channel, "fit", args.static)
    apply_window(record, key, args.skip, args.split)
    result, curve = fit_channel(record, key, args.model)
    if args.json:
        from imunoise.web.views import documents

        sys.stdout.write(documents.dumps(fit_json(record, key, result, curve)) + "\n")
    else:
        for w in record.warnings:
            print(f"warning: {w}", file=sys.stderr)
        print(fit_text(key, record.series(key), result, curve))
    return 0
