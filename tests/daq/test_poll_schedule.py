"""Polling a part without a FIFO: the data-ready schedule reads every sample when the host is
late by less than most of a period, and the sample clock counts exactly what a longer delay
lost. A model of the part (one sample register, a new-data flag) and of the host (lateness,
bus latency) in virtual time, against the truth the model knows."""

from __future__ import annotations

import math

import numpy as np
import pytest

from imunoise.daq.drivers.common import PolledSampleClock
from imunoise.daq.poll_schedule import DataReadySchedule

FS = 204.8
T = 1.0 / FS


class CountPaced:
    """The fixed-rate schedule (2 % faster than the part) that the drivers used before."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s / 1.02
        self.due = 0.0
        self._k = 0

    def start(self, now: float) -> None:
        self.due, self._k, self._t0 = now, 0, now

    def after_poll(self, started: float, finished: float, fresh: bool) -> float:
        self._k += 1
        self.due = self._t0 + self._k * self.period_s
        return self.due


def run(schedule, lateness, seconds=60.0, seed=0, phase=0.37, held=None):
    """Poll the model part; per fresh read (true lost, counted lost, phase of the read).

    ``held(rng)``: how long a read is held up after its time was taken (s; the host stalled
    between taking the time and sending the request, or the request waited in a bridge)."""
    rng = np.random.default_rng(seed)
    clock = PolledSampleClock(FS)
    schedule.start(0.0)
    last_read, next_index, t = -1, 0, 0.0
    events = []
    while t < seconds:
        start = max(schedule.due, t) + lateness(rng)
        delay = held(rng) if held is not None else 0.0
        read_at = start + delay + rng.uniform(0.02, 0.06) * T  # the bus's latency
        newest = math.floor((read_at - phase * T) * FS)
        fresh = newest > last_read and newest >= 0
        if fresh:
            true_lost = newest - last_read - 1 if last_read >= 0 else 0
            counted = clock.fresh(start, next_index) if last_read >= 0 else clock.fresh(start, 0)
            events.append((true_lost, counted, (read_at / T - phase) % 1.0))
            next_index += counted + 1
            last_read = newest
        else:
            clock.stale(start, next_index - 1)
        t = read_at + rng.uniform(0.02, 0.06) * T
        schedule.after_poll(start, t, fresh)
    return np.array(events)


def jitter(rng):
    """A busy host: mostly a few per cent of a period late, one poll in fifty up to 0.8."""
    if rng.random() < 0.02:
        return rng.uniform(0.2, 0.8) * T
    return rng.exponential(0.03 * T)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_late_host_loses_nothing_on_the_data_ready_schedule(seed):
    ev = run(DataReadySchedule(T), jitter, seed=seed)
    assert len(ev) == pytest.approx(60 * FS, abs=2)
    assert ev[:, 0].sum() == 0 and ev[:, 1].sum() == 0


def test_the_fixed_rate_schedule_loses_samples_under_the_same_host():
    """Why the schedule exists: at fixed rate the poll phase drifts through each appearance,
    and a poll a little late there loses a sample. The sample clock still counts them."""
    ev = run(CountPaced(T), jitter, seed=0)
    lost, counted = ev[:, 0].sum(), ev[:, 1].sum()
    assert lost > 0.005 * len(ev)
    assert counted == pytest.approx(lost, rel=0.05)


def test_retries_stay_few_and_polls_sit_just_after_each_appearance():
    sched = DataReadySchedule(T)
    ev = run(sched, lambda rng: rng.exponential(0.03 * T), seed=3)
    assert sched.retries < 0.05 * len(ev)
    # Read phases after the part's own appearance (bus latency included).
    assert np.percentile(ev[:, 2], 95) < 0.3


@pytest.mark.parametrize("seed", [0, 1])
def test_a_stalled_host_gets_its_losses_counted(seed):
    """Stalls of 1.2 to 3.8 periods. A read just after an appearance may count one sample
    short (the phase is known to a bracket's width); the next bracket finds the slip and
    counts it, so the running count, which places every later sample in time, is never more
    than one sample off (before: up to 13, and the total 1.4-2.5 % short; now exact)."""

    def stalls(rng):
        if rng.random() < 0.02:
            return rng.uniform(1.2, 3.8) * T
        return rng.exponential(0.03 * T)

    ev = run(DataReadySchedule(T), stalls, seed=seed)
    lossy = ev[ev[:, 0] > 0]
    assert len(lossy) > 100
    assert np.abs(ev[:, 0] - ev[:, 1]).max() <= 1
    assert np.abs(np.cumsum(ev[:, 0] - ev[:, 1])).max() <= 1
    assert ev[:, 1].sum() == pytest.approx(ev[:, 0].sum(), rel=0.01)


@pytest.mark.parametrize("seed", [0, 1])
def test_a_read_held_up_after_its_time_was_taken_loses_no_count_for_good(seed):
    """One read in a hundred held up 0.6 to 2.5 periods after its time was taken (the host
    stopped between the two, or the request waited in the bridge): it reads a later sample
    than its time says and the loss before it goes uncounted. The part's clock does not jump,
    so the bracket after it, a whole period later than the phase followed, counts the slip
    (empty polls in between may not move the phase far: they rest on the same miscounted
    index). 120 s at 204.8 Hz: counted 235 of 235 and 281 of 282 lost, the running count at
    most 3 off (before: 163 and 200, and every sample after each slip placed a period early
    for good: 72 and 84 periods by the end)."""

    def held(rng):
        return rng.uniform(0.6, 2.5) * T if rng.random() < 0.01 else 0.0

    ev = run(DataReadySchedule(T), lambda rng: rng.exponential(0.03 * T), seconds=120.0,
             seed=seed, held=held)
    lost, counted = ev[:, 0].sum(), ev[:, 1].sum()
    assert lost > 200
    assert counted == pytest.approx(lost, rel=0.02)
    assert np.abs(np.cumsum(ev[:, 0] - ev[:, 1])).max() <= 4


def run_status_then_data(lateness, seconds=120.0, seed=0, phase=0.37, status_s=0.12 * T,
                         drift_ppm=0.0):
    """The ITG-3200's poll: a status read, and when it shows new data a data read a status
    read's duration later, which takes the newest sample then. The part's clock runs
    ``drift_ppm`` fast. Per fresh read: (true lost, counted lost)."""
    rng = np.random.default_rng(seed)
    fs_part = FS * (1.0 + drift_ppm * 1e-6)
    clock = PolledSampleClock(FS, reads_latch_at_once=True)
    schedule = DataReadySchedule(T)
    schedule.start(0.0)
    last_read, next_index, t = -1, 0, 0.0
    events = []
    while t < seconds:
        start = max(schedule.due, t) + lateness(rng)
        status_at = start + rng.uniform(0.02, 0.06) * T
        fresh = math.floor((status_at - phase * T) * fs_part) > last_read
        if fresh:
            data_start = start + status_s
            data_at = data_start + rng.uniform(0.02, 0.06) * T
            newest = math.floor((data_at - phase * T) * fs_part)
            if last_read < 0:
                counted = clock.fresh(data_start, 0, seen_at=start)
                events.append((0, counted))
            else:
                counted = clock.fresh(data_start, next_index, seen_at=start)
                events.append((newest - last_read - 1, counted))
            next_index += counted + 1
            last_read = newest
            t = data_at + rng.uniform(0.02, 0.06) * T
        else:
            clock.stale(start, next_index - 1)
            t = status_at + rng.uniform(0.02, 0.06) * T
        schedule.after_poll(start, t, fresh)
    return np.array(events)


@pytest.mark.parametrize("drift_ppm", [0.0, 300.0, -300.0])
def test_a_status_then_data_poll_counts_its_losses(drift_ppm):
    """Stalls of 0.5 to 3 periods, so that many reads land near a period boundary. The
    anchor follows the bounds the polls set (an empty poll comes just before the appearance,
    the schedule makes sure of it) instead of a bracket's middle, and a found sample bounds it
    from the status read's start: at 204.8 Hz, 120 s, the count is off by one in 1-5 % of the
    lossy reads (16-19 % with a bracket's middle and the data read's time), a read counted
    short is made good at the next bracket, and the running count is never more than 5
    samples off (before the brackets found slips: 6 and 9 short at the end of the runs with
    0 and +300 ppm; now 0)."""

    def stalls(rng):
        if rng.random() < 0.02:
            return rng.uniform(0.5, 3.0) * T
        return rng.exponential(0.03 * T)

    ev = run_status_then_data(stalls, seed=int(abs(drift_ppm)) + 1, drift_ppm=drift_ppm)
    lossy = int((ev[:, 0] > 0).sum())
    wrong = int((ev[:, 0] != ev[:, 1]).sum())
    assert lossy > 300
    assert wrong < 0.06 * lossy
    assert np.abs(ev[:, 0] - ev[:, 1]).max() <= 1
    assert np.abs(np.cumsum(ev[:, 0] - ev[:, 1])).max() <= 5
    assert ev[:, 1].sum() == pytest.approx(ev[:, 0].sum(), rel=0.01)
