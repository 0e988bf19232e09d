"""Channels of several devices onto one time base: band-limited interpolation that keeps
lines exact, white noise's short-tau Allan level and the gaps."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.alignment import HALF_TAPS, align, interpolate
from imunoise.analysis.allan import oadev
from imunoise.core.series import ChannelSeries


def _adev8(x: np.ndarray) -> float:
    """Overlapping Allan deviation at 8 samples."""
    return float(oadev(x, 1.0, m=np.array([8]), ci=None).dev[0])


def test_a_line_at_0_8_of_nyquist_is_interpolated_to_1e_3_of_its_amplitude():
    n = np.arange(20_000)
    u = np.arange(100, 19_000) + 0.37
    for f in (0.01, 0.2, 0.4):  # cycles per sample
        got = interpolate(np.sin(2 * np.pi * f * n), u)
        assert np.max(np.abs(got - np.sin(2 * np.pi * f * u))) < 1e-3, f


def test_white_noise_keeps_its_allan_level_at_any_offset():
    """Linear interpolation halfway between samples halves white noise's variance; the
    band-limited kernel keeps the Allan deviation at 8 samples within 0.5 % (one
    realisation, so the comparison is not limited by the estimator's spread)."""
    x = np.random.default_rng(7).standard_normal(400_000)
    ref = _adev8(x[HALF_TAPS:-HALF_TAPS])
    for frac in (0.1, 0.25, 0.5):
        u = np.arange(HALF_TAPS, x.size - HALF_TAPS) + frac
        y = interpolate(x, u)
        assert np.isfinite(y).all()
        got = _adev8(y)
        assert got == pytest.approx(ref, rel=5e-3), frac
    halfway = 0.5 * (x[:-1] + x[1:])  # linear interpolation at offset 0.5, for contrast
    assert _adev8(halfway) < 0.98 * ref


def _series(values, fs, t0, starts=(0,), seg_t0=None):
    return ChannelSeries("gyro_x", "rad/s", fs, np.asarray(values, float),
                         np.asarray(starts, np.int64), t0,
                         None if seg_t0 is None else np.asarray(seg_t0, float))


def test_align_takes_the_reference_times_and_keeps_gaps_as_segments():
    fs, n = 100.0, 5000
    f = 3.0
    t_ref = 10.0 + np.arange(n) / fs
    ref = _series(np.sin(2 * np.pi * f * t_ref), fs, 10.0)
    # the other device samples 0.43 periods later and lost 20 samples after its 2000th
    t_other = 10.0043 + np.arange(n + 20) / fs
    keep = np.r_[0:2000, 2020:n + 20]
    other = _series(np.cos(2 * np.pi * f * t_other[keep]), fs, t_other[0], starts=(0, 2000),
                    seg_t0=(t_other[0], t_other[2020]))
    got = align({"a": ref, "b": other}, "a")
    assert got.interpolated == ["b"] and got.apart == []
    a, b = got.series["a"], got.series["b"]
    assert a.n_samples == b.n_samples < n
    # left out: the kernel's reach before the other device's first sample, and its 20 lost
    # samples with the reach on both sides (its last sample lies beyond the reference's)
    assert len(a.segment_starts) == 2
    assert n - a.n_samples == pytest.approx(HALF_TAPS + 20 + 2 * HALF_TAPS - 1, abs=2)
    t = a.time_of(np.arange(a.n_samples))
    assert np.max(np.abs(a.values - np.sin(2 * np.pi * f * t))) < 1e-12
    assert np.max(np.abs(b.values - np.cos(2 * np.pi * f * t))) < 1e-3
    assert got.kept_share == pytest.approx(a.n_samples / n)


def test_align_leaves_out_a_rate_too_far_from_the_reference():
    ref = _series(np.zeros(1000), 100.0, 0.0)
    fast = _series(np.zeros(3000), 300.0, 0.0)
    got = align({"a": ref, "c": fast}, "a")
    assert got.apart == ["c"] and got.interpolated == [] and list(got.series) == ["a"]


def test_times_at_the_kernels_reach_are_nan_not_an_index_error():
    x = np.arange(100.0)
    u = np.array([HALF_TAPS - 1.0, x.size - HALF_TAPS - 1.0, x.size - HALF_TAPS, 1e9, -5.0])
    got = interpolate(x, u)
    assert got[:2] == pytest.approx(u[:2], abs=1e-9)  # a ramp is interpolated exactly
    assert np.isnan(got[2:]).all()
