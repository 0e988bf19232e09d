"""Pieces shared by the device drivers: stream buffers and sample-time reconstruction.

A driver records each sample it reads as (sample index, raw counts). The sample index counts
device samples since the first one, including samples known to be missed, so sample times are
``t_anchor + index / fs`` (the configured rate and the count, never the host clock) and a jump
in the index is a gap whose length is known.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from imunoise.core.blocks import SampleBlock


class StreamBuffer:
    """Raw samples of one stream waiting to become :class:`SampleBlock` objects.

    Args:
        stream: stream name, e.g. ``/adis16350/imu``.
        channels: channel names in the order of the raw columns.
        fs_hz: configured sample rate of the stream.
        to_si: maps the raw count matrix ``(n, len(raw_names))`` to SI values
            ``(n, len(channels))``.
        raw_names: names under which raw columns go into ``SampleBlock.raw`` (default:
            ``channels``); extra raw columns beyond the SI channels are allowed.
    """

    def __init__(self, stream: str, channels: Sequence[str], fs_hz: float,
                 to_si: Callable[[np.ndarray], np.ndarray],
                 raw_names: Sequence[str] | None = None) -> None:
        self.stream = stream
        self.channels = list(channels)
        self.raw_names = list(raw_names) if raw_names is not None else list(channels)
        self.fs_hz = float(fs_hz)
        self.to_si = to_si
        self.t_anchor: float | None = None
        self._idx: list[int] = []
        self._rows: list[Sequence[int]] = []
        self._last_index = -1
        self._last_emitted = -1
        self.samples = 0
        self.missed = 0
        self.gaps = 0
        self.last_host_time: float | None = None

    def anchor(self, wall_time_s: float) -> None:
        """Set the time of sample index 0 (host epoch seconds), once."""
        if self.t_anchor is None:
            self.t_anchor = float(wall_time_s)

    @property
    def next_index(self) -> int:
        return self._last_index + 1

    def add(self, row: Sequence[int], *, missed: int = 0, host_time: float | None = None
            ) -> None:
        """Append one sample that follows ``missed`` lost samples, read at ``host_time``."""
        index = self._last_index + 1 + max(0, int(missed))
        self._idx.append(index)
        self._rows.append(row)
        self._last_index = index
        self.samples += 1
        if host_time is not None:
            self.last_host_time = host_time
        if missed > 0:
            self.missed += int(missed)
            self.gaps += 1

    def add_many(self, rows: np.ndarray, *, missed: int = 0,
                 host_time: float | None = None) -> None:
        """Append consecutive samples (a FIFO drain) after ``missed`` lost samples; the last
        one was the newest at ``host_time``."""
        n = len(rows)
        if n == 0:
            return
        start = self._last_index + 1 + max(0, int(missed))
        self._idx.extend(range(start, start + n))
        self._rows.extend(np.asarray(rows).tolist())
        self._last_index = start + n - 1
        self.samples += n
        if host_time is not None:
            self.last_host_time = host_time
        if missed > 0:
            self.missed += int(missed)
            self.gaps += 1

    def drift_ppm(self) -> float | None:
        """Host clock rate relative to the device's, in parts per million (None: too early).

        Compares the host time at which the newest sample was read with the time the sample
        count gives it; the reading latency (under a period) fades as the run grows.
        """
        if self.t_anchor is None or self.last_host_time is None or self._last_index < 1:
            return None
        device_elapsed = self._last_index / self.fs_hz
        if device_elapsed < 1.0:
            return None
        return ((self.last_host_time - self.t_anchor) / device_elapsed - 1.0) * 1e6

    def take(self) -> list[SampleBlock]:
        """Blocks for everything buffered, split at gaps (``gap_before`` = samples missing)."""
        if not self._idx:
            return []
        idx = np.asarray(self._idx, dtype=np.int64)
        raw = np.asarray(self._rows, dtype=np.int64).reshape(len(idx), -1)
        self._idx, self._rows = [], []
        si = self.to_si(raw)
        prev = np.concatenate(([self._last_emitted], idx[:-1]))
        jumps = idx - prev - 1
        starts = np.flatnonzero(jumps != 0)
        if starts.size == 0 or starts[0] != 0:
            starts = np.concatenate(([0], starts))
        bounds = np.append(starts, len(idx))
        t_anchor = self.t_anchor or 0.0
        blocks = []
        for a, b in zip(bounds[:-1], bounds[1:], strict=True):
            t = t_anchor + idx[a:b] / self.fs_hz
            blocks.append(SampleBlock(
                stream=self.stream, t=t,
                channels={c: si[a:b, k].copy() for k, c in enumerate(self.channels)},
                fs_hz=self.fs_hz,
                raw={c: raw[a:b, k].copy() for k, c in enumerate(self.raw_names)},
                gap_before=int(max(jumps[a], 0)),
            ))
        self._last_emitted = int(idx[-1])
        return blocks


STALE_MOVE_MAX = 0.25
"""How far (periods) empty polls may move a polled part's phase later than the last fresh
read left it. An empty poll bounds the phase only if every loss before it was counted: after
a read that hid a loss, each empty poll would move the phase later by part of a period, and
together they would take the hidden loss for a late phase."""
COUNT_MARGIN = 0.15
"""A read of a part behind a bridge less than this (periods) after the time its sample
should have appeared counts that sample as not yet there. The phase is known to about a
bracket's width; a loss counted short is found by the next bracket, one counted in excess
could not be taken back."""


class PolledSampleClock:
    """Counts samples lost by a polled device (no FIFO, no sample counter on the chip).

    The chip only shows whether its sample is new; how many samples came since the last read
    is told by the time. ``anchor`` is the host time at which the device's sample 0 appeared
    (on the clock of the polls, every time taken as a read begins), so the newest sample at
    host time t is ``floor((t - anchor) * fs)``. Each poll bounds the anchor: one that found
    nothing newer than sample i says sample i + 1 had not appeared (a lower bound); one that
    found sample i says it had (an upper bound).

    With ``reads_latch_at_once`` (a part on a local bus, the ITG-3200: a read takes the
    registers a short, steady time after it begins) the anchor moves only as far as each
    bound requires. The :class:`imunoise.daq.poll_schedule.DataReadySchedule` creeps its polls
    earlier
    until one finds nothing, so the lower bound sits just before each appearance; the middle
    of a bracket (an empty poll, then one that found the sample) would be late by a good part
    of the bracket (at 1 kHz about 5 % of a period), and a poll late by nearly a whole period
    would then be taken to hold one sample fewer than it did. Without it (the ADIS16350
    behind a serial bridge, whose latency varies from read to read) a single poll's time
    bounds the phase only loosely: a bracket sets the anchor to its middle, and a poll that
    found data moves it only when it is off by more than half a period.

    Either way the estimate follows the device's clock, and a poll late by up to a period less
    the anchor's uncertainty counts exactly the samples lost. A read that takes a later
    sample than its time says (the host stalled after taking the time, or the request waited
    in a bridge) hides the loss before it; the next bracket then implies a phase a whole
    period later, which the part's steady clock cannot have, and counts the hidden samples
    there (:meth:`_slipped`). A device that stalls still
    leaves a gap as long as the stall: "nothing new" moves the anchor by at most half a
    period, and not at all once the device is overdue.
    """

    def __init__(self, fs_hz: float, *, reads_latch_at_once: bool = False) -> None:
        self.fs_hz = float(fs_hz)
        self.period_s = 1.0 / self.fs_hz
        self.reads_latch_at_once = reads_latch_at_once
        self.anchor: float | None = None
        self._resyncing = False
        self._last_fresh: float | None = None
        self._found_anchor: float | None = None  # the anchor as the last fresh read left it
        self._stale: tuple[float, int] | None = None

    def reconnected(self) -> None:
        """The device was reopened: until the next fresh sample, "no new data" says nothing
        about the samples made while it was away."""
        self._resyncing = True
        self._stale = None

    def stale(self, t: float, last_index: int) -> None:
        """A poll at host time ``t`` found nothing newer than ``last_index``."""
        if last_index < 0 or self._resyncing or self._last_fresh is None:
            return
        found = self._found_anchor  # set by every fresh read, as _last_fresh is
        assert self.anchor is not None and found is not None
        if t - self._last_fresh > 1.5 * self.period_s:
            # Overdue: the device stalls. The poll that finally finds data brackets nothing;
            # the stall is counted from the phase it had.
            self._stale = None
            return
        self._stale = (t, last_index)
        not_before = t - (last_index + 1) * self.period_s
        if 0.0 < not_before - self.anchor and not_before - found <= STALE_MOVE_MAX * self.period_s:
            self.anchor = not_before

    def fresh(self, t: float, next_index: int, seen_at: float | None = None) -> int:
        """A poll whose data read began at ``t`` found a new sample; how many were lost
        before it.

        ``seen_at``: when the status read that found the sample new began, for a part read
        as status then data (the ITG-3200); the sample had appeared by then.
        """
        missed = self._fresh(t, next_index, seen_at)
        self._found_anchor = self.anchor
        return missed

    def _fresh(self, t: float, next_index: int, seen_at: float | None) -> int:
        seen = t if seen_at is None else seen_at
        bracket, self._stale = self._stale, None
        restarted, self._resyncing = self._resyncing, False
        self._last_fresh = t
        if self.anchor is None:
            self.anchor = t - next_index * self.period_s
            return 0
        if restarted:
            # The old phase counts the samples lost while away; a reset device samples on a
            # new phase, which the next bracket finds.
            missed = max(0, int(math.floor((t - self.anchor) * self.fs_hz)) - next_index)
            self.anchor = t - (next_index + missed) * self.period_s
            return missed
        in_bracket = (bracket is not None and bracket[1] == next_index - 1
                      and seen - bracket[0] <= 0.5 * self.period_s)
        if self.reads_latch_at_once:
            # Sample next_index (or a later one) had appeared when it was seen.
            self.anchor = min(self.anchor, seen - next_index * self.period_s)
            if in_bracket:  # it appeared between the two polls
                return self._slipped(bracket[0] - next_index * self.period_s, tight=True)
            return max(0, int(math.floor((t - self.anchor) * self.fs_hz)) - next_index)
        # A bridge's latency varies from read to read: one poll's time bounds the phase only
        # to within that variation, so a bracket sets its middle, and a finding poll moves the
        # phase only when it is off by more than half a period.
        if in_bracket:
            return self._slipped(0.5 * (bracket[0] + seen) - next_index * self.period_s,
                                 tight=False)
        newest = int(math.floor((t - self.anchor) * self.fs_hz - COUNT_MARGIN))
        if newest < next_index:
            if (seen - self.anchor) * self.fs_hz < next_index - 0.5:
                self.anchor = seen - next_index * self.period_s
            return 0
        return newest - next_index

    def _slipped(self, anchor: float, tight: bool) -> int:
        """Set the phase from a bracket that puts sample ``next_index`` at ``anchor`` (the
        time of sample 0 it implies); the samples lost that no count had found.

        A bracket is exact about the sample it found only if every loss before it was
        counted. A read whose time was taken before the host stalled (or whose request waited
        in a bridge) reads a later sample than its time says, and the loss before it goes
        uncounted; the bracket that follows then implies a phase a whole period or more later
        than the one the polls have followed. The part's clock does not jump, so such a
        difference is samples lost: they are counted here, and the phase kept. A difference
        of less than half a period is the bracket refining the phase (``tight``: a lower
        bound, applied only as far as it requires; otherwise the bracket's middle)."""
        # against the phase the last fresh read left: empty polls since may have moved it
        # later (up to STALE_MOVE_MAX), on the word of the same miscounted index
        found = self._found_anchor  # a bracket needs an empty poll, which needs a fresh read
        assert self.anchor is not None and found is not None
        slip = int(math.floor((anchor - found) * self.fs_hz + 0.5))
        if slip > 0:
            anchor -= slip * self.period_s
            self.anchor = min(self.anchor, found)
        self.anchor = max(self.anchor, anchor) if tight else anchor
        return max(slip, 0)


def sign_extend(values: np.ndarray | int, bits: int) -> np.ndarray:
    """Two's-complement values of ``bits`` bits (upper bits ignored) as signed integers."""
    v = np.asarray(values, dtype=np.int64) & ((1 << bits) - 1)
    return np.where(v & (1 << (bits - 1)), v - (1 << bits), v)
