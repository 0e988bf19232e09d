"""How the time-critical processes (acquisition, recorder, simulator) ask for the CPU: their
scheduling priority, the interpreter's thread switch interval and a heap whose start-up
objects the garbage collector no longer walks. Used by each of those processes, so it sits
below all of them."""

from __future__ import annotations

import gc
import os
from typing import Any

GIL_SWITCH_S = 0.0001
"""The interpreter's thread switch interval in the acquisition and simulator processes. With
the recorder's writer thread in the acquisition process, the default 5 ms let it hold up a
poll by a whole ADIS16350 period at 204.8 Hz; at 0.5 ms a 1 kHz ITG-3200 still lost 0.2 % of
its samples, at 0.1 ms 0.06 %. The recorder now has a process of its own; the simulator's
emulated bridge still runs threads."""


def settle_heap() -> None:
    """Keep the garbage collector's full passes short from here on.

    After the imports (numpy, scipy, the drivers) a full collection walks about 70,000
    objects, 36 ms of held interpreter: seven ADIS16350 samples at 204.8 Hz, and the collector
    starts one by itself every few minutes. Frozen, the objects alive at start-up are never
    walked again; what the loop allocates later is collected as usual.
    """
    gc.collect()
    gc.freeze()


def raise_priority(mode: str) -> dict[str, Any]:
    """Raise this process's scheduling priority as far as ``mode`` asks and the system
    allows; what was granted and what was refused (for /health)."""
    out: dict[str, Any] = {"asked": mode}
    if mode == "realtime" and hasattr(os, "sched_setscheduler"):
        try:
            prio = min(20, os.sched_get_priority_max(os.SCHED_FIFO))
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(prio))
            out["policy"] = f"SCHED_FIFO {prio}"
        except OSError as exc:
            out["refused"] = f"SCHED_FIFO: {exc.strerror or exc}"
    if "policy" not in out and mode in ("realtime", "nice"):
        try:
            os.nice(-10)
        except OSError as exc:
            out["refused"] = "; ".join(filter(None, [out.get("refused"),
                                                    f"nice -10: {exc.strerror or exc}"]))
        out["policy"] = "SCHED_OTHER"
    out.setdefault("policy", "SCHED_OTHER")
    out["nice"] = os.nice(0)
    return out
