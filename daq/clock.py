"""Time sources for acquisition and simulators.

Acquisition paces a device by sample counts against a monotonic clock. A simulated device and
its acquisition loop can share a :class:`VirtualClock`, whose ``sleep`` advances time instantly,
so a simulated hour runs in seconds while every driver, transport and pacing path still runs.
"""

from __future__ import annotations

import heapq
import threading
import time
from collections.abc import Callable


class RealClock:
    """The host's monotonic clock (seconds) and an epoch anchor for sample times."""

    realtime = True

    def __init__(self) -> None:
        self._mono0 = time.monotonic()
        self._epoch0 = time.time()

    def now(self) -> float:
        """Monotonic time in seconds."""
        return time.monotonic()

    def wall(self) -> float:
        """Epoch seconds that advance with :meth:`now` (no steps from NTP corrections)."""
        return self._epoch0 + (time.monotonic() - self._mono0)

    def sleep(self, dt: float) -> None:
        if dt > 0:
            time.sleep(dt)

    def sleep_until(self, t: float) -> None:
        self.sleep(t - self.now())


class VirtualClock:
    """Simulated time (seconds) that only moves when someone sleeps or calls :meth:`advance`.

    Thread-safe: a simulator thread may read it while the acquisition thread advances it.
    """

    realtime = False

    def __init__(self, start: float = 0.0, epoch0: float | None = None) -> None:
        self._t = float(start)
        self._epoch0 = time.time() if epoch0 is None else float(epoch0)
        self._lock = threading.Lock()
        self._timers: list[tuple[float, int, Callable[[], None]]] = []
        self._seq = 0

    def call_at(self, t: float, fn: Callable[[], None]) -> None:
        """Run ``fn`` once simulated time reaches ``t`` (for scripted faults in tests)."""
        with self._lock:
            self._seq += 1
            heapq.heappush(self._timers, (t, self._seq, fn))
        self._run_timers()

    def _run_timers(self) -> None:
        while True:
            with self._lock:
                if not self._timers or self._timers[0][0] > self._t:
                    return
                _, _, fn = heapq.heappop(self._timers)
            fn()

    def now(self) -> float:
        with self._lock:
            return self._t

    def wall(self) -> float:
        return self._epoch0 + self.now()

    def advance(self, dt: float) -> None:
        if dt > 0:
            with self._lock:
                self._t += dt
            self._run_timers()

    def sleep(self, dt: float) -> None:
        self.advance(dt)

    def sleep_until(self, t: float) -> None:
        with self._lock:
            if t > self._t:
                self._t = t
        self._run_timers()


Clock = RealClock | VirtualClock
