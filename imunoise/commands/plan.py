"""``imunoise plan``: how long a record must be for a parameter's 95 % interval to reach a target.

From a model with values (``--model white:N=3e-4,random_walk:K=2e-5 --rate 100``) or from a
recording (``FILE --channel gyro_x``: the model, default white,bias_instability,random_walk,
is fitted to it first; the answer then also says how far the recording is from the target).
Targets are relative half-widths of the 95 % interval: ``--target K=20%,B=10%`` (write
``TERM.P`` when a parameter name is in several terms). By default the interval is the one
``imunoise fit`` reports (Allan fit); ``--method likelihood`` gives the Cramer-Rao bound of the
exact Gaussian likelihood (white, gauss_markov and random_walk models only), the narrowest any
estimator can reach. The assumption behind every answer is printed with it.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from imunoise.analysis.default_model import DEFAULT_MODEL_TEXT
from imunoise.commands.common import add_rate_option
from imunoise.errors import UsageError
from imunoise.pipeline.fitting import fit_errors
from imunoise.pipeline.reading import open_imu_channel


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("plan", help="record length needed for a target interval",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", nargs="?", help="a recording to plan from (.csv, .mcap, .bag ...)")
    p.add_argument("--channel", metavar="SEL", help="channel of FILE, e.g. gyro_x")
    p.add_argument("--model", metavar="TERMS",
                   help="terms, with every value when there is no FILE (e.g. "
                        "white:N=3e-4,random_walk:K=2e-5, SI units); with FILE the terms to "
                        f"fit (default {DEFAULT_MODEL_TEXT})")
    p.add_argument("--target", required=True, metavar="P=X%",
                   help="wanted 95 %% half-widths, e.g. K=20%%,B=10%%")
    p.add_argument("--method", choices=("allan", "likelihood"), default="allan",
                   help="allan: the interval imunoise fit reports (default); likelihood: the "
                        "Cramer-Rao bound of the exact likelihood")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    add_rate_option(p)
    p.set_defaults(func=run)


def _duration(s: float) -> str:
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.1f} min"
    if s < 3 * 86400:
        return f"{s / 3600:.2f} h"
    return f"{s / 86400:.1f} days"


def _from_file(args: argparse.Namespace) -> tuple[str, float, dict[str, Any]]:
    """The fitted model as a spec with values, the rate, and facts about the recording."""
    from imunoise.analysis.fit import fit_series

    if not args.channel:
        raise UsageError("plan: give --channel with a recording (e.g. --channel gyro_x)")
    record, key = open_imu_channel(args.file, args.rate, args.channel, "plan", args.static)
    series = record.series(key)
    with fit_errors(key):
        result, _ = fit_series(series.values, series.fs_hz, args.model or DEFAULT_MODEL_TEXT,
                               segment_starts=series.segment_starts)
    spec = ",".join(t.term + "".join(f":{k}={max(v, 1e-300):.9g}" for k, v in t.params.items())
                    for t in result.terms)
    now = {f"{t.term}.{k}": ((hi - lo) / (2 * v) if v > 0 else math.inf)
           for t in result.terms for k, v in t.params.items()
           for lo, hi in [t.ci95[k]]}
    unresolved = {f"{t.term}.{k}": t.ci95[k][1] for t in result.terms for k in t.params
                  if not t.ci95[k][0] > 0.0}
    return spec, series.fs_hz, {"channel": key, "recorded_s": series.duration_s,
                                "now": now, "unresolved": unresolved,
                                "warnings": record.warnings}


def _row(p: Any, facts: dict[str, Any]) -> dict[str, Any]:
    """One target's JSON row, with the recording's state when planning from a file."""
    row = p.to_dict()
    recorded = facts.get("recorded_s")
    if recorded is None:
        return row
    name = f"{p.target.label}.{p.target.param}"
    now = facts["now"].get(name)
    row["now_relative_halfwidth"] = now if now is not None and math.isfinite(now) else None
    row["recorded_s"] = recorded
    row["more_s"] = None if p.record_s is None else max(0.0, p.record_s - recorded)
    if name in facts["unresolved"]:  # no value to plan from: say so, plan nothing
        row.update(record_s=None, reachable=False, more_s=None, now_relative_halfwidth=None,
                   unresolved_upper_bound=facts["unresolved"][name])
    return row


def _line(row: dict[str, Any], p: Any, recorded: float | None) -> str:
    """One target's text line."""
    head = f"  {p.target.param} ({p.target.label})"
    if "unresolved_upper_bound" in row:
        return (f"{head}: not resolved in this recording (95 % upper bound "
                f"{row['unresolved_upper_bound']:.4g}): nothing to plan from; state a value "
                "with --model TERMS-WITH-VALUES --rate HZ")
    line = f"{head} = {p.value:.4g}: 95 % interval within +-{100 * p.target.relative:g} % "
    line += (f"after {_duration(p.record_s)}" if p.record_s is not None else
             "not reachable (not within years of recording)")
    if recorded is None:
        return line
    now = row["now_relative_halfwidth"]
    line += (f"; now +-{100 * now:.3g} % after {_duration(recorded)}"
             if now is not None else f"; now unresolved after {_duration(recorded)}")
    if row["more_s"] is not None:
        line += ", target met" if row["more_s"] == 0 else f", {_duration(row['more_s'])} more"
    return line


def _usable_terms(model: str | None) -> None:
    """A usage error for a term that only a record's other channels define (``chain_filter``):
    a plan simulates the model's estimates with no such record."""
    from imunoise.analysis.terms import TermError, get_term, parse_model

    if not model:
        return
    try:
        names = parse_model(model).names
    except TermError as exc:
        raise UsageError(f"plan: {exc}") from None
    for name in names:
        if not get_term(name).usable():
            raise UsageError(f"plan: {name} is measured from a record's other channels "
                             f"(imunoise fit FILE --model ...,{name}); plan from the model "
                             f"without it")


def run(args: argparse.Namespace) -> int:
    from imunoise.analysis.planning import parse_targets, plan

    _usable_terms(args.model)
    if args.file:
        spec, fs, facts = _from_file(args)
    else:
        if not args.model or args.rate is None:
            raise UsageError("plan: give FILE --channel SEL, or --model TERMS-WITH-VALUES and "
                             "--rate HZ")
        spec, fs, facts = args.model, float(args.rate), {}
    try:  # a TermError is a ValueError too: one line, exit 2
        plans = plan(spec, fs, parse_targets(args.target, spec), args.method)
    except ValueError as exc:
        raise UsageError(f"plan: {exc}") from None
    rows = [_row(p, facts) for p in plans]
    if args.json:
        from imunoise.pipeline import documents

        doc = {"model": spec, "fs_hz": fs, "targets": rows,
               "assumption": plans[0].assumption if plans else ""}
        if facts:
            doc.update({"file": args.file, "channel": facts["channel"],
                        "warnings": facts["warnings"]})
        sys.stdout.write(documents.dumps(doc) + "\n")
        return 0
    for w in facts.get("warnings", []):
        print(f"warning: {w}", file=sys.stderr)
    where = f"{args.file} {facts['channel']}" if facts else "the model"
    print(f"record length for {where} at {fs:g} Hz ({args.method} method)")
    for row, p in zip(rows, plans, strict=True):
        print(_line(row, p, facts.get("recorded_s")))
    if plans:
        print(f"assumes {plans[0].assumption}")
    return 0
