"""``imunoise diagnose``: fit the given model, then rank the effects it is missing.

Every term of the vocabulary that the model lacks is added in turn and the model refitted;
evidence the Allan curve cannot give joins in (spectral lines, correlation with the
temperature record, drift, a changing noise level, outliers, gaps). Where the channel steps
together with the record's other channels of its kind (the bench knocked or tilted), taking
those steps out (``common_steps``) is a suggestion too. A suggestion is
significant only when it passes the tool's own test, set so that on data the model fully
explains nothing is significant in at least 95 % of cases.

Several files are replicates: recordings of one unit. Each run is diagnosed alone (``--rounds``
rounds of the loop, as on that file by itself: the top significant suggestion applied, a term
or a cut of that run), the runs side by side on the CPUs; the most common term set is fitted to
every run, the shape parameters (correlation times, resonance and line frequencies, quality
factors, filter cutoffs and taps) are tested for agreement across runs and shared, the
amplitudes refitted per run, and the parameters that differ between runs beyond their
intervals are named.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

import numpy as np

from imunoise.commands.common import add_rate_option, add_window_options
from imunoise.commands.fit import fit_text
from imunoise.errors import UsageError
from imunoise.pipeline import common_steps, cross_channel
from imunoise.pipeline.assembly import diagnosis_document
from imunoise.pipeline.fitting import diagnose_channel, full_window_args, parse_model
from imunoise.pipeline.reading import apply_window, open_imu_channel


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("diagnose", help="fit, then rank the missing effects",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", nargs="+", metavar="FILE",
                   help="input recording (.csv, .mcap or rosbag2 folder); several files are "
                        "replicates of one unit")
    p.add_argument("--channel", required=True, metavar="SEL",
                   help="channel to diagnose, e.g. gyro_x or /imu:gyro_x")
    p.add_argument("--model", required=True, metavar="TERMS",
                   help="comma-separated terms of the model to test, e.g. "
                        "white,bias_instability,random_walk")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    p.add_argument("--rounds", type=_rounds, default=4, metavar="R",
                   help="with several files: rounds of the diagnosis loop run on each file "
                        "alone to choose the unit's term set (0: fit --model as given; "
                        "default 4)")
    add_rate_option(p)
    add_window_options(p)
    p.set_defaults(func=run)


def _rounds(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        value = -1
    if value < 0:
        raise argparse.ArgumentTypeError(f"--rounds {text!r}: a whole number >= 0")
    return value


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
    held: list[str] = []  # strong evidence, held back (their reason is printed)
    for i, s in enumerate(diag.suggestions, 1):
        mark = "*" if s.significant else " "
        after = (f"{s.chi2_per_dof_after:.3g}" if np.isfinite(s.chi2_per_dof_after)
                 else "n/a")
        term = TERMS.get(s.term)  # a warm-up or bias step is no term: its remedy is a cut
        verb, name = s.action, s.label or s.term
        psd_after = ((getattr(s, "error_after", None) or {}).get("psd") or {}).get(
            "deviance_per_bin")
        psd_txt = "" if psd_after is None else f" psd/bin -> {psd_after:.3g}"
        lines.append(f"  {mark}{i:2d}. {verb} {name:17s} chi2/dof {s.chi2_per_dof_before:.3g} "
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
        elif s.p_value < diag.alpha and s.held_by:
            held.append(name)
            lines.append(f"        held back: {s.held_reason}")
    best = next((s for s in diag.suggestions if s.significant), None)
    if best is not None:
        extra = "".join(f" {a}" for a in best.apply.get("args", []))
        lines.append(f"  next: imunoise fit {file} --channel {key} "
                     f"--model {best.apply.get('model', model_text + ',' + best.term)}{extra}")
    if best is None and diag.fit.failures and held:
        lines.append(f"  the model fails; {', '.join(held)} lower its error but are held back "
                     "for the reason each states: added alone they do not describe the sensor "
                     "better. Look at the failing tau ranges above, the hold-out findings and "
                     "the evidence below; a term they make redundant may need to go first")
    elif best is None and diag.fit.failures:
        lines.append("  the model fails, but no single added term explains the failure: look at "
                     "the failing tau ranges above and at the evidence below")
    lines.append("")
    lines.append("  evidence")
    for f in diag.findings:
        mark = "*" if f.significant else " "
        lines.append(f"  {mark} {f.kind:16s} {f.why}")
    return "\n".join(lines)


def run_replicates(args: argparse.Namespace) -> int:
    """Several files: replicates of one unit (see the module docstring)."""
    from imunoise.pipeline import documents
    from imunoise.pipeline.assembly import replicates_document, replicates_warnings
    from imunoise.pipeline.fitting import diagnose_replicates
    from imunoise.pipeline.replicates_text import replicates_text

    _distinct_files(args.file)
    records = []
    key = ""
    for path in args.file:
        try:
            record, key_i = open_imu_channel(path, args.rate, args.channel, "diagnose",
                                             args.static)
        except UsageError as exc:
            # a reading error names its file already; a channel missing from one of the
            # runs would not say which
            raise UsageError(str(exc) if path in str(exc) else f"{path}: {exc}") from exc
        if key and key_i != key:
            raise UsageError(f"diagnose: --channel {args.channel} is {key} in "
                             f"{args.file[0]} but {key_i} in {path}")
        key = key_i
        try:
            apply_window(record, key, args.skip, args.split)
        except UsageError as exc:
            raise UsageError(f"{path}: {exc}") from exc
        records.append((path, record))
    res = diagnose_replicates(records, key, args.model, args.rounds)
    if args.json:
        doc = replicates_document(records, key, args.model, res)
        sys.stdout.write(documents.dumps(doc) + "\n")
    else:
        for w in replicates_warnings(records, key):
            print(f"warning: {w}", file=sys.stderr)
        print(replicates_text(key, records[0][1].series(key).units, res))
    return 0


def _distinct_files(paths: list[str]) -> None:
    """A usage error where one file is given twice: a replicate is another recording, and a
    run compared with itself agrees by construction."""
    seen: dict[str, str] = {}
    for path in paths:
        real = os.path.realpath(path)
        if real in seen:
            raise UsageError(f"diagnose: {path} is {seen[real]} again: replicates are "
                             f"different recordings of one unit, each file once")
        seen[real] = path


def run(args: argparse.Namespace) -> int:
    from imunoise.analysis import chain_shape

    model, with_steps = common_steps.split_model(args.model)
    parse_model(model)  # a misspelt term fails before a long read
    if len(args.file) > 1:
        if with_steps:
            raise UsageError(f"diagnose: {common_steps.TERM} is found per record; diagnose "
                             f"the replicates without it")
        return run_replicates(args)
    args.file = args.file[0]
    record, key = open_imu_channel(args.file, args.rate, args.channel, "diagnose",
                                   args.static)
    group = cross_channel.comparison_group(record.channels, key)
    whole = record.channels[key]
    found = common_steps.steps_of(record, key, group)
    # taken out of the channel (the model names them), or offered as a suggestion
    removed = common_steps.required(found, key, whole.units) if with_steps else None
    offered = found if not with_steps and found is not None and found.of(key) else None
    if removed is not None:
        common_steps.remove_steps(record, key, removed)
    # the record with the steps taken out, cut below as the channel is, for the suggestion
    without_steps = common_steps.corrected_copy(record, key, offered) if offered else None
    apply_window(record, key, args.skip, args.split)
    # the channels' coherence does not depend on the fit: computed beside it
    pending = cross_channel.start_channel_coherence(record, key, group, args.skip,
                                                    args.split or ())
    names, _ = parse_model(model)
    shape = cross_channel.chain_shape_source(
        record, key, group, whole, None if args.skip or args.split else pending)
    with chain_shape.using(shape):
        cross_channel.require_chain_shape(names, key)  # measured now if the model names it
        diag = diagnose_channel(record, key, model, time_origin_s=args.skip)
        if removed is not None:
            common_steps.keep_in_applies(diag.suggestions)
        elif offered is not None and without_steps is not None:
            diag.suggestions = common_steps.rank_removal(
                diag, without_steps, whole, key, offered, model, args.skip, args.split or [])
        for sug in diag.suggestions:
            sug.apply["args"] = full_window_args(sug.apply.get("args", []), args.skip,
                                                 args.split)
        # the lines and resonances judged against the other channels: common or own
        doc, coherence = diagnosis_document(record, key, diag, group, args.skip,
                                            args.split or (), pending)
        if removed is not None:
            common_steps.add_to_document(doc, removed, key)
        if args.json:
            from imunoise.pipeline import documents

            sys.stdout.write(documents.dumps(doc) + "\n")
        else:
            for w in record.warnings:
                print(f"warning: {w}", file=sys.stderr)
            print(diagnosis_text(key, record.series(key), diag, args.file, args.model))
            if removed is not None:
                print("  " + common_steps.steps_line(removed, key, whole.units))
            lines = [c for c in (coherence or {}).get("classification", [])]
            if lines:
                print()
                print("  environment or sensor (coherence with the other channels)")
                for c in lines:
                    print(f"    {c['term']} at {c['f_hz']:.4g} Hz: {c['origin']}. {c['why']}")
            shapes = [s for s in (coherence or {}).get("shared_shapes", [])
                      if key in s.get("channels", [])]
            if shapes:
                print()
                print("  the channel's spectral shape (against the other channels)")
                for s in shapes:
                    print(f"    {s['text']}")
    return 0
