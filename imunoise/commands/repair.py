"""``imunoise repair``: rewrite a crashed or truncated MCAP file as a clean, indexed one.

Every complete chunk is kept; a damaged tail (a chunk cut off by a crash or a full disk) is
dropped. The input is never modified unless ``--in-place`` is given.
"""

from __future__ import annotations

import argparse
import os
import struct
import sys
from pathlib import Path

from imunoise.errors import RuntimeFailure, UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("repair", help="rewrite a crashed MCAP file as a clean indexed one",
                       description=__doc__)
    p.add_argument("file", help="the .mcap file to repair")
    p.add_argument("-o", "--output", metavar="OUT",
                   help="output file (default: FILE with .repaired.mcap)")
    p.add_argument("--in-place", action="store_true",
                   help="replace FILE by the repaired file (written beside it first)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from imunoise.daq.mcap_layout import McapFormatError
    from imunoise.daq.repair import repair

    src = Path(args.file)
    if not src.is_file():
        raise UsageError(f"repair: {src}: no such file")
    if args.in_place and args.output:
        raise UsageError("repair: give either --output or --in-place")
    if args.in_place:
        dst = src.with_name(src.name + ".repairing")
    else:
        dst = Path(args.output) if args.output else src.with_name(
            src.name.removesuffix(".mcap") + ".repaired.mcap")
        if dst.resolve() == src.resolve():
            raise UsageError("repair: the output must differ from the input (or --in-place)")
    try:
        result = repair(src, dst)
    except McapFormatError as exc:
        dst.unlink(missing_ok=True)
        raise UsageError(f"repair: {src}: {exc}") from exc
    except (ValueError, struct.error, IndexError, OverflowError) as exc:  # damaged beyond use
        dst.unlink(missing_ok=True)
        raise UsageError(f"repair: {src}: damaged MCAP records ({type(exc).__name__})") from exc
    except OSError as exc:
        dst.unlink(missing_ok=True)
        raise RuntimeFailure(f"repair: {exc}") from exc
    if args.in_place:
        os.replace(dst, src)
        dst = src
    for w in result.warnings[:20]:
        print(f"warning: {w}", file=sys.stderr)
    if len(result.warnings) > 20:
        print(f"warning: ... and {len(result.warnings) - 20} more", file=sys.stderr)
    dropped = f", {result.dropped_chunks} damaged chunk(s) dropped" if \
        result.dropped_chunks else ""
    dropped += f", {result.dropped_bytes} bytes of damaged tail dropped" if \
        result.dropped_bytes else ""
    print(f"repair: {src}: {result.method}: {result.messages} messages{dropped} -> {dst}",
          file=sys.stderr)
    return 0
