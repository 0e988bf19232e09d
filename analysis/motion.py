"""Where a sensor moved: still and moving stretches of a record, from its own samples.

Noise coefficients describe a sensor at rest. A robot's log moves most of the time, and
motion read as noise gives numbers that are not noise. The record is cut into windows of
about a second; a window is moving when

* its spread is far above the typical window's (the sensor's own noise) and above a motion
  level (``GYRO_MOTION_SPREAD``, ``ACCEL_MOTION_SPREAD``): rotation,
  vibration, handling (spread and level are medians, so that a single spike, an outlier, is
  not motion); or its spread is above any MEMS noise level at rest
  (``GYRO_STD_FLOOR``, ``ACCEL_STD_FLOOR``), which catches records that never rest;
* it holds a shock: on at least ``SHOCK_AXES`` axes, ``SHOCK_SAMPLES`` or more samples lie
  ``SHOCK_SIGMAS`` typical spreads (and the motion level) away from the window's median. A
  blow to the bench rings through the body for a fraction of a second, seen by several axes
  at once, and is too short to move the window's median or spread; a corrupt frame or a lone
  spike (one sample, on any number of axes) and a burst on one axis stay. One shock of half a
  g for 0.3 s raised an ADIS16405 accelerometer's Allan variance at 10 ms by 17 % over the
  1.4 h that held it;
* its mean rate departs from the still windows' median rate (a steady turn has a small spread
  but a large mean), beyond both the noise of a window mean and ``GYRO_MEAN_FLOOR``;
* its mean specific force changes from the window before by more than ``ACCEL_STEP_FLOOR``
  (a new tilt or a steady acceleration; rests in different orientations stay still).

The thresholds sit many standard deviations above what white noise, bias instability or rate
random walk do in one window, so that a still record has no moving window (calibrated in the
tests on simulated still records with those terms). Still windows next to a moving one are
dropped too (settling), and still stretches shorter than ``MIN_STILL_S`` are not used.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

WINDOW_S = 1.0
"""Window length (s); at least ``MIN_WINDOW_SAMPLES`` samples."""
MIN_WINDOW_SAMPLES = 32
SPREAD_FACTOR = 4.0
"""A window whose spread exceeds the record's typical (median) window spread by this factor,
and is above the motion level below, moves."""
GYRO_MOTION_SPREAD = 0.01
"""rad/s (about 0.6 deg/s): a rate spread below this is not called motion."""
ACCEL_MOTION_SPREAD = 0.05
"""m/s^2: a specific-force spread below this is not called motion."""
MEAN_SIGMAS = 8.0
"""A window mean further than this many window-mean standard deviations from the still level
moves."""
GYRO_STD_FLOOR = 0.1
"""rad/s: a per-sample spread above any MEMS gyro's noise at rest (about 10 times typical)."""
ACCEL_STD_FLOOR = 0.5
"""m/s^2: likewise for accelerometers."""
GYRO_MEAN_FLOOR = 0.02
"""rad/s (about 1 deg/s): a mean rate change below this is not called motion."""
ACCEL_STEP_FLOOR = 0.1
"""m/s^2 (about 0.6 deg of tilt): a mean specific-force change below this is not motion."""
MIN_STILL_S = 10.0
"""Still stretches shorter than this (s) are not used for noise analysis."""
SHOCK_SIGMAS = 10.0
"""A sample further than this many typical window spreads from its window's median is struck
(a Gaussian sample is, with probability 1.5e-23)."""
SHOCK_SAMPLES = 3
"""Struck samples an axis needs in one window (a lone spike or a corrupt frame has one)."""
SHOCK_AXES = 2
"""Axes, gyro and accelerometer together, struck in one window for a shock."""


@dataclass(frozen=True)
class Stretch:
    """A run of samples ``[start, stop)`` that moved or rested, with how much it moved."""

    start: int
    stop: int
    moving: bool
    peak_rate: float
    """Largest window-mean departure of the rate from rest (rad/s; nan without a gyro)."""
    peak_force: float
    """Largest window-to-window change of the mean specific force (m/s^2; nan without an
    accelerometer)."""
    shock: bool = False
    """The stretch moved by a shock alone (a short blow seen by several axes)."""


