"""Cross-spectra and coherence: the exact distribution, simulated known coherence, the null's
false-alarm rate, streaming equals batch, and the ADIS16405 run 1 line."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal
from scipy import stats

from imunoise.analysis.coherence import (
    CrossSpectralAccumulator,
    coherence,
    cross_spectra,
    msc_cdf,
    msc_expected,
    msc_interval,
    msc_null_sf,
    msc_threshold,
)


def _mc_msc(g: float, n: int, trials: int, seed: int) -> np.ndarray:
    """MSC estimates of ``n`` independent complex Gaussian averages with true coherence g."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(trials, n)) + 1j * rng.normal(size=(trials, n))
    e = rng.normal(size=(trials, n)) + 1j * rng.normal(size=(trials, n))
    b = np.sqrt(g) * a + np.sqrt(1 - g) * e
    sab = np.sum(a * b.conj(), axis=1)
    return np.abs(sab) ** 2 / (np.sum(np.abs(a) ** 2, 1) * np.sum(np.abs(b) ** 2, 1))


@pytest.mark.parametrize("g, n", [(0.0, 12), (0.3, 20), (0.9, 60), (0.5, 7)])
def test_distribution_matches_monte_carlo(g, n):
    c = _mc_msc(g, n, 40000, seed=3)
    q = np.quantile(c, [0.05, 0.25, 0.5, 0.75, 0.95])
    # the empirical cdf at the sample quantiles: binomial spread sqrt(p(1-p)/N) <= 0.0025
    assert np.allclose(msc_cdf(q, g, n), [0.05, 0.25, 0.5, 0.75, 0.95], atol=0.01)
    se_mean = np.std(c) / np.sqrt(c.size)
    assert abs(np.mean(c) - msc_expected(g, n)) < 4 * se_mean


def test_null_distribution_and_threshold():
    x = np.array([0.0, 0.01, 0.1, 0.5])
    assert np.allclose(msc_cdf(x, 0.0, 31.0), 1 - (1 - x) ** 30)
    assert np.allclose(msc_null_sf(x, 31.0), (1 - x) ** 30)
    thr = msc_threshold(31.0, 0.05)
    assert np.isclose(msc_null_sf(thr, 31.0), 0.05)
    fam = msc_threshold(31.0, 0.05, n_tests=10)
    assert np.isclose(1 - (1 - msc_null_sf(fam, 31.0)) ** 10, 0.05)
    assert np.isclose(msc_expected(0.0, 31.0), 1 / 31.0)


def test_interval_coverage_of_independent_averages():
    g, n = 0.6, 25
    c = _mc_msc(g, n, 4000, seed=4)
    lo, hi = msc_interval(c, n, 0.95)
    cover = np.mean((lo <= g) & (g <= hi))
    assert abs(cover - 0.95) < 4 * np.sqrt(0.95 * 0.05 / c.size)
    # equal tails
    assert abs(np.mean(g < lo) - 0.025) < 4 * np.sqrt(0.025 * 0.975 / c.size)


def _common_record(n: int, seed: int, sc: float = 1.0, se=(1.0, 0.5, 2.0)) -> np.ndarray:
    """Three channels: one common white noise (std ``sc``) plus own white noises ``se``."""
    rng = np.random.default_rng(seed)
    c = sc * rng.normal(size=n)
    return np.column_stack([c + s * rng.normal(size=n) for s in se])


def test_known_coherence_recovered_within_intervals():
    se = np.array([1.0, 0.5, 2.0])
    truth = {(0, 1): 1 / ((1 + se[0] ** 2) * (1 + se[1] ** 2)),
             (0, 2): 1 / ((1 + se[0] ** 2) * (1 + se[2] ** 2)),
             (1, 2): 1 / ((1 + se[1] ** 2) * (1 + se[2] ** 2))}
    covered = total = 0
    for seed in range(4):
        x = _common_record(1 << 16, seed, se=se)
        co = coherence(x, 100.0, ["a", "b", "c"], nperseg=256, points_per_decade=10)
        for k, (a, b) in enumerate(co.pairs):
            g = truth[("abc".index(a), "abc".index(b))]
            covered += int(np.sum((co.ci_low[k] <= g) & (g <= co.ci_high[k])))
            total += co.f_hz.size
            # merged points average many bins: the estimate sits near the truth
            assert np.all(np.abs(co.msc[k][-5:] - g) < 0.05)
    cover = covered / total
    # points of one pair are close to independent (distinct bins); 95 % nominal
    assert 0.95 - 4 * np.sqrt(0.05 * 0.95 / total) < cover <= 1.0, cover


