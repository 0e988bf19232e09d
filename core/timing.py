"""Sample timing shared by every reader: nominal rate, real gaps, jitter, gap-free segments.

Every reader (CSV, EuRoC, MCAP, rosbag2, ROS 1) hands its time stamps to :func:`analyse_stamps`,
so that the same stamps give the same rate, gaps and segments whatever the file format.

The model: a sensor samples on its own clock at a steady rate; the stamps are that grid plus
jitter (a host clock stamping on receipt is late by a varying latency, then on time again) and
minus the samples really lost. With the nominal period P and the first stamp t0, sample i sits
``o_i = (t_i - t0) / P - i`` periods off its place on a loss-free grid. Jitter makes ``o``
spike and come back; a lost sample raises it by one for good; time going backwards lowers it.
The level of ``o`` (a running median, which keeps steps and removes spikes shorter than its
half-width, rounded to whole samples) is therefore the count of samples missing so far; a
segment boundary sits wherever it changes. Within a segment the samples are taken to lie on
the grid (re-timed), and the distance of the stamps from it is reported as jitter. P comes
from a least-squares line through the stamps against their grid positions, so that jitter
averages out and a slightly wrong nominal rate does not accumulate into false losses.
Sequence numbers, where a format has them (ROS 1 ``header.seq``), give the missing counts
directly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

MEDIAN_HALF_WIDTH = 4
"""Half-width of the running median of the grid offset: stamps late for up to this many samples
in a row are jitter; a longer offset that returns is still a segment boundary pair, not data
lost silently."""

_CHUNK = 1 << 18  # samples filtered at once: bounds the temporary (chunk x window) arrays


@dataclass
class Timing:
    """Sampling of one stream.

    Attributes:
        fs_hz: nominal sampling rate (Hz), 9 significant digits.
        t0_s: time of the first sample (s, the stamps' epoch).
        segment_starts: indices where gap-free segments begin (always starts with 0).
        missing: samples really missing (summed over the gaps; backward steps not counted).
        jitter_rms_s: root mean square distance of the stamps from the sample grid (s).
        jitter_max_s: largest such distance (s).
        backward: places where time went backwards or repeated a grid position.
        notes: one-line descriptions for the user.
        gaps: samples missing before each segment start but the first (-1: time went back).
        segment_t0_s: where each segment's sample grid lies (s, as ``t0_s``), once a reader
            has worked it out from the stamps (None until then).
    """

    fs_hz: float
    t0_s: float
    segment_starts: np.ndarray
    missing: int = 0
    jitter_rms_s: float = 0.0
    jitter_max_s: float = 0.0
    backward: int = 0
    notes: list[str] = field(default_factory=list)
    gaps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    segment_t0_s: np.ndarray | None = None

    def facts(self) -> dict[str, float | int]:
        """JSON-ready summary: rate, samples missing, jitter and backward steps."""
        return {"fs_hz": self.fs_hz, "segments": int(self.segment_starts.size),
                "missing_samples": self.missing, "jitter_rms_s": self.jitter_rms_s,
                "jitter_max_s": self.jitter_max_s, "backward_steps": self.backward}


def relative_seconds(t: np.ndarray) -> tuple[np.ndarray, float]:
    """(times after the first in s, first time in s) from int64 ns or float s stamps.

    Integer nanoseconds are differenced before scaling: a float64 holds an epoch stamp of
    1.7e9 s only to about 240 ns, which would bias the rate in its ninth digit.
    """
    t = np.asarray(t)
    if t.size == 0:
        return np.zeros(0), 0.0
    if np.issubdtype(t.dtype, np.integer):
        rel = (t - t[0]).astype(np.float64)
        rel *= 1e-9  # in place: one temporary of the record's length, not two
        return rel, int(t[0]) * 1e-9
    t = t.astype(np.float64)
    return t - t[0], float(t[0])


def _levels(rel: np.ndarray, period: float, idx: np.ndarray) -> np.ndarray:
    """Missing-sample count so far at each sample (int64) for the grid of ``period`` s: the
    running median of the rounded grid offset over ``2 MEDIAN_HALF_WIDTH + 1`` samples.

    Rounding is monotone, so it commutes with the median; and where the rounded offset is
    constant over a whole window the median is that constant. The median is therefore only
    evaluated next to the places where the rounded offset changes (few in a real record).
    """
    n = rel.size
    x = rel / period
    x -= idx[:n]
    r = np.rint(x, out=x).astype(np.int64)
    change = np.flatnonzero(r[1:] != r[:-1])
    if change.size == 0:
        return r
    half = MEDIAN_HALF_WIDTH
    idx = np.unique(np.clip(change[:, None] + np.arange(1 - half, half + 1), 0, n - 1))
    padded = np.concatenate((np.full(half, r[0]), r, np.full(half, r[-1])))
    levels = r.copy()
    for a in range(0, idx.size, _CHUNK):
        part = idx[a:a + _CHUNK]
        windows = padded[part[:, None] + np.arange(2 * half + 1)]
        levels[part] = np.median(windows, axis=1).astype(np.int64)
    return levels


def _period_on_grid(rel: np.ndarray, levels: np.ndarray, idx: np.ndarray) -> float:
    """Least-squares period (s) of the stamps against their grid positions ``idx + levels``."""
    n = rel.size
    grid = idx[:n] + levels
    g_mean = float(grid.mean())
    den = float(np.dot(grid, grid)) - n * g_mean * g_mean
    num = float(np.dot(grid, rel)) - n * g_mean * float(rel.mean())
    return num / den if den > 0 else float("nan")


def _clean(rel: np.ndarray) -> bool:
    """True when every interval lies within a quarter of the median interval (the stamps of a
    recorder on the sample clock): no loss and no jitter to sort out, the common case, taken
    in two passes instead of the grid refinement's dozen. Chunked: the intervals of a long
    record are never all held at once."""
    n = rel.size
    step = max(1, (n - 1) // 100_000)
    m = (n - 1 + step - 1) // step  # the intervals dt[::step]
    med = float(np.median(rel[1::step][:m] - rel[0:-1:step][:m]))
    if not med > 0:
        return False
    for a in range(0, n - 1, _CHUNK):
        dt = np.diff(rel[a:a + _CHUNK + 1])
        dt -= med
        if float(np.max(np.abs(dt, out=dt))) >= 0.25 * med:
            return False
    return True


def _clean_timing(rel: np.ndarray, t0: float, rate_hz: float | None, label: str) -> Timing:
    """Timing of stamps that :func:`_clean` passed: nothing missing, nothing backwards; the
    least-squares period over the sample index and the jitter around that grid, accumulated
    in chunks (bounded temporaries whatever the record's length)."""
    n = rel.size
    # least-squares slope of rel against 0..n-1: closed-form sums of the index
    i_mean = (n - 1) / 2.0
    den = n * (n * n - 1.0) / 12.0
    dot = sum(float(np.dot(np.arange(a, min(n, a + _CHUNK), dtype=np.float64),
                           rel[a:a + _CHUNK])) for a in range(0, n, _CHUNK))
    period = (dot - n * i_mean * float(rel.mean())) / den
    step = max(1, n // 100_000)
    centre = float(np.median(rel[::step] - period * np.arange(0, n, step, dtype=np.float64)))
    sq, worst = 0.0, 0.0
    for a in range(0, n, _CHUNK):
        r = np.arange(a, min(n, a + _CHUNK), dtype=np.float64)
        r *= -period
        r += rel[a:a + _CHUNK]
        r -= centre
        sq += float(np.dot(r, r))
        worst = max(worst, float(np.max(np.abs(r))))
    jitter_rms, jitter_max = float(np.sqrt(sq / n)), worst
    fs = float(rate_hz) if rate_hz else float(f"{1.0 / period:.9g}")
    notes = []
    if jitter_max > 0.25 * period:
        notes.append(f"{label}time stamps jitter by up to {jitter_max:.3g} s (rms "
                     f"{jitter_rms:.3g} s) around the {fs:.6g} Hz grid: re-timed on the grid, "
                     "not treated as gaps")
    return Timing(fs, t0, np.zeros(1, np.int64), 0, jitter_rms, jitter_max, 0, notes)


def _first_period(rel: np.ndarray) -> float:
    """A first period (s): the mean of the intervals within half a median interval of it.

    The median alone picks the nominal interval robustly (gaps and backward steps do not move
    it) but not precisely: stamps rounded to 1 ms at 300 Hz have intervals of 3 and 4 ms. The
    mean over the intervals near it is good to about 1e-3 even then, which is what the grid
    refinement needs to start from.
    """
    dt = np.diff(rel)
    dt = dt[dt > 0]
    if dt.size == 0:
        raise ValueError("cannot infer a sampling rate: fewer than two increasing time stamps")
    med = float(np.median(dt[:: max(1, dt.size // 200_000)]))
    near = dt[np.abs(dt - med) < 0.5 * med]
    return float(np.mean(near)) if near.size else med


def _grid_period(rel: np.ndarray, first: float, idx: np.ndarray) -> tuple[float, np.ndarray]:
    """Period (s) and missing-sample levels, refined over growing spans of the record.

    The median interval is only good to about 1e-3 when a host clock jitters (late stamps
    outnumber early ones among the outliers); over 10^4 samples that would add up to false
    losses. So the period is refined by the least-squares line over the first 256 samples,
    then over eight times more, and so on: each span is short enough for the previous period
    to place every sample within a fraction of a period of its grid position.
    """
    period = first
    span = 256
    while True:
        m = min(rel.size, span)
        levels = _levels(rel[:m], period, idx)
        refined = _period_on_grid(rel[:m], levels, idx)
        if np.isfinite(refined) and refined > 0:
            period = refined
        if m == rel.size:
            return period, _levels(rel, period, idx)
        span *= 8


def analyse_stamps(t: np.ndarray, *, seq: np.ndarray | None = None,
                   rate_hz: float | None = None, name: str = "") -> Timing:
    """Rate, real gaps, jitter and gap-free segments of one stream's time stamps.

    Args:
        t: stamps, int64 nanoseconds or float seconds, in file order.
        seq: sequence numbers of the samples (consecutive when nothing was lost), if the
            format has them; they then decide where samples are missing.
        rate_hz: the nominal rate when the user knows it; the stamps still place the samples
            on their grid (a host clock may run at a slightly different rate).
        name: stream name for the notes.

    Raises:
        ValueError: fewer than two increasing stamps and no ``rate_hz``.
    """
    rel, t0 = relative_seconds(t)
    n = rel.size
    label = f"{name}: " if name else ""
    if n < 2 or not np.any(np.diff(rel) > 0):
        if rate_hz:
            return Timing(float(rate_hz), t0, np.zeros(1, np.int64))
        raise ValueError("cannot infer a sampling rate: fewer than two increasing time stamps")
    if seq is None and _clean(rel):  # every interval within a quarter period: nothing lost
        return _clean_timing(rel, t0, rate_hz, label)
    idx = np.arange(n, dtype=np.float64)
    if seq is not None:
        s = np.asarray(seq, dtype=np.int64)
        levels = (s - s[0]) - np.arange(n, dtype=np.int64)
        period = _period_on_grid(rel, levels, idx)
    else:
        period, levels = _grid_period(rel, _first_period(rel), idx)
    if not (np.isfinite(period) and period > 0):
        period = _first_period(rel)
    steps = np.diff(levels)
    breaks = np.flatnonzero(steps != 0) + 1
    missing = int(steps[steps > 0].sum())
    backward = int(np.count_nonzero(steps < 0))
    resid = idx + levels
    resid *= -period
    resid += rel
    resid -= np.median(resid[:: max(1, n // 100_000)])
    jitter_rms = float(np.sqrt(np.dot(resid, resid) / n))
    jitter_max = float(np.max(np.abs(resid)))
    fs = float(rate_hz) if rate_hz else float(f"{1.0 / period:.9g}")
    notes = []
    if missing:
        ahead = np.flatnonzero(steps > 0)
        widest = int(ahead[np.argmax(rel[ahead + 1] - rel[ahead])])
        notes.append(f"{label}{missing} sample(s) missing in {ahead.size} gap(s) (largest "
                     f"{rel[widest + 1] - rel[widest]:.3g} s, before sample {widest + 2}); "
                     "segments are analysed separately")
    if backward:
        first = int(np.flatnonzero(steps < 0)[0])
        notes.append(f"{label}time goes backwards or repeats at {backward} place(s) (first "
                     f"before sample {first + 2}); treated as segment boundaries, samples kept")
    if jitter_max > 0.25 * period:
        notes.append(f"{label}time stamps jitter by up to {jitter_max:.3g} s (rms "
                     f"{jitter_rms:.3g} s) around the {fs:.6g} Hz grid: re-timed on the grid, "
                     "not treated as gaps")
    gaps = np.where(steps[breaks - 1] > 0, steps[breaks - 1], -1).astype(np.int64)
    return Timing(fs, t0, np.concatenate(([0], breaks)).astype(np.int64), missing,
                  jitter_rms, jitter_max, backward, notes, gaps)


def estimate_rate(t: np.ndarray) -> float:
    """Nominal sampling rate in Hz from sample times (s or int64 ns): :func:`analyse_stamps`'s."""
    return analyse_stamps(t).fs_hz


def segment_starts_from_times(t: np.ndarray, fs_hz: float, tolerance: float = 0.5) -> np.ndarray:
    """Indices where a new segment starts for stamps already known to be jitter-free (the
    streams this project writes itself): wherever an interval departs from ``1/fs_hz`` by more
    than ``tolerance`` sample periods."""
    t = np.asarray(t, dtype=np.float64)
    if t.size == 0:
        return np.zeros(1, dtype=np.int64)
    dt = np.diff(t) * fs_hz
    breaks = np.flatnonzero(np.abs(dt - 1.0) > tolerance) + 1
    return np.concatenate(([0], breaks)).astype(np.int64)
