"""A rich progress bar on stderr for work that takes more than a few seconds."""

from __future__ import annotations

import sys

from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn


def progress_bar(enabled: bool) -> Progress:
    """A transient progress bar drawn on stderr (never stdout); a no-op when not ``enabled``.

    Use as a context manager: ``with progress_bar(big) as bar: task = bar.add_task(...)``.
    """
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed:.0f}/{task.total:.0f}"),
        TimeElapsedColumn(),
        console=Console(file=sys.stderr),
        transient=True,
        disable=not enabled,
    )