def test_zero_coherence_false_alarm_rate_with_overlapped_segments():
    """Independent channels: the share of bins above the single-point threshold is alpha
    when the number of averages is the overlapped segments' equivalent one."""
    above = bins = 0
    for seed in range(20):
        rng = np.random.default_rng(100 + seed)
        x = rng.normal(size=(1 << 16, 2))
        cs = cross_spectra(x, 50.0, ["a", "b"], nperseg=512)
        msc = cs.msc("a", "b")
        above += int(np.sum(msc > msc_threshold(cs.n_avg, 0.05)))
        bins += msc.size
    rate = above / bins
    # adjacent Hann bins correlate (|c1|^2 = 4/9): the spread of the share is taken 1.5
    # times the binomial one
    assert abs(rate - 0.05) < 3 * 1.5 * np.sqrt(0.05 * 0.95 / bins), rate


def test_family_threshold_false_alarm():
    hits = 0
    trials = 40
    for seed in range(trials):
        rng = np.random.default_rng(500 + seed)
        x = rng.normal(size=(1 << 13, 2))
        co = coherence(x, 10.0, ["a", "b"], nperseg=64, points_per_decade=20)
        hits += int(np.any(co.msc[0] > co.threshold_family))
    # family-wise 5 %: a binomial count of 40 trials; P(X >= 7 | p = 0.05) < 0.005
    assert hits <= 6
    assert stats.binom.sf(hits - 1, trials, 0.05) > 0.005


def test_matches_scipy_and_streaming_equals_batch():
    x = _common_record(20000, 7)
    cs = cross_spectra(x, 100.0, ["a", "b", "c"], nperseg=512)
    f, c = scipy.signal.coherence(x[:, 0], x[:, 2], fs=100.0, nperseg=512)
    assert np.allclose(cs.msc("a", "c"), c[2:256], rtol=1e-9)
    f, p = scipy.signal.welch(x[:, 1], fs=100.0, nperseg=512)
    assert np.allclose(cs.psd("b"), p[2:256], rtol=1e-9)
    acc = CrossSpectralAccumulator(["a", "b", "c"], 100.0, 512)
    for block in np.array_split(x, 37):
        acc.add(block)
    st = acc.result()
    assert np.allclose(st.s, cs.s, rtol=1e-10, atol=0)
    assert st.n_avg == pytest.approx(cs.n_avg)


def test_gaps_are_not_bridged():
    x = _common_record(6000, 8)
    y = x.copy()
    y[3000:] += 1e3  # a jump at the gap: bridged, it would dominate the spectrum
    whole = cross_spectra(x, 100.0, ["a", "b", "c"], nperseg=256, segment_starts=[0, 3000])
    split = cross_spectra(y, 100.0, ["a", "b", "c"], nperseg=256, segment_starts=[0, 3000])
    assert np.allclose(split.s, whole.s)
    assert split.n_segments == 2 * (1 + (3000 - 256) // 128)


def test_bad_input_is_a_value_error():
    with pytest.raises(ValueError, match="NaN"):
        cross_spectra(np.full((1000, 2), np.nan), 100.0, ["a", "b"], nperseg=64)
    with pytest.raises(ValueError, match="two channels"):
        cross_spectra(np.zeros((1000, 1)), 100.0, ["a"], nperseg=64)
    with pytest.raises(ValueError, match="gap-free"):
        cross_spectra(np.zeros((10, 2)), 100.0, ["a", "b"], nperseg=64)


def test_adis16405_run1_line_is_coherent_across_accelerometer_axes(shared_data):
    d = np.load(shared_data / "adis16405" / "run1.npz")
    acc = d["accel_counts"] * float(d["accel_scale_g"]) * 9.80665
    cs = cross_spectra(acc, 100.0, ["accel_x", "accel_y", "accel_z"], nperseg=8192)
    k = int(np.argmin(np.abs(cs.f_hz - 0.564)))
    measured = {("accel_x", "accel_y"): 0.963, ("accel_x", "accel_z"): 0.940,
                ("accel_y", "accel_z"): 0.908}
    for (a, b), value in measured.items():
        c = cs.msc(a, b)[k]
        assert c == pytest.approx(value, abs=0.002)
        lo, hi = msc_interval(c, cs.n_avg)
        assert lo > 0.85 and hi < 0.98
        assert c > msc_threshold(cs.n_avg, 0.05, n_tests=cs.f_hz.size)
