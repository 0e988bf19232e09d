"""Channels of several devices on one time base: each channel interpolated, band-limited, at
the sample times of a reference channel, so that the cross-channel view (coherence,
subtraction, the three-cornered hat) can compare sensors that were recorded together but
sampled at their own instants (two devices are never read at the same moment).

Band-limited (a Kaiser-windowed sinc of :data:`HALF_TAPS` samples each side) rather than
linear: linear interpolation is a low-pass filter whose gain depends on where between two
samples the new time falls (white noise keeps only half its variance halfway), which would
bias the own-noise levels read from the aligned channels. The windowed sinc keeps white
noise's variance within 0.5 % at any offset over the band up to 0.9 of the Nyquist frequency;
a faster source is low-passed to the reference's Nyquist frequency on the way. A constant
delay between devices changes no coherence (it is a phase); what is compared is each
device's own clock as its stamps place the samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imunoise.core.series import ChannelSeries

HALF_TAPS = 16
"""Source samples used on each side of a new time."""

KAISER_BETA = 8.0
"""Shape of the window on the sinc (stop-band about 80 dB down)."""

RATE_RATIO_LIMIT = 2.0
"""Largest ratio between a channel's rate and the reference's that is interpolated."""

_CHUNK = 1 << 15  # new samples computed at once: bounds the (chunk x taps) temporaries


PHASES = 1024
"""Fractional offsets at which the kernel is tabulated (a new time is rounded to 1/1024 of a
sample: a timing error far below any stamp's jitter)."""


def kernel_table(cutoff: float = 1.0) -> np.ndarray:
    """(PHASES + 1, 2 HALF_TAPS) weights: row ``p`` for a new time ``p / PHASES`` of a sample
    after the tap at offset 0, columns for the taps at offsets ``-HALF_TAPS + 1 .. HALF_TAPS``;
    each row sums to 1."""
    offsets = np.arange(-HALF_TAPS + 1, HALF_TAPS + 1)
    d = (np.arange(PHASES + 1) / PHASES)[:, None] - offsets[None, :]
    w = cutoff * np.sinc(cutoff * d)
    w *= np.i0(KAISER_BETA * np.sqrt(np.clip(1.0 - (d / HALF_TAPS) ** 2, 0.0, 1.0)))
    return w / w.sum(axis=1, keepdims=True)


def interpolate(x: np.ndarray, u: np.ndarray, cutoff: float = 1.0) -> np.ndarray:
    """``x`` (one gap-free segment) at fractional sample indices ``u``; NaN where the kernel
    would reach beyond ``x``. ``cutoff``: the pass band as a share of ``x``'s Nyquist
    frequency (1: all of it; below 1 the result is low-passed there first)."""
    x = np.asarray(x, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    out = np.full(u.shape, np.nan)
    inside = (u >= HALF_TAPS - 1) & (u < x.size - HALF_TAPS)
    where = np.flatnonzero(inside)
    table = kernel_table(cutoff)
    offsets = np.arange(-HALF_TAPS + 1, HALF_TAPS + 1)
    for a in range(0, where.size, _CHUNK):
        idx = where[a:a + _CHUNK]
        ui = u[idx]
        base = np.floor(ui)
        phase = np.rint((ui - base) * PHASES).astype(np.int64)
        taps = base.astype(np.int64)[:, None] + offsets[None, :]
        out[idx] = np.einsum("ij,ij->i", table[phase], x[taps])
    return out


def sample_times(s: ChannelSeries) -> np.ndarray:
    """Time (s) of every sample of ``s``: each segment on its rate's grid from its start."""
    return s.time_of(np.arange(s.n_samples))


def onto_times(s: ChannelSeries, t: np.ndarray, fs_out: float) -> np.ndarray:
    """``s`` interpolated at the increasing times ``t`` (s, the clock of ``s.t0_s``), band
    limited to ``fs_out``'s Nyquist frequency; NaN where no segment of ``s`` covers a time
    with the kernel's reach."""
    out = np.full(t.shape, np.nan)
    starts = np.append(s.segment_starts, s.n_samples)
    t0s = s.segment_times()
    cutoff = min(1.0, float(fs_out) / float(s.fs_hz))
    for k in range(len(s.segment_starts)):
        a, b = int(starts[k]), int(starts[k + 1])
        if b - a < 2 * HALF_TAPS:
            continue
        lo = np.searchsorted(t, t0s[k] + (HALF_TAPS - 1) / s.fs_hz, side="left")
        hi = np.searchsorted(t, t0s[k] + (b - a - HALF_TAPS) / s.fs_hz, side="left")
        if hi > lo:
            u = (t[lo:hi] - t0s[k]) * s.fs_hz
            out[lo:hi] = interpolate(s.values[a:b], u, cutoff)
    return out


@dataclass
class Alignment:
    """Channels brought onto one time base.

    Attributes:
        series: every channel that could be aligned, on the reference's sample times (the
            reference's own channels cut to the span all of them cover).
        reference: the channel whose sample times the others take.
        interpolated: the channels that were interpolated.
        apart: channels left out (rate too far from the reference's, or no overlap).
        kept_share: share of the reference's samples that every aligned channel covers.
    """

    series: dict[str, ChannelSeries]
    reference: str
    interpolated: list[str]
    apart: list[str]
    kept_share: float

    def note(self) -> str:
        return (f"{len(self.interpolated)} channel(s) of other devices interpolated "
                f"(band-limited) onto the sample times of {self.reference}; "
                f"{100 * self.kept_share:.1f} % of its samples are covered by all")


def _same_grid(a: ChannelSeries, b: ChannelSeries) -> bool:
    return (a.fs_hz == b.fs_hz and a.n_samples == b.n_samples
            and np.array_equal(a.segment_starts, b.segment_starts)
            and np.allclose(a.segment_times(), b.segment_times(), rtol=0.0,
                            atol=1e-6 / a.fs_hz))


def align(series: dict[str, ChannelSeries], reference: str) -> Alignment:
    """Every channel of ``series`` on the sample times of ``series[reference]``."""
    ref = series[reference]
    t = sample_times(ref)
    values: dict[str, np.ndarray] = {}
    interpolated: list[str] = []
    apart: list[str] = []
    valid = np.ones(ref.n_samples, dtype=bool)
    for key, s in series.items():
        if _same_grid(s, ref):
            values[key] = s.values
            continue
        ratio = float(s.fs_hz) / float(ref.fs_hz)
        if not (1.0 / RATE_RATIO_LIMIT <= ratio <= RATE_RATIO_LIMIT):
            apart.append(key)
            continue
        v = onto_times(s, t, ref.fs_hz)
        ok = np.isfinite(v)
        if not ok.any():
            apart.append(key)
            continue
        values[key] = v
        valid &= ok
        interpolated.append(key)
    kept = np.flatnonzero(valid)
    if kept.size == 0:
        return Alignment({reference: ref}, reference, [], [k for k in series if k != reference],
                         0.0)
    # a new segment wherever a kept sample does not follow the one before, or the reference
    # starts one
    is_start = np.zeros(ref.n_samples, dtype=bool)
    is_start[ref.segment_starts] = True
    follows = np.concatenate(([False], np.diff(kept) == 1))
    new_start = ~follows | is_start[kept]
    starts = np.flatnonzero(new_start).astype(np.int64)
    seg_t0 = t[kept[starts]]
    out = {key: ChannelSeries(series[key].name, series[key].units, ref.fs_hz,
                              np.ascontiguousarray(v[kept]), starts, float(t[kept[0]]),
                              seg_t0)
           for key, v in values.items()}
    return Alignment(out, reference, interpolated, apart, kept.size / ref.n_samples)
