"""The acquisition loop: paces a device driver at its rate and hands out sample blocks.

A part that flags new data but keeps no FIFO (the driver says so with ``polls_data_ready``)
is polled on its own sample phase (:class:`imunoise.daq.poll_schedule.DataReadySchedule`). Other
drivers (FIFO drains, replay) are paced by count: the k-th poll is due at
``t_start + k * period`` on a monotonic clock, so oversleeping one poll never shifts the next
ones and nothing drifts over hours. Transient
faults (timeouts, garbage, NACK bursts, an unplugged cable, stuck data-ready) close the device
and reopen it with backoff; the samples lost meanwhile show up as ``gap_before`` of the next
block. Permanent faults, or an outage longer than ``max_outage_s``, end the loop with
:class:`~imunoise.daq.errors.AcquisitionFailed` and the state ``"failed: <reason>"``.
"""

from __future__ import annotations

import math
import re
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Protocol

from imunoise.core.blocks import SampleBlock
from imunoise.daq.clock import Clock, RealClock
from imunoise.daq.drivers.common import StreamBuffer
from imunoise.daq.errors import AcquisitionFailed, DeviceError, PermanentDeviceError
from imunoise.daq.poll_schedule import DataReadySchedule

LATE_SKIP_PERIODS = 2.0  # polls this far behind schedule re-anchor it (no burst catch-up)
LATE_SKIP_MIN_S = 0.02
HANDOUT_SLACK_PERIODS = 0.7
"""Blocks are handed out right after a poll that leaves at least this many poll periods
before the next one is due, so that the consumer's work (under ``serve``, pickling the blocks
for the analysis side's and the recorder's rings) falls where it delays no poll; a hand-out
waits at most one more ``block_s`` for such a poll. The simulated ADIS16350 leaves that much
after 96 % of its polls, the 1 kHz razor (gyro read and accelerometer drain) after 30 %. The
1 kHz razor with its recorder's writer thread in-process (as it then was), 25 s runs
interleaved: fewer samples missed in five pairs of six (71 against 170 on a quiet host); under
``serve`` (bench/serve.py, 3 min idle) 198 and 170 lost against 242 and 299 handing out at the
first poll past ``block_s``."""


class Driver(Protocol):
    """What the loop needs from a device driver.

    A driver of a part without a FIFO may also set ``polls_data_ready = True`` and, after each
    poll, ``found_new_sample`` (whether that poll found a new sample of the part it locks to);
    the loop then polls on the part's sample phase.
    """

    name: str
    rate_hz: float
    poll_period_s: float
    config: dict[str, str]

    def open(self) -> None: ...

    def close(self) -> None: ...

    def poll(self) -> int: ...

    def take_blocks(self) -> list[SampleBlock]: ...

    @property
    def streams(self) -> list[StreamBuffer]: ...


@dataclass
class AcquisitionStats:
    """Counters of one acquisition run.

    Attributes:
        samples: samples delivered, all IMU streams together.
        dropped: samples known to be missing (sum of ``gap_before``).
        gaps: number of gaps.
        reconnects: successful reopenings after a fault.
        jitter_s: rms lateness of the polls behind their schedule (s).
        max_late_s: worst lateness (s).
        drift_ppm: host clock minus device clock over the run, parts per million.
        state: ``"running"``, ``"reconnecting"``, ``"stopped"`` or ``"failed: reason"``.
        last_error: the most recent fault message.
        faults: count of faults per kind of message.
    """

    samples: int = 0
    dropped: int = 0
    gaps: int = 0
    reconnects: int = 0
    jitter_s: float = 0.0
    max_late_s: float = 0.0
    drift_ppm: float = 0.0
    state: str = "stopped"
    last_error: str = ""
    faults: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        return dict(self.__dict__)


