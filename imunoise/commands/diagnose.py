"""``imunoise diagnose``: fit the given model, then rank the effects it is missing.

Every term of the vocabulary that the model lacks is added in turn and the model refitted;
evidence the Allan curve cannot give joins in (spectral lines, correlation with the
temperature record, drift, a changing noise level, outliers, gaps). A suggestion is
significant only when it passes the tool's own test, set so that on data the model fully
explains nothing is significant in at least 95 % of cases.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from daq.readers import ReadError, open_record
from daq.record import ChannelSelectionError, Record, select_channels
from imunoise.commands.fit import _positive_rate, fit_json, fit_text
from imunoise.errors import RuntimeFailure, UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("diagnose", help="fit, then rank the missing effects",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", help="input recording (.csv, .mcap or rosbag2 folder)")
    p.add_argument("--channel", required=True, metavar="SEL",
                   help="channel to diagnose, e.g. gyro_x or /imu:gyro_x")
    p.add_argument("--model", required=True, metavar="TERMS",
                   help="comma-separated terms of the model to test, e.g. "
                        "white,bias_instability,random_walk")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    p.add_argument("--rate", type=_positive_rate, metavar="HZ",
                   help="sampling rate in Hz (needed for a CSV without a time column 't')")
    p.set_defaults(func=run)


def diagnose_channel(record: Record, key: str, model_text: str) -> Any:
    """Run :func:`analysis.diagnosis.diagnose` on one channel of a record.

    Raises UsageError for an unknown term or a record too short to fit."""
    from analysis.diagnosis import diagnose
    from analysis.fit import parse_model_spec
    from analysis.terms import TermError

    try:
        names, fixed = parse_model_spec(model_text)
    except TermError as exc:
        raise UsageError(str(exc)) from None
    if not names:
        raise UsageError("diagnose: --model names no term")
    series = record.series(key)
    temp = record.temperature
    temperature = None
    if temp is not None and temp.n_samples >= 2:
        temperature = (temp.t0_s + np.arange(temp.n_samples) / temp.fs_hz, temp.values)
    try:
        return diagnose(series.values, series.fs_hz, names,
                        segment_starts=series.segment_starts, t0_s=series.t0_s,
                        temperature=temperature, units=series.units, fixed=dict(fixed))
    except TermError as exc:
        raise UsageError(str(exc)) from None
    except ValueError as exc:
        raise UsageError(f"{key}: {exc}") from None
    except np.linalg.LinAlgError as exc:
        raise RuntimeFailure(f"{key}: the fit failed numerically ({exc})") from None


def diagnosis_json(record: Record, key: str, diag: Any) -> dict[str, Any]:
    """``fit``'s JSON document plus ``suggestions`` (best first) and ``evidence``."""
    doc = fit_json(record, key, diag.fit, diag.curve)
    doc["suggestions"] = [s.to_dict() for s in diag.suggestions]
    doc["evidence"] = [f.to_dict() for f in diag.findings]
    return doc


def diagnosis_text(key: str, series: Any, diag: Any, file: str = "FILE",
                   model_text: str = "TERMS") -> str:
    """Readable report: the fit, then the suggestions and the evidence."""
    from analysis.terms import get_term, param_unit

    u = series.units
    lines = [fit_text(key, series, diag.fit, diag.curve), "", "  suggestions (best first; "
             f"* = significant at family level {diag.alpha:g})"]
    for i, s in enumerate(diag.suggestions, 1):
        mark = "*" if s.significant else " "
        after = (f"{s.chi2_per_dof_after:.3g}" if np.isfinite(s.chi2_per_dof_after)
                 else "n/a")
        lines.append(f"  {mark}{i:2d}. add {s.term:17s} chi2/dof {s.chi2_per_dof_before:.3g} -> "
                     f"{after:8s} p = {s.p_value:.2g}")
        term = get_term(s.term)
        pars = [f"{p.name} = {s.params[p.name]:.4g} {param_unit(p, u)}" for p in term.params
                if p.name in s.params]
        if pars:
            lines.append(f"        {', '.join(pars)}")
        if s.significant:
            lines.append(f"        {s.why}")
    best = next((s for s in diag.suggestions if s.significant), None)
    if best is not None:
        lines.append(f"  next: imunoise fit {file} --channel {key} "
                     f"--model {model_text},{best.term}")
    if best is None and diag.fit.failures:
        lines.append("  the model fails, but no single added term explains the failure: look at "
                     "the failing tau ranges above and at the evidence below")
    lines.append("")
    lines.append("  evidence")
    for f in diag.findings:
        mark = "*" if f.significant else " "
        lines.append(f"  {mark} {f.kind:16s} {f.why}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    try:
        record = open_record(args.file, rate_hz=args.rate)
    except ReadError as exc:
        raise UsageError(str(exc)) from None
    try:
        keys = select_channels(record, [args.channel])
    except ChannelSelectionError as exc:
        raise UsageError(str(exc)) from None
    key = keys[0]
    if key == "temp":
        raise UsageError("diagnose: choose an IMU channel (gyro_* or accel_*), "
                         "not the temperature")
    diag = diagnose_channel(record, key, args.model)
    if args.json:
        from imunoise import report_json

        sys.stdout.write(report_json.dumps(diagnosis_json(record, key, diag)) + "\n")
    else:
        for w in record.warnings:
            print(f"warning: {w}", file=sys.stderr)
        print(diagnosis_text(key, record.series(key), diag, args.file, args.model))
    return 0