@dataclass(frozen=True)
class Motion:
    """Still and moving stretches of a record sampled at ``fs_hz``."""

    fs_hz: float
    n_samples: int
    stretches: tuple[Stretch, ...]

    @property
    def moving(self) -> tuple[Stretch, ...]:
        return tuple(s for s in self.stretches if s.moving)

    @property
    def still(self) -> tuple[Stretch, ...]:
        """Still stretches long enough to analyse."""
        return tuple(s for s in self.stretches if not s.moving
                     and (s.stop - s.start) >= MIN_STILL_S * self.fs_hz)

    @property
    def moved(self) -> bool:
        return bool(self.moving)

    def still_seconds(self) -> float:
        return sum(s.stop - s.start for s in self.still) / self.fs_hz

    def describe(self) -> str:
        """One line for the user."""
        if not self.moved:
            return "the sensor rested throughout (no motion found)"
        total = self.n_samples / self.fs_hz
        moving_s = sum(s.stop - s.start for s in self.moving) / self.fs_hz
        parts = []
        for s in self.moving[:5]:
            how = []
            if np.isfinite(s.peak_rate):
                how.append(f"{np.degrees(s.peak_rate):.3g} deg/s")
            if np.isfinite(s.peak_force):
                how.append(f"{s.peak_force:.3g} m/s^2")
            parts.append(f"{s.start / self.fs_hz:.1f}-{s.stop / self.fs_hz:.1f} s"
                         + (" (a shock)" if s.shock else
                            f" (up to {', '.join(how)})" if how else ""))
        more = f" and {len(self.moving) - 5} more" if len(self.moving) > 5 else ""
        return (f"the sensor moved in {len(self.moving)} stretch(es), {moving_s:.0f} s of "
                f"{total:.0f} s: {'; '.join(parts)}{more}")


_CHUNK_WINDOWS = 2048
"""Windows handled at once: the medians copy their input, so a long record is taken in pieces
(bounded memory whatever its length)."""

Axes = np.ndarray | Sequence[np.ndarray]
"""Samples of several axes: a (samples x axes) array, or one 1-D array per axis (not copied)."""


def _columns(x: Axes) -> list[np.ndarray]:
    if isinstance(x, np.ndarray):
        return [x] if x.ndim == 1 else [x[:, j] for j in range(x.shape[1])]
    return [np.asarray(c) for c in x]


WindowStats = tuple[np.ndarray, np.ndarray, np.ndarray]
"""Per window of one sensor: robust spread (largest over its axes), median of each axis, and
each axis's ``SHOCK_SAMPLES``-th largest distance from that median (units of the samples)."""