class Acquisition:
    """A device being recorded: ``for block in acq.blocks(60): ...``.

    Args:
        driver: the device driver.
        clock: time source shared with a simulator, or the host clock.
        block_s: how often buffered samples are handed out (s of data per block).
        max_outage_s: give up when the device stays unreachable this long.
        on_close: extra clean-up (simulator threads) run by :meth:`close`.
    """

    def __init__(self, driver: Driver, *, clock: Clock | None = None, block_s: float = 0.1,
                 max_outage_s: float = 30.0,
                 on_close: list[Callable[[], None]] | None = None) -> None:
        self.driver = driver
        self.clock = clock or RealClock()
        self.block_s = block_s
        self.max_outage_s = max_outage_s
        self.stats = AcquisitionStats()
        self.simulator: object | None = None
        self._on_close = on_close or []
        self._stop = threading.Event()
        self._opened = False
        self._late_sq = 0.0
        self._late_n = 0
        self._outage_since: float | None = None

    @property
    def config(self) -> dict[str, str]:
        return dict(self.driver.config)

    @property
    def rate_hz(self) -> float:
        return self.driver.rate_hz

    def open(self) -> None:
        """Connect and configure the device; DeviceError with the reason if it cannot."""
        if not self._opened:
            self.driver.open()
            self._opened = True
            self.stats.state = "running"

    def stop(self) -> None:
        """Ask :meth:`blocks` to finish after handing out what it has (thread-safe)."""
        self._stop.set()

    def close(self) -> None:
        """Stop, close the device and release simulators; safe to call twice."""
        self._stop.set()
        if self._opened:
            self.driver.close()
            self._opened = False
        for fn in self._on_close:
            fn()
        self._on_close = []
        if not self.stats.state.startswith("failed"):
            self.stats.state = "stopped"

    def __enter__(self) -> Acquisition:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- the loop --------------------------------------------------------------------------
    def blocks(self, duration_s: float | None = None) -> Iterator[SampleBlock]:
        """Sample blocks until ``duration_s`` of device time has passed, or :meth:`stop`."""
        for batch in self.batches(duration_s):
            yield from batch

    def batches(self, duration_s: float | None = None) -> Iterator[list[SampleBlock]]:
        """:meth:`blocks`, those handed out together (every ``block_s``) as one list (never
        empty), so that a consumer can do its most urgent work with all of them first."""
        self.open()
        clock = self.clock
        period = self.driver.poll_period_s
        schedule = (DataReadySchedule(1.0 / self.driver.rate_hz)
                    if getattr(self.driver, "polls_data_ready", False) else None)
        t_start = clock.now()
        t_end = math.inf if duration_s is None else t_start + duration_s
        if schedule is not None:
            schedule.start(t_start)
        k = 0
        next_flush = t_start + self.block_s
        while not self._stop.is_set():
            due = schedule.due if schedule is not None else t_start + k * period
            if due >= t_end or clock.now() >= t_end:
                break
            clock.sleep_until(due)
            now = clock.now()
            late = now - due
            self._note_late(late)
            k += 1
            if schedule is None and late > max(LATE_SKIP_PERIODS * period, LATE_SKIP_MIN_S):
                # The host fell behind (slow bus, busy machine): polling in a burst to
                # catch up would only re-read the newest sample, so restart the schedule.
                t_start, k = now, 1
            try:
                found = self.driver.poll()
                if found > 0:
                    self._outage_since = None
            except PermanentDeviceError as exc:
                yield from self._flush()
                self._fail(str(exc))
            except DeviceError as exc:
                yield from self._flush()
                self._recover(exc)
                t_start, k = clock.now(), 0
                if schedule is not None:
                    schedule.start(t_start)
                continue
            if schedule is not None:
                schedule.after_poll(now, clock.now(),
                                    bool(getattr(self.driver, "found_new_sample", found > 0)))
            if now >= next_flush and (now >= next_flush + self.block_s
                                      or self._slack_periods(schedule, t_start, k, period)
                                      >= HANDOUT_SLACK_PERIODS):
                yield from self._flush()
                next_flush = max(next_flush + self.block_s, now)
        yield from self._flush()
        if self.stats.state == "running":
            self.stats.state = "stopped"

    def _slack_periods(self, schedule: DataReadySchedule | None, t_start: float, k: int,
                       period: float) -> float:
        """Time from now to the next poll, in poll periods."""
        now = self.clock.now()
        if schedule is not None:
            return (schedule.due - now) / schedule.period_s
        return (t_start + k * period - now) / period if period > 0 else math.inf

    def _note_late(self, late: float) -> None:
        late = max(0.0, late)
        self._late_sq += late * late
        self._late_n += 1
        self.stats.jitter_s = math.sqrt(self._late_sq / self._late_n)
        self.stats.max_late_s = max(self.stats.max_late_s, late)

    def _flush(self) -> Iterator[list[SampleBlock]]:
        batch = self.driver.take_blocks()
        for block in batch:
            if block.stream.endswith("/imu"):
                self.stats.samples += len(block)
                if block.gap_before > 0:
                    self.stats.dropped += block.gap_before
                    self.stats.gaps += 1
        self._update_drift()
        if batch:
            yield batch

    def _update_drift(self) -> None:
        drift = self.driver.streams[0].drift_ppm()
        if drift is not None:
            self.stats.drift_ppm = drift

    def _note_fault(self, message: str) -> None:
        self.stats.last_error = message
        reason = message.rsplit(": ", 1)[-1] if ": " in message else message
        key = re.sub(r"\d+(\.\d+)?", "#", reason.split(" (")[0]).strip()[:60]
        self.stats.faults[key] = self.stats.faults.get(key, 0) + 1

    def _fail(self, reason: str) -> None:
        self._note_fault(reason)
        self.stats.state = f"failed: {reason}"
        try:
            self.driver.close()
        finally:
            self._opened = False
        raise AcquisitionFailed(reason)

    def _recover(self, exc: DeviceError) -> None:
        """Reopen with exponential backoff until it works or ``max_outage_s`` passes.

        The outage runs from the first fault until fresh data flows again, so a device that
        reopens fine but never delivers still ends in failure.
        """
        self._note_fault(str(exc))
        self.stats.state = "reconnecting"
        if self._outage_since is None:
            self._outage_since = self.clock.now()
        t0 = self._outage_since
        backoff = 0.05
        last = str(exc)
        while True:
            self.driver.close()
            if self._stop.is_set():
                self.stats.state = "stopped"
                return
            if self.clock.now() - t0 > self.max_outage_s:
                self._fail(f"{last}; gave up after {self.max_outage_s:g} s of retries")
            self.clock.sleep(backoff)
            backoff = min(backoff * 2, 2.0)
            try:
                self.driver.open()
            except PermanentDeviceError as err:
                self._fail(str(err))
            except DeviceError as err:
                last = str(err)
                continue
            self.stats.reconnects += 1
            self.stats.state = "running"
            return
