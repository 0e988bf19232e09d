"""The ``imunoise`` command line: wires ``daq``, ``analysis`` and ``web`` together."""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import Sequence
from typing import NoReturn

from imunoise import __version__
from imunoise.core.errors import ImunoiseError
from imunoise.errors import RuntimeFailure, UsageError

MAX_MESSAGE = 300
"""Characters of the one line an error prints, ``imunoise: `` included."""

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


def one_line(exc: BaseException) -> str:
    """An error as the one line the command line prints: ``imunoise: `` first, line breaks
    joined, cut to :data:`MAX_MESSAGE` characters (quoted user data is already cut where it
    is quoted; this bounds what is not)."""
    text = " ".join(part.strip() for part in str(exc).splitlines() if part.strip())
    if not text.startswith("imunoise"):
        text = f"imunoise: {text}"
    return text if len(text) < MAX_MESSAGE else text[:MAX_MESSAGE - 4] + "..."


BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""The variables that size a BLAS library's thread pool when it loads."""


def one_blas_thread_per_process() -> None:
    """Keep each process's linear algebra on one thread, unless the user sized it.

    The commands' parallel work runs in worker processes, one per CPU
    (:mod:`imunoise.pipeline.workers`); a BLAS thread pool in each of them as well would ask
    for more threads than there are CPUs, and its threads spin waiting for work that is
    mostly small matrices (``diagnose`` on a 1e6-sample channel took 6.4 s with the default
    pools against 5.5 s without, on two CPUs). It takes effect only before numpy is
    imported, as at the command line's own start."""
    if "numpy" in sys.modules:
        return
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")


def main(argv: Sequence[str] | None = None) -> int:
    if argv is None:  # the program itself, not a caller in a running interpreter
        one_blas_thread_per_process()
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help(sys.stderr)
            return 2
        code = args.func(args)
        return int(code or 0)
    except ImunoiseError as exc:  # bad input (a ReadError too: exit 2) or a runtime failure
        print(one_line(exc), file=sys.stderr)
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
