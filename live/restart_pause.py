"""When to replace a child process that ended: at once after a long life, after a growing
pause when it keeps ending soon after its start.

A child that cannot do its work (a device that cannot be opened, a folder that cannot be
written) ends within seconds of every start; replacing it at once would spend a core on
starting interpreters. Used by the acquisition process's parent and by the acquisition
process for its recorder.
"""

from __future__ import annotations

import time
from collections.abc import Callable

QUICK_DEATH_S = 10.0
"""A child that ends sooner than this after its start counts as a quick death."""
MAX_PAUSE_S = 30.0


class RestartPause:
    """Tracks one child's starts and ends; :meth:`ended` says when to start the next.

    After a child that lived at least ``quick_s``, the next starts at once; after the n-th
    quick death in a row, after ``min(max_pause_s, 2 ** (n - 1))`` seconds (1, 2, 4 ... 30).
    Times are on ``clock`` (seconds, monotonic).
    """

    def __init__(self, quick_s: float = QUICK_DEATH_S, max_pause_s: float = MAX_PAUSE_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.quick_s = quick_s
        self.max_pause_s = max_pause_s
        self.clock = clock
        self.quick_deaths = 0
        self._started_at = clock()

    def started(self) -> None:
        """A child was started now."""
        self._started_at = self.clock()

    def ended(self) -> float:
        """The child has ended (now): when to start the next one (on ``clock``)."""
        now = self.clock()
        self.quick_deaths = self.quick_deaths + 1 if now - self._started_at < self.quick_s else 0
        pause = min(self.max_pause_s, 2.0 ** (self.quick_deaths - 1)) if self.quick_deaths else 0.0
        return now + pause


def describe_exit(code: int | None) -> str:
    """A child's exit code in words: ``exit code -9 (signal 9)``."""
    return f"exit code {code}" + (f" (signal {-code})" if code and code < 0 else "")
