"""The ``imunoise`` command line: wires ``daq``, ``analysis`` and ``web`` together."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

from imunoise import __version__
from imunoise.errors import RuntimeFailure, UsageError

# Sub-command modules under imunoise.commands, in the order --help lists them.
COMMAND_MODULES: list[str] = [
    "analyze",
    "fit",
    "diagnose",
    "reproduce",
    "record",
    "serve",
    "replay",
    "repair",
    "export_kalibr",
    "plan",
    "fleet",
    "fleet_report",
]


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors are one line on stderr and exit code 2.

    Command descriptions are the modules' docstrings; their reStructuredText literal marks
    are dropped for the terminal.
    """

    def __init__(self, *args, **kwargs) -> None:
        if kwargs.get("description"):
            kwargs["description"] = kwargs["description"].replace("``", "")
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        raise UsageError(f"{self.prog}: {message}")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="imunoise",
        description="Characterise MEMS inertial sensors: record, Allan variance and PSD, "
        "noise-model fits, and a diagnosis of what the model misses.",
    )
    parser.add_argument("--version", action="version", version=f"imunoise {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    for name in COMMAND_MODULES:
        importlib.import_module(f"imunoise.commands.{name}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help(sys.stderr)
            return 2
        code = args.func(args)
        return int(code or 0)
    except (UsageError, RuntimeFailure) as exc:
        print(f"imunoise: {exc}" if not str(exc).startswith("imunoise") else str(exc),
              file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("imunoise: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader of stdout went away (``imunoise analyze --json | head``): stop quietly,
        # and keep the interpreter's final flush from failing again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except OSError as exc:  # disk full, permission denied ... where no command caught it
        where = f": {exc.filename}" if getattr(exc, "filename", None) else ""
        print(f"imunoise: {exc.strerror or exc}{where}", file=sys.stderr)
        return RuntimeFailure.exit_code


if __name__ == "__main__":
    sys.exit(main())
