"""``imunoise replay``: feed a recording through the rolling analyzer as if it were live.

Blocks are handed over on the sample clock: real time by default, ``--speed X`` times faster,
or as fast as possible with ``--speed max``. At the end a per-channel summary is printed
(samples, duration, gaps and a white-noise density estimate from first differences).
With ``--serve`` the rolling analyzer's results are served over HTTP instead (the API and
dashboard of ``imunoise serve``) until Ctrl-C.
"""

from __future__ import annotations

import argparse
import math
import sys

from imunoise.errors import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("replay", help="feed a log through the rolling analyzer as if live",
                       description=__doc__)
    p.add_argument("file", help="recording (.mcap, rosbag2 folder or .csv)")
    p.add_argument("--speed", default="1", metavar="X",
                   help="times real time (default 1); 'max' or 0 for as fast as possible")
    p.add_argument("--json", action="store_true", help="print the summary as JSON on stdout")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--serve", action="store_true",
                   help="serve the API and dashboard (as imunoise serve) while replaying, "
                        "until Ctrl-C")
    p.add_argument("--host", default="127.0.0.1",
                   help="with --serve: address to bind (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000,
                   help="with --serve: HTTP port (default 8000)")
    p.set_defaults(func=run)


def _speed(text: str) -> float | None:
    if text.strip().lower() in ("max", "inf", "0"):
        return None
    try:
        speed = float(text)
    except ValueError:
        speed = float("nan")
    if not math.isfinite(speed) or speed < 0:
        raise UsageError(f"bad speed {text!r}: a positive factor, or 'max'")
    return speed


def _consumers(summary):
    consumers = [summary]
    try:
        from imunoise.live.scheduler import RollingAnalyzer

        analyzer = RollingAnalyzer()
    except (ImportError, TypeError):  # not available, or needs set-up replay cannot give
        return consumers
    consumers.append(analyzer.update)
    return consumers


def _serve(args: argparse.Namespace, speed: float | None) -> int:
    """``imunoise serve --replay FILE`` with the blocks paced at ``speed`` (None: unpaced)."""
    from pathlib import Path

    from imunoise.commands import serve

    if not Path(args.file).exists():
        raise UsageError(f"replay: {args.file}: no such file or directory")
    sub = argparse.ArgumentParser(prog="imunoise").add_subparsers()
    serve.register(sub)
    serve_args = sub.choices["serve"].parse_args(
        ["--replay", args.file, "--host", args.host, "--port", str(args.port)])
    serve_args.speed = speed
    return serve.run(serve_args)


def _print_rows(rows: list[dict]) -> None:
    """The summary table: samples, duration, gaps and white-noise density per channel."""
    print(f"{'channel':32s} {'samples':>10s} {'duration':>10s} {'gaps':>5s}  white noise")
    for r in rows:
        n = r["white_noise_density"]
        unit = r["units"]
        head = (f"{r['channel']:32s} {r['samples']:>10d} {r['duration_s']:>9.1f}s "
                f"{r['gaps']:>5d}  ")
        if not math.isfinite(n):
            print(head + "n/a (fewer than two samples in a row)")
            continue
        if unit == "rad/s":
            conv = f"{n * 180 / math.pi * 60:.4g} deg/sqrt(h)"
        elif unit == "m/s^2":
            conv = f"{n * 60:.4g} m/s/sqrt(h)"
        else:
            conv = ""
        print(head + f"{n:.4g} {unit}/sqrt(Hz)  {conv}")


def _run_replay(blocks, total: int | None, feed, speed: float | None, show: bool) -> None:
    """Replay the blocks into ``feed``, with a progress bar when ``show``."""
    from imunoise.daq.replay import replay

    if not show:
        replay(blocks, feed, speed)
        return
    from rich.progress import Progress

    with Progress(transient=True) as bar:
        task = bar.add_task("replay", total=total or None)

        def step(block) -> None:
            if block.stream.endswith("imu") or "gyro_x" in block.channels:
                bar.advance(task, len(block))

        replay(blocks, feed, speed, progress=step)


def run(args: argparse.Namespace) -> int:
    from imunoise.daq.readers import ReadError
    from imunoise.daq.readers.mcap_scan import UnsupportedLayout
    from imunoise.daq.replay import ReplaySummary, open_blocks

    speed = _speed(args.speed)
    if args.serve:
        return _serve(args, speed)
    warnings: list[str] = []
    try:
        blocks, total = open_blocks(args.file, warnings)
    except ReadError as exc:
        raise UsageError(f"replay: {exc}") from exc
    summary = ReplaySummary()
    consumers = _consumers(summary)

    def feed(block) -> None:
        for c in consumers:
            c(block)

    try:
        _run_replay(blocks, total, feed, speed, not args.no_progress and sys.stderr.isatty())
    except ReadError as exc:
        raise UsageError(f"replay: {exc}") from exc
    except (ValueError, UnsupportedLayout) as exc:
        raise UsageError(f"replay: {args.file}: {exc}") from exc
    rows = summary.rows()
    if args.json:
        from imunoise.pipeline.documents import dumps, number

        for r in rows:
            r["white_noise_density"] = number(r["white_noise_density"])
        print(dumps({"file": args.file, "channels": rows, "warnings": warnings}))
        return 0
    for w in warnings:
        print(f"warning: {w}", file=sys.stderr)
    _print_rows(rows)
    return 0
