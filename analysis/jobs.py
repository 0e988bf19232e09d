"""How an analysis runs its independent jobs: the caller decides.

Some analyses fall into jobs that read one shared context and do not depend on each other:
the diagnosis's candidate refits, the two halves of the hold-out part, the profile intervals
of a fit's parameters. They hand them to a *job map* ``map(fn, shared, items)``, which must
return ``[fn(shared, item) for item in items]`` in that order. This package starts no
process or thread, so its own map runs the jobs in turn; the command line passes one that
forks worker processes (:func:`imunoise.pipeline.workers.cpu_job_map`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

JobMap = Callable[[Callable[[Any, Any], Any], Any, Sequence[Any]], list[Any]]
"""``map(fn, shared, items) -> [fn(shared, item) for item in items]``."""


def serial_map(fn: Callable[[Any, Any], Any], shared: Any, items: Sequence[Any]) -> list[Any]:
    """The jobs one after the other, here."""
    return [fn(shared, item) for item in items]
