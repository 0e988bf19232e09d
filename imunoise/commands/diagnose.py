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

from imunoise.commands.common import add_rate_option, add_window_options
from imunoise.commands.fit import fit_text
from imunoise.pipeline import cross_channel
from imunoise.pipeline.assembly import diagnosis_document
from imunoise.pipeline.fitting import diagnose_channel, full_window_args, parse_model
from imunoise.pipeline.reading import apply_window, open_imu_channel


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
    add_rate_option(p)
    add_window_options(p)
    p.set_defaults(func=run)


def _suggested_param(term: str, name: str, value: float, ci: tuple[float, float] | None,
                     unit: str) -> str:
    """One parameter of a suggested term's refit; an amplitude whose interval reaches zero is
    no estimate (as in the fit's model lines), and a dimensionless unit "1" is left out."""
    from imunoise.analysis.terms import get_term

    if not get_term(term).resolved(name, ci):
        text = f"{name} not resolved (95 % upper bound {ci[1]:.4g} {unit})"
    else:
        text = f"{name} = {value:.4g} {unit}"
    return text.replace(" 1)", ")").removesuffix(" 1")


def diagnosis_text(key: str, series: Any, diag: Any, file: str = "FILE",
                   model_text: str = "TERMS") -> str:
    """Readable report: the fit, then the suggestions and the evidence."""
    from imunoise.analysis.model_error import parts_line
    from imunoise.analysis.terms import TERMS, param_unit

    u = series.units
    lines = [fit_text(key, series, diag.fit, diag.curve)]
    parts = getattr(diag, "error_parts", None)
    if parts:
        lines.append("  " + parts_line(diag.fit.chi2_per_dof, parts).replace("\n", "\n  "))
    lines += ["", "  suggestions (best first; "
              f"* = significant at family level {diag.alpha:g})"]
    for i, s in enumerate(diag.suggestions, 1):
        mark = "*" if s.significant else " "
        after = (f"{s.chi2_per_dof_after:.3g}" if np.isfinite(s.chi2_per_dof_after)
                 else "n/a")
        term = TERMS.get(s.term)
        # a warm-up or bias step is no term: its remedy cuts the record (apply.args)
        verb = "add" if term is not None else "cut"
        psd_after = ((getattr(s, "error_after", None) or {}).get("psd") or {}).get(
            "deviance_per_bin")
        psd_txt = "" if psd_after is None else f" psd/bin -> {psd_after:.3g}"
        lines.append(f"  {mark}{i:2d}. {verb} {s.term:17s} chi2/dof {s.chi2_per_dof_before:.3g} "
                     f"-> {after:8s}{psd_txt} p = {s.p_value:.2g}")
        if term is not None:
            pars = [_suggested_param(s.term, p.name, s.params[p.name], s.ci95.get(p.name),
                                     param_unit(p, u))
                    for p in term.params if p.name in s.params]
        else:
            pars = [f"{k} = {v:.4g} {'s' if k.endswith('_s') else u}"
                    for k, v in s.params.items()]
        if pars:
            lines.append(f"        {', '.join(pars)}")
        if s.significant:
            lines.append(f"        {s.why}")
    best = next((s for s in diag.suggestions if s.significant), None)
    if best is not None:
        extra = "".join(f" {a}" for a in best.apply.get("args", []))
        lines.append(f"  next: imunoise fit {file} --channel {key} "
                     f"--model {best.apply.get('model', model_text + ',' + best.term)}{extra}")
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
    parse_model(args.model)  # a misspelt term fails before a long read
    record, key = open_imu_channel(args.file, args.rate, args.channel, "diagnose",
                                   args.static)
    group = cross_channel.same_time_base(record.channels, key)
    apply_window(record, key, args.skip, args.split)
    diag = diagnose_channel(record, key, args.model, time_origin_s=args.skip)
    for sug in diag.suggestions:
        sug.apply["args"] = full_window_args(sug.apply.get("args", []), args.skip, args.split)
    # the lines and resonances judged against the other channels: common or own
    doc, coherence = diagnosis_document(record, key, diag, group, args.skip, args.split or ())
    if args.json:
        from imunoise.pipeline import documents

        sys.stdout.write(documents.dumps(doc) + "\n")
    else:
        for w in record.warnings:
            print(f"warning: {w}", file=sys.stderr)
        print(diagnosis_text(key, record.series(key), diag, args.file, args.model))
        lines = [c for c in (coherence or {}).get("classification", [])]
        if lines:
            print()
            print("  environment or sensor (coherence with the other channels)")
            for c in lines:
                print(f"    {c['term']} at {c['f_hz']:.4g} Hz: {c['origin']}. {c['why']}")
    return 0
