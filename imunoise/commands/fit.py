"""``imunoise fit``: fit one noise model to a channel and show where it fails.

The model is a comma-separated list of terms (listed below). A parameter written after a term
is held at that value (SI units): ``--model white,gauss_markov:T=100,random_walk``; a model
with every parameter given is evaluated as it stands. ``common_steps`` in the model takes out of
the channel, before the fit, the bias steps it takes together with the record's other channels
of its kind (a knock or a tilt of the bench; docs/environment.md).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import numpy as np

from imunoise.commands.common import (
    add_rate_option,
    add_window_options,
    failure_lines,
    model_lines,
)
from imunoise.pipeline.assembly import fit_document
from imunoise.pipeline.documents import z_on_curve
from imunoise.pipeline.fitting import fit_channel, parse_model
from imunoise.pipeline.reading import apply_window, open_imu_channel


def register(sub: argparse._SubParsersAction) -> None:
    import textwrap

    from imunoise.analysis.terms import TERMS

    names = textwrap.fill(f"Terms: {', '.join(TERMS)}.", width=92)
    p = sub.add_parser("fit", help="fit one model, show where it fails",
                       description=f"{__doc__}\n{names}",
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


def fit_summary(result: Any, units: str) -> str:
    """The fitted model with its intervals, the error and the failing tau ranges."""
    return "\n".join(model_lines(result, units) + failure_lines(result))


def chain_shape_line(shape: dict[str, Any]) -> str:
    """The sentence that says where ``chain_filter``'s response came from."""
    lo, hi = shape["reference_band_hz"]
    return (f"chain_filter: the response measured from {', '.join(shape['channels'])} of this "
            f"record (their PSDs' geometric mean, each divided by its median over "
            f"{lo:g}-{hi:g} Hz; 1 below {hi:g} Hz)")


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
    from imunoise.analysis import chain_shape
    from imunoise.pipeline import common_steps, cross_channel

    model, with_steps = common_steps.split_model(args.model)
    names, _ = parse_model(model)  # a misspelt term fails before a long read
    record, key = open_imu_channel(args.file, args.rate, args.channel, "fit", args.static)
    group = cross_channel.comparison_group(record.channels, key)
    whole = record.channels[key]
    steps = common_steps.required(common_steps.steps_of(record, key, group), key,
                                  whole.units) if with_steps else None
    if steps is not None:
        common_steps.remove_steps(record, key, steps)
    apply_window(record, key, args.skip, args.split)
    shape = cross_channel.chain_shape_source(record, key, group, whole)
    # the fit's results read the shared response whenever they evaluate the model
    with chain_shape.using(shape if "chain_filter" in names else None):
        cross_channel.require_chain_shape(names, key)
        result, curve = fit_channel(record, key, model)
        doc, parts = fit_document(record, key, model, result, curve)
        if steps is not None:
            common_steps.add_to_document(doc, steps, key)
        if args.json:
            from imunoise.pipeline import documents

            sys.stdout.write(documents.dumps(doc) + "\n")
        else:
            from imunoise.analysis.model_error import parts_line

            for w in doc.get("warnings", []):  # the reader's, and the channel's held samples
                print(f"warning: {w}", file=sys.stderr)
            print(fit_text(key, record.series(key), result, curve))
            if "chain_shape" in doc:
                print("  " + chain_shape_line(doc["chain_shape"]))
            if steps is not None:
                print("  " + common_steps.steps_line(steps, key, whole.units))
            print("  " + parts_line(result.chi2_per_dof, parts).replace("\n", "\n  "))
    return 0
