"""When to poll a part that flags new data but keeps no FIFO (ADIS16350, ITG-3200).

Such a part holds one sample; the next one overwrites it, so each sample must be read between
its own appearance and the next one's. Polling at a fixed rate a little above the sample rate
lets the poll times drift through the sample period; each time they cross an appearance, a
poll only a few per cent of a period late reads nothing new and the one after it finds the
sample after next, and the lost sample cannot be told from the host's timing. Measured on the
simulated ADIS16350 at 204.8 Hz in its own process: about one such loss every 50 polls.

:class:`DataReadySchedule` locks onto the part's own sample phase instead. Each sample is
polled when it is expected; a poll that finds no new data is retried a tenth of a period later;
each poll that finds data at the first try expects the next sample a little earlier (a five
hundredth of a period), so that now and then a poll comes too early and a retry brackets the
appearance again. The polls then sit within about a tenth of a period after each appearance
(about one poll in fifty is a retry), and a poll may be late by nearly a whole period before a
sample is lost. The brackets also give :class:`imunoise.daq.drivers.common.PolledSampleClock` the
phase it counts lost samples with.
"""

from __future__ import annotations

RETRY_FRACTION = 0.1
"""A poll that found no new data is repeated this fraction of a period later."""
EARLIER_FRACTION = 0.002
"""Each poll that found data at the first try moves the next one this much earlier (periods)."""


class DataReadySchedule:
    """Poll times locked to the sample phase of a polled part.

    Args:
        period_s: the part's sample period (s).

    Use: :meth:`start` when the device is opened, then after each poll :meth:`after_poll`
    with whether it found a new sample; :attr:`due` is when the next poll should start
    (monotonic clock, s).
    """

    def __init__(self, period_s: float) -> None:
        self.period_s = float(period_s)
        self.retry_s = RETRY_FRACTION * self.period_s
        self.earlier_s = EARLIER_FRACTION * self.period_s
        self.due = 0.0
        self.locked = False
        self.retries = 0
        self._retrying = False

    def start(self, now: float) -> None:
        """Begin (or begin again after a reopen or a stall): find the phase first."""
        self.due = now
        self.locked = False
        self._retrying = False

    def after_poll(self, started: float, finished: float, fresh: bool) -> float:
        """Record a poll begun at ``started`` and ended at ``finished`` that found a new
        sample (``fresh``) or not; returns :attr:`due`."""
        planned = self.due
        if started - planned > self.period_s:
            self.locked = False  # so late that the plan says nothing about the phase now
        if not fresh:
            self.retries += 1
            self._retrying = True
            self.due = finished + self.retry_s
            return self.due
        if not self.locked:
            if not self._retrying:
                # A sample read, but when it appeared is not known: look again until a poll
                # finds nothing, and the one after it the next sample.
                self.due = finished + self.retry_s
                return self.due
            self.locked = True
            planned = started
        base = planned if self._retrying else planned - self.earlier_s
        self._retrying = False
        # A late poll moves nothing: the next sample is due a period after this one was
        # expected, and when that is already past it is read at once.
        self.due = base + self.period_s
        return self.due
