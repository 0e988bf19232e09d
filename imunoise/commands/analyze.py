"""``imunoise analyze``: Allan deviation, PSD and the default model fit for every channel."""

from __future__ import annotations

import argparse

from imunoise.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("analyze", help="Allan + PSD + default model fit, all channels",
                       description=__doc__)
    p.add_argument("file", help="input recording (.csv, .mcap or rosbag2 folder)")
    p.add_argument("--channel", action="append", default=[], metavar="SEL",
                   help="channel to analyse (repeatable), e.g. gyro_x or /imu:gyro_x")
    p.add_argument("--json", action="store_true", help="print JSON on stdout")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    raise UsageError("analyze: not available yet")