def _spread_and_centre(cols: list[np.ndarray], w: int) -> WindowStats:
    """Per whole window of ``w`` samples: the robust standard deviation, largest over the axes
    (1.4826 times the median absolute deviation, which a spike, a shock or an outlier
    does not move), the median of each axis, and each axis's ``SHOCK_SAMPLES``-th largest
    absolute departure from its median (a shock's reach). The windows are gathered a chunk at
    a time, so no copy of the whole record is made.

    Each window's samples are sorted (numpy's vectorised sort of contiguous rows is about ten
    times faster than ``np.median`` and ``np.partition`` along a strided axis); the medians
    are the mean of the middle two sorted values, as ``np.median`` takes them, and an axis
    whose window holds a NaN gets NaN for all three, as ``np.median`` gives it."""
    n_win = cols[0].shape[0] // w
    spread = np.empty(n_win)
    centre = np.empty((n_win, len(cols)))
    reach = np.empty((n_win, len(cols)))
    part = np.empty((min(n_win, _CHUNK_WINDOWS), len(cols), w))
    kth = w - min(SHOCK_SAMPLES, w)
    middle = slice((w - 1) // 2, w // 2 + 1)  # one value for an odd w, two for an even
    for a in range(0, n_win, _CHUNK_WINDOWS):
        k = min(_CHUNK_WINDOWS, n_win - a)
        for j, c in enumerate(cols):
            part[:k, j, :] = c[a * w:(a + k) * w].reshape(k, w)
        ordered = np.sort(part[:k], axis=2)
        med = ordered[:, :, middle].mean(axis=2, keepdims=True)
        med[np.isnan(ordered[:, :, -1:])] = np.nan  # a sort puts NaN last
        dev = np.sort(np.abs(part[:k] - med), axis=2)
        spread[a:a + k] = 1.4826 * dev[:, :, middle].mean(axis=2).max(axis=1)
        centre[a:a + k] = med[:, :, 0]
        reach[a:a + k] = dev[:, :, kth]
    return spread, centre, reach


def _moving_windows(gyro: WindowStats | None, accel: WindowStats | None, w: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per window: moving flag, rate departure (rad/s), force change (m/s^2) and shock flag
    (a window that moves by the shock rule alone), from each sensor's per-window statistics
    as :func:`_spread_and_centre` gives them."""
    n_win = (gyro if gyro is not None else accel)[0].shape[0]  # type: ignore[index]  # one is given
    moving = np.zeros(n_win, bool)
    rate = np.full(n_win, np.nan)
    force = np.full(n_win, np.nan)
    struck = np.zeros(n_win, int)
    for stats, floor in ((gyro, GYRO_MOTION_SPREAD), (accel, ACCEL_MOTION_SPREAD)):
        if stats is not None:
            limit = max(SHOCK_SIGMAS * float(np.median(stats[0])), floor)
            struck += (stats[2] > limit).sum(axis=1)
    shaken = struck >= SHOCK_AXES
    if gyro is not None:
        std, mean, _ = gyro
        quiet = float(np.median(std))
        moving |= ((std > SPREAD_FACTOR * quiet) & (std > GYRO_MOTION_SPREAD)) \
            | (std > GYRO_STD_FLOOR)
        still = ~(moving | shaken)
        rest = mean[still] if np.any(still) else mean
        level = np.median(rest, axis=0)
        rate = np.abs(mean - level).max(axis=1)
        limit = max(MEAN_SIGMAS * quiet / np.sqrt(w), GYRO_MEAN_FLOOR)
        moving |= rate > limit
    if accel is not None:
        std, mean, _ = accel
        quiet = float(np.median(std))
        moving |= ((std > SPREAD_FACTOR * quiet) & (std > ACCEL_MOTION_SPREAD)) \
            | (std > ACCEL_STD_FLOOR)
        step = np.zeros(n_win)
        step[1:] = np.abs(np.diff(mean, axis=0)).max(axis=1)
        force = step
        limit = max(MEAN_SIGMAS * quiet / np.sqrt(w) * np.sqrt(2.0), ACCEL_STEP_FLOOR)
        jump = step > limit
        moving |= jump
        moving[:-1] |= jump[1:]  # the change happened across both windows
    # handling throws samples far out too: a shock is a window that nothing else moves
    shock = shaken & ~moving
    return moving | shock, rate, force, shock


def window_samples(fs_hz: float) -> int:
    """Samples per motion window at ``fs_hz``."""
    return max(MIN_WINDOW_SAMPLES, int(round(WINDOW_S * fs_hz)))


class MotionWindows:
    """The per-window statistics of :func:`detect_motion`, gathered from blocks of samples as
    they are read, so that a record too long to hold is judged exactly as a loaded one.

    Feed each block's axes in record order with :meth:`update` (all axes the same length; a
    partial window is carried to the next block), then call :meth:`motion`. Memory: two
    floats per axis and window (about 1 MB for a day at 100 Hz) plus one window of samples.
    """

    def __init__(self, fs_hz: float, n_gyro: int, n_accel: int) -> None:
        if n_gyro == 0 and n_accel == 0:
            raise ValueError("motion detection needs gyro or accelerometer samples")
        self.fs_hz = float(fs_hz)
        self.w = window_samples(fs_hz)
        self.n_samples = 0
        self._n = (n_gyro, n_accel)
        self._carry = [np.empty((0, k)) for k in self._n]
        self._stats: list[list[WindowStats]] = [[], []]

    def update(self, gyro: Sequence[np.ndarray] = (), accel: Sequence[np.ndarray] = ()) -> None:
        """Add the next samples of every axis (gyro in rad/s, accelerometer in m/s^2)."""
        n_new = None
        for j, axes in enumerate((gyro, accel)):
            if not self._n[j]:
                continue
            block = np.column_stack([np.asarray(a, dtype=np.float64) for a in axes])
            n_new = block.shape[0]
            data = np.concatenate((self._carry[j], block)) if self._carry[j].size else block
            whole = data.shape[0] // self.w * self.w
            if whole:
                cols = [data[:whole, i] for i in range(data.shape[1])]
                self._stats[j].append(_spread_and_centre(cols, self.w))
            self._carry[j] = data[whole:].copy()
        self.n_samples += int(n_new or 0)

    def motion(self) -> Motion:
        """The still and moving stretches of everything fed."""
        stats: list[WindowStats | None] = []
        for j in range(2):
            if not self._n[j]:
                stats.append(None)
                continue
            parts = self._stats[j]
            std = np.concatenate([p[0] for p in parts]) if parts else np.empty(0)
            mean, reach = ((np.concatenate([p[i] for p in parts]) if parts
                            else np.empty((0, self._n[j]))) for i in (1, 2))
            stats.append((std, mean, reach))
        return _stretches(self.fs_hz, self.n_samples, self.w, stats[0], stats[1])


def detect_motion(fs_hz: float, gyro: Axes | None = None, accel: Axes | None = None) -> Motion:
    """Still and moving stretches of a record.

    Args:
        fs_hz: sampling rate (Hz).
        gyro: rates (rad/s): samples x axes, or one array per axis; or None.
        accel: specific force (m/s^2), likewise; or None.
    """
    if gyro is None and accel is None:
        raise ValueError("motion detection needs gyro or accelerometer samples")
    gyro = _columns(gyro) if gyro is not None else None
    accel = _columns(accel) if accel is not None else None
    n = (gyro if gyro is not None else accel)[0].shape[0]  # type: ignore[index]  # checked above
    w = window_samples(fs_hz)
    return _stretches(fs_hz, n, w,
                      _spread_and_centre(gyro, w) if gyro is not None and n >= 3 * w else None,
                      _spread_and_centre(accel, w) if accel is not None and n >= 3 * w else None)


def _stretches(fs_hz: float, n: int, w: int, gyro: WindowStats | None,
               accel: WindowStats | None) -> Motion:
    """Stretches of ``n`` samples from the per-window statistics of each sensor."""
    if n < 3 * w or (gyro is None and accel is None):
        return Motion(fs_hz, n, (Stretch(0, n, False, np.nan, np.nan),))
    moving, rate, force, shock = _moving_windows(gyro, accel, w)
    # settling: a still window next to a moving one is not used either
    grown = moving.copy()
    grown[1:] |= moving[:-1]
    grown[:-1] |= moving[1:]
    flags = np.append(grown, grown[-1])  # the partial last window follows the one before
    rate = np.append(rate, rate[-1])
    force = np.append(force, force[-1])
    shock = np.append(shock, False)
    moving = np.append(moving, False)
    edges = np.flatnonzero(np.diff(flags.astype(np.int8))) + 1
    bounds = np.concatenate(([0], edges, [flags.size]))
    stretches = []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        start, stop = int(a) * w, min(n, int(b) * w) if b < flags.size else n
        mv = bool(flags[a])
        peak_r = float(np.nanmax(rate[a:b])) if mv and np.isfinite(rate[a:b]).any() else np.nan
        peak_f = float(np.nanmax(force[a:b])) if mv and np.isfinite(force[a:b]).any() else np.nan
        # a stretch is a shock's when every window that moved did so by the shock rule
        hit = bool(shock[a:b].any()) and not bool((moving[a:b] & ~shock[a:b]).any())
        stretches.append(Stretch(start, stop, mv, peak_r, peak_f, hit))
    return Motion(fs_hz, n, tuple(stretches))
