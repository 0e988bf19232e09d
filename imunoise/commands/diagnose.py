"""``imunoise diagnose``: fit the given model, then rank the effects it is missing.

Every term of the vocabulary that the model lacks is added in turn and the model refitted;
evidence the Allan curve cannot give joins in (spectral lines, correlation with the
temperature record, drift, a changing noise level, outliers, gaps). A suggestion is
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
from imunoise.pipeline import cross_channel
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


def _value(v: float, unit: str) -> str:
    return f"{v:.4g} {unit}".removesuffix(" 1")


def _part(value: float | None) -> str:
    """An error part for the text, "n/a" where it could not be computed."""
    return "n/a" if value is None else f"{value:.3g}"


def replicates_text(key: str, units: str, res: Any) -> str:
    """Readable report of several runs of one unit: term sets, shared shapes, per-run
    amplitudes and the parameters that differ between runs."""
    from imunoise.analysis.terms import get_term, param_unit

    def unit(term: str, name: str) -> str:
        return param_unit(next(p for p in get_term(term).params if p.name == name), units)

    lines = [f"{key}: {len(res.runs)} runs of one unit"]
    if res.per_run_terms:
        for lab, terms in zip(res.runs, res.per_run_terms, strict=True):
            lines.append(f"  {lab}: the loop alone chooses {','.join(terms)}")
        common, n = res.common_terms
        lines.append(f"  most common term set ({n} of {len(res.runs)} runs): {','.join(common)}")
    lines.append(f"  model fitted to every run: {','.join(res.term_set)}")
    lines.append("  runs (allan chi2/dof alone -> shared shapes held | the run's own fit's psd "
                 "deviance/bin | hold-out chi2/dof)")
    parts = res.error_parts or [{} for _ in res.runs]
    for lab, free, tied, p in zip(res.runs, res.free_fits, res.tied_fits, parts, strict=True):
        psd = (p.get("psd") or {}).get("deviance_per_bin")
        holdout = p.get("holdout") or {}
        changes = holdout.get("changes_free") or {}
        # a change between the run's halves is a finding: the part with it fitted says
        # whether anything else is wrong
        found = "" if changes.get("chi2_per_dof") is None else \
            f" ({_part(changes['chi2_per_dof'])} with {', '.join(changes['params'])} " \
            f"fitted on each half)"
        lines.append(f"    {lab}: {free.chi2_per_dof:.3g} -> {tied.chi2_per_dof:.3g} | psd "
                     f"{_part(psd)} | hold-out {_part(holdout.get('chi2_per_dof'))}{found}")
    lines.append(f"  shared shape parameters (95 % intervals; chi2 of the runs against the "
                 f"pooled value, * = differ at family level {res.alpha:g})")
    if not res.shared:
        lines.append("    (the model has none)")
    for h in res.shared:
        u = unit(h.term, h.param)
        mark = "*" if h.differs else " "
        lines.append(f"  {mark} {h.term:17s} {h.param:5s} = {_value(h.pooled, u)} "
                     f"[{h.ci95[0]:.4g}, {h.ci95[1]:.4g}]  chi2 {h.q:.3g} on {h.dof} dof, "
                     f"p = {h.p_value:.2g}")
    lines.append("  per-run amplitudes (95 % intervals, shared shapes held)")
    for h in res.amplitudes:
        u = unit(h.term, h.param)
        mark = "*" if h.differs else " "
        vals = ", ".join("-" if e is None else f"<{e.ci95[1]:.3g}" if e.unresolved else
                         f"{e.value:.3g} [{e.ci95[0]:.3g}, {e.ci95[1]:.3g}]"
                         for e in res.tied_values(h))
        lines.append(f"  {mark} {h.term:17s} {h.param:5s} ({u}): {vals}  chi2 {h.q:.3g} on "
                     f"{h.dof} dof (own fits)")
    differ = res.differ
    if differ:
        lines.append("  differ between runs beyond their intervals")
        for h in differ:
            u = unit(h.term, h.param)
            values = res.per_run_values(h)
            vals = ", ".join("-" if e is None else f"{e.value:.4g}" for e in values)
            peaks = [str(r + 1) for r, e in enumerate(values) if e is not None
                     and e.source == "psd"]
            src = f" (runs {', '.join(peaks)} at their spectrum's peak)" if peaks else ""
            lines.append(f"    {h.term} {h.param}: {vals} {u} by run{src}; chi2 = {h.q:.3g} "
                         f"on {h.dof} dof, p = {h.p_value:.2g}")
    else:
        lines.append("  no parameter differs between runs beyond its interval")
    return "\n".join(lines)


def run_replicates(args: argparse.Namespace) -> int:
    """Several files: replicates of one unit (see the module docstring)."""
    from imunoise.pipeline import documents
    from imunoise.pipeline.assembly import replicates_document, replicates_warnings
    from imunoise.pipeline.fitting import diagnose_replicates

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
    parse_model(args.model)  # a misspelt term fails before a long read
    if len(args.file) > 1:
        return run_replicates(args)
    args.file = args.file[0]
    record, key = open_imu_channel(args.file, args.rate, args.channel, "diagnose",
                                   args.static)
    group = cross_channel.comparison_group(record.channels, key)
    apply_window(record, key, args.skip, args.split)
    # the channels' coherence does not depend on the fit: computed beside it
    pending = cross_channel.start_channel_coherence(record, key, group, args.skip,
                                                    args.split or ())
    diag = diagnose_channel(record, key, args.model, time_origin_s=args.skip)
    for sug in diag.suggestions:
        sug.apply["args"] = full_window_args(sug.apply.get("args", []), args.skip, args.split)
    # the lines and resonances judged against the other channels: common or own
    doc, coherence = diagnosis_document(record, key, diag, group, args.skip, args.split or (),
                                        pending)
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
