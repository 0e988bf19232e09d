"""How the service's child processes take SIGTERM and Ctrl-C.

Ctrl-C reaches every process of the terminal's group; only ``serve`` acts on it, and it ends
its children in order. SIGTERM (``terminate()`` of a child that did not end when asked, or an
administrator) asks a child to end as if its parent had. The handler only sets a flag:
setting a ``multiprocessing`` Event there can wait forever, since the Event's wake-up waits
for every waiting thread to acknowledge it, and the waiting thread may be the very one the
signal interrupted. The child's loops look at the flag as often as at their stop Event.
"""

from __future__ import annotations

import signal
from typing import Any


class TermFlag:
    """True once SIGTERM has arrived (after :meth:`install`)."""

    def __init__(self) -> None:
        self.raised = False

    def install(self) -> TermFlag:
        """Handle SIGTERM with this flag and ignore SIGINT, in the calling (main) thread."""
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, self._on_term)
        return self

    def _on_term(self, signum: int, frame: object) -> None:
        self.raised = True

    def __bool__(self) -> bool:
        return self.raised


def end_process(proc: Any, stop: Any, timeout_s: float, grace_s: float = 2.0) -> None:
    """Ask a child to end (set its ``stop`` Event), wait ``timeout_s`` for it, then send it
    SIGTERM and wait ``grace_s`` more. ``proc`` may be None (never started)."""
    stop.set()
    if proc is None:
        return
    proc.join(timeout_s)
    if proc.is_alive():
        proc.terminate()
        proc.join(grace_s)
