"""``imunoise analyze``: Allan deviation, PSD and the default model fit for every channel."""

from __future__ import annotations

import argparse
import os
import sys
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from imunoise.commands.common import add_rate_option, read_record, select
from imunoise.core.record import Record
from imunoise.core.series import ChannelSeries
from imunoise.core.units import CI95
from imunoise.progress import progress_bar, spinner

if TYPE_CHECKING:  # scipy-backed modules load only when a command runs, not for --help
    from imunoise.analysis.psd import PsdEstimate

"""Confidence level of the Allan and PSD intervals in the output."""

# Samples (summed over channels) above which the work takes more than a few seconds.
_PROGRESS_SAMPLES = 2_000_000
_PROGRESS_FILE_BYTES = 30_000_000


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("analyze", help="Allan + PSD + default model fit, all channels",
                       description=__doc__)
    p.add_argument("file", help="input recording (.csv, .mcap or rosbag2 folder)")
    p.add_argument("--channel", action="append", default=[], metavar="SEL",
                   help="channel to analyse (repeatable), e.g. gyro_x or /imu:gyro_x; "
                        "default: every IMU channel")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    add_rate_option(p)
    p.add_argument("--overbound-band", type=_band, metavar="LO:HI",
                   help="frequency band (Hz) where the over-bounding model must also lie on or "
                        "above the measured PSD's upper 95 %% bound (default: Allan only)")
    p.add_argument("--stream", choices=("auto", "always", "never"), default="auto",
                   help="read an MCAP file in two bounded-memory passes instead of loading it: "
                        "'auto' (default) when its IMU samples would take more than 160 MB "
                        "(about 9 h of six channels at 100 Hz); Allan deviation exact up to "
                        "m = 4096 and strided beyond, no diagnosis in --report "
                        "(docs/analyze.md)")
    p.add_argument("--report", metavar="OUT.html",
                   help="also write a self-contained HTML report (plots, coefficients, "
                        "discrete-time model, diagnosis) to OUT.html")
    p.set_defaults(func=run)


@dataclass
class ChannelAnalysis:
    """What ``analyze`` computed for one channel."""

    key: str
    series: ChannelSeries
    allan: Any | None = None  # imunoise.analysis.allan.AllanCurve
    psd: PsdEstimate | None = None
    fit: Any | None = None  # imunoise.analysis.fit.FitResult of DEFAULT_MODEL
    warnings: list[str] = field(default_factory=list)


DEFAULT_MODEL = "white,bias_instability,random_walk"
"""The model ``analyze`` fits to every channel."""


def _band(text: str) -> tuple[float, float]:
    """argparse type of ``--overbound-band LO:HI`` (Hz)."""
    lo, sep, hi = text.partition(":")
    try:
        band = (float(lo), float(hi))
    except ValueError:
        raise argparse.ArgumentTypeError(f"bad band {text!r}: write LO:HI in Hz, e.g. 0.1:20"
                                         ) from None
    if not sep or not 0 <= band[0] < band[1]:
        raise argparse.ArgumentTypeError(f"bad band {text!r}: need 0 <= LO < HI (Hz)")
    return band


def _fit(out: ChannelAnalysis) -> None:
    from imunoise.analysis.fit import fit_allan
    from imunoise.analysis.terms import TermError

    if out.allan is None:
        return
    try:
        out.fit = fit_allan(out.allan, DEFAULT_MODEL)
    except (TermError, ValueError, np.linalg.LinAlgError) as exc:
        out.warnings.append(f"no model fit: {exc}")


def _allan(series: ChannelSeries, out: ChannelAnalysis) -> None:
    from imunoise.analysis.allan import oadev

    try:
        out.allan = oadev(series.values, series.fs_hz, m="octave",
                          segment_starts=series.segment_starts, ci=CI95)
    except ValueError as exc:
        out.warnings.append(f"no Allan deviation: {exc}")


def _psd(series: ChannelSeries, out: ChannelAnalysis) -> None:
    from imunoise.analysis.psd import default_nperseg, log_psd

    bounds = np.append(series.segment_starts, series.n_samples)
    longest = int(np.max(np.diff(bounds))) if series.n_samples else 0
    try:
        out.psd = log_psd(series.values, series.fs_hz, segment_starts=series.segment_starts,
                          ci=CI95, nperseg=default_nperseg(longest))
    except ValueError as exc:
        out.warnings.append(f"no PSD: {exc}")


