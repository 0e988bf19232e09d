"""``imunoise analyze``: Allan deviation, PSD and the default model fit for every channel."""

from __future__ import annotations

import argparse
import os
import sys

from imunoise.commands.common import add_rate_option
from imunoise.core.record import Record
from imunoise.errors import UsageError
from imunoise.pipeline import cross_channel
from imunoise.pipeline.channel_analysis import analyze_record
from imunoise.pipeline.documents import dataset_statement
from imunoise.pipeline.reading import read_record, select
from imunoise.progress import spinner

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
    p.add_argument("--subtract-common", action="store_true",
                   help="also analyse each channel's own noise: what the other channels "
                        "explain (their coherent part) removed, reported beside the raw "
                        "analysis with the subtraction's error (docs/environment.md)")
    p.set_defaults(func=run)


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
    from imunoise.pipeline import streamed_analysis

    if args.report:
        from imunoise.export.files import check_output_folder

        check_output_folder(args.report)
    src = streamed_analysis.stream_source(args.file, getattr(args, "stream", "auto"))
    streamed = src is not None
    subtract = bool(getattr(args, "subtract_common", False))
    if subtract and streamed:
        raise UsageError("--subtract-common needs the samples in memory: add --stream never")
    pending = None
    if streamed:
        record, results = streamed_analysis.analyze_streamed(args.file, args.channel, args.rate,
                                                             args.static, src=src)
    else:
        record = _read(args.file, args.rate, args.static)
        keys = select(record, args.channel)
        # the channels' coherence does not depend on their analyses: computed beside them
        pending = cross_channel.PendingCoherence(keys,
                                                 cross_channel.coherence_inputs(record, keys))
        results = analyze_record(record, keys)
    coherence = residuals = None
    if args.json or args.report:
        from imunoise.pipeline import documents
        from imunoise.pipeline.assembly import analysis_document, printed_analysis

        doc, coherence, residuals = analysis_document(
            args.file, record, results, streamed=streamed, subtract=subtract,
            full=bool(args.report), band_hz=args.overbound_band, pending=pending)
        if args.report:
            from imunoise.export.files import write_text_atomically
            from imunoise.export.report_html import render_report

            write_text_atomically(args.report, render_report(doc))
            print(f"wrote {args.report}", file=sys.stderr)
    if args.json:
        sys.stdout.write(documents.dumps(printed_analysis(doc)) + "\n")
    else:
        if coherence is None and not streamed:
            coherence, residuals = cross_channel.coherence_document(
                record, [r.key for r in results], subtract=subtract, pending=pending)
        _print_text(args.file, record, results, coherence, residuals)
    return 0


def _print_text(file: str, record: Record, results: list, coherence: dict | None,
                residuals: dict | None) -> None:
    """The text output: each channel's table and fit (and own noise), then the coherence."""
    from imunoise.analysis.model_error import parts_line
    from imunoise.commands.fit import fit_summary
    from imunoise.export.report_text import channel_text
    from imunoise.pipeline.documents import analyze_error_parts

    for w in record.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"{file}: {len(results)} channel(s)")
    for r in results:
        print()
        print(channel_text(r.key, r.series, r.allan, r.psd, r.warnings))
        if r.fit is not None:
            print(fit_summary(r.fit, r.series.units))
            if r.psd is not None:
                _, parts = analyze_error_parts(r)
                print("  " + parts_line(r.fit.chi2_per_dof, parts))
        for line in dataset_lines(record, r.key):
            print(line)
        if residuals and r.key in residuals:
            print(_own_text(r, residuals[r.key]))
    lines = cross_channel.coherence_lines(coherence)
    if lines:
        print()
        print("\n".join(lines))


def _own_text(r, sub) -> str:
    """The channel's own noise (common part removed) for the text output."""
    from imunoise.analysis.default_model import DEFAULT_MODEL_TEXT
    from imunoise.analysis.fit import fit_allan
    from imunoise.commands.fit import fit_summary
    from imunoise.export.report_text import channel_text
    from imunoise.pipeline.channel_analysis import allan_curve, psd_estimate

    s = r.series
    own = cross_channel.own_series(s, sub)
    e = sub.error
    lines = ["", f"{r.key} own noise (coherent part of the other channels removed: "
             f"{e['removed_share']:.1%} of the variance; at most {e['leak_share']:.1%} of the "
             f"residual is the references' noise passed in)"]
    try:
        curve = allan_curve(own)
        lines.append(channel_text(f"{r.key} (own)", own, curve, psd_estimate(own), []))
        lines.append(fit_summary(fit_allan(curve, DEFAULT_MODEL_TEXT), s.units))
        level, (lo, hi) = sub.white_level(s.fs_hz, cross_channel.OWN_TAU_S,
                                          segment_starts=own.segment_starts)
        lines.append(f"  own white level at tau = {cross_channel.OWN_TAU_S:g} s: "
                     f"{level:.4g} {s.units}/sqrt(Hz) [{lo:.4g}, {hi:.4g}]")
    except ValueError as exc:
        lines.append(f"  no own-noise analysis: {exc}")
    return "\n".join(lines)
