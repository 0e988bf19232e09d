"""``imunoise reproduce``: the seed papers' figures beside ours, with a verdict per line.

``petkov2010``: Petkov & Slavov (2010), ADIS16350 noise model (Markov coefficient, driving
noise, white level from the rms, re-estimate of the fitted gyro and accelerometer models).
``hemerly2017``: Hemerly (2017), ARMA(0,1) relations, condition number of the moment
equations, and a Monte Carlo of Allan-asymptote errors.
"""

from __future__ import annotations

import argparse
import json
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reproduce", help="recompute a seed paper's figures",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("paper", choices=["petkov2010", "hemerly2017"], help="which paper")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    p.add_argument("--seed", type=int, default=None,
                   help="seed of the simulations (default 2010 for petkov2010, 2017 for "
                        "hemerly2017, so runs repeat)")
    p.set_defaults(func=run)


def _fmt(v: float | None) -> str:
    return "-" if v is None else f"{v:.6g}"


def run(args: argparse.Namespace) -> int:
    from imunoise.analysis.reproduce import PAPERS

    fn = PAPERS[args.paper]
    rows = fn() if args.seed is None else fn(seed=args.seed)
    if args.json:
        sys.stdout.write(json.dumps({"paper": args.paper,
                                     "rows": [r.to_dict() for r in rows]}) + "\n")
        return 0
    w = max(len(r.quantity) for r in rows)
    print(f"{'quantity':{w}s}  {'paper':>12s}  {'ours':>12s}  unit           verdict")
    for r in rows:
        print(f"{r.quantity:{w}s}  {_fmt(r.paper):>12s}  {_fmt(r.ours):>12s}  {r.unit:14s} "
              f"{r.verdict}")
    return 0