def analyze_record(record: Record, keys: list[str], show_progress: bool | None = None
                   ) -> list[ChannelAnalysis]:
    """Allan deviation and PSD of the selected channels of a record."""
    total = sum(record.series(k).n_samples for k in keys)
    if show_progress is None:
        show_progress = total > _PROGRESS_SAMPLES
    results = []
    with progress_bar(show_progress) as bar:
        task = bar.add_task("analysing", total=2 * len(keys))
        for key in keys:
            series = record.series(key)
            out = ChannelAnalysis(key=key, series=series)
            bar.update(task, description=f"{key}: Allan deviation")
            _allan(series, out)
            _fit(out)
            bar.advance(task)
            bar.update(task, description=f"{key}: PSD")
            _psd(series, out)
            bar.advance(task)
            results.append(out)
    return results


def analysis_json(path: str, record: Record, results: list[ChannelAnalysis]) -> dict[str, Any]:
    """The ``analyze`` JSON document of analysed channels."""
    from imunoise.web.views import documents
    from imunoise.web.views.documents import fit_fields

    channels = {
        r.key: documents.channel_json(r.series, r.allan, psd=r.psd, include_psd=True,
                                        warnings=r.warnings, channel=r.key,
                                        **(fit_fields(r.fit, r.allan) if r.fit else {}))
        for r in results
    }
    doc = documents.analyze_json(path, channels, record.warnings)
    stated = dataset_statement(record)
    if stated:
        doc["dataset"] = stated
    for key in ("timing", "motion"):
        if key in record.facts:
            doc[key] = record.facts[key]
    return doc


def dataset_statement(record: Record) -> dict[str, Any]:
    """What a dataset's own ``sensor.yaml`` states (EuRoC/ASL layout), to show beside the
    measured values: ``{"sensor_yaml": path, "rate_hz": ..., "gyroscope_noise_density": ...}``."""
    md = record.metadata
    out: dict[str, Any] = {}
    for key, value in md.items():
        if key == "dataset_sensor_yaml":
            out["sensor_yaml"] = value
        elif key.startswith("dataset_"):
            out[key.removeprefix("dataset_")] = float(value)
    return out


def dataset_lines(record: Record, key: str) -> list[str]:
    """The dataset's stated noise figures for one channel's kind, for the text output."""
    stated = dataset_statement(record)
    kind = "gyroscope" if key.split(":")[-1].startswith("gyro") else "accelerometer"
    units = {"gyroscope": ("rad/s/sqrt(Hz)", "rad/s^2/sqrt(Hz)"),
             "accelerometer": ("m/s^2/sqrt(Hz)", "m/s^3/sqrt(Hz)")}[kind]
    parts = [f"{name} {stated[name]:.4g} {unit}"
             for name, unit in ((f"{kind}_noise_density", units[0]),
                                (f"{kind}_random_walk", units[1])) if name in stated]
    if not parts:
        return []
    return [f"  stated by {stated.get('sensor_yaml', 'sensor.yaml')} (not measured): "
            + ", ".join(parts) + "; compare N and K above"]


def _read(path: str, rate_hz: float | None, static: str = "auto") -> Record:
    big = os.path.isfile(path) and os.path.getsize(path) > _PROGRESS_FILE_BYTES
    with spinner(big) as bar:
        bar.add_task(f"reading {path}", total=None)
        return read_record(path, rate_hz, static)


def run(args: argparse.Namespace) -> int:
    from imunoise import streamed_analysis

    if args.report:
        from imunoise.files import check_output_folder

        check_output_folder(args.report)
    src = streamed_analysis.stream_source(args.file, getattr(args, "stream", "auto"))
    streamed = src is not None
    if streamed:
        record, results = streamed_analysis.analyze_streamed(args.file, args.channel, args.rate,
                                                             args.static, src=src)
    else:
        record = _read(args.file, args.rate, args.static)
        keys = select(record, args.channel)
        results = analyze_record(record, keys)
    if args.json or args.report:
        from imunoise import outputs
        from imunoise.web.views import documents

        doc = outputs.complete_document(analysis_json(args.file, record, results), record,
                                        full=bool(args.report), band_hz=args.overbound_band,
                                        diagnose=not streamed)
        if args.report:
            from imunoise.files import write_text_atomically
            from imunoise.report_html import render_report

            write_text_atomically(args.report, render_report(doc))
            print(f"wrote {args.report}", file=sys.stderr)
    if args.json:
        sys.stdout.write(documents.dumps(outputs.without_report_extras(doc)) + "\n")
    else:
        from imunoise.commands.fit import fit_summary
        from imunoise.report_text import channel_text

        for w in record.warnings:
            print(f"warning: {w}", file=sys.stderr)
        print(f"{args.file}: {len(results)} channel(s)")
        for r in results:
            print()
            print(channel_text(r.key, r.series, r.allan, r.psd, r.warnings))
            if r.fit is not None:
                print(fit_summary(r.fit, r.series.units))
            for line in dataset_lines(record, r.key):
                print(line)
    return 0
