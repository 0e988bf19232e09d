"""Rich progress displays on stderr for work that takes more than a few seconds."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
)


def progress_bar(enabled: bool) -> Progress:
    """A transient progress bar drawn on stderr (never stdout); a no-op when not ``enabled``.

    Use as a context manager: ``with progress_bar(big) as bar: task = bar.add_task(...)``;
    every task needs a ``total``.
    """
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=Console(file=sys.stderr),
        transient=True,
        disable=not enabled,
    )


def spinner(enabled: bool) -> Progress:
    """A transient spinner with elapsed time on stderr for work of unknown length."""
    return Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        TimeElapsedColumn(),
        console=Console(file=sys.stderr),
        transient=True,
        disable=not enabled,
    )
