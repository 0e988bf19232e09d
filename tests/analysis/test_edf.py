"""Equivalent degrees of freedom, chi-square intervals and lag-1 ACF noise identification."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy import special, stats

from imunoise.analysis.edf import (
    LAG1_MIN_POINTS,
    chi2_interval,
    greenhall_edf,
    noise_id_lag1,
    noise_id_lag1_series,
)

allantools_ci = pytest.importorskip("allantools.ci")


def _power_law(alpha: int, n: int, seed: int) -> np.ndarray:
    """Rate noise with one-sided PSD ~ f^alpha, by shaping white noise in the frequency domain."""
    rng = np.random.default_rng(seed)
    spec = np.fft.rfft(rng.standard_normal(n))
    f = np.fft.rfftfreq(n)
    f[0] = f[1]
    return np.fft.irfft(spec * f ** (alpha / 2.0), n)


CASES = list(
    itertools.product(
        [2, 1, 0, -1, -2],  # alpha
        [2, 3],  # d
        [1, 3, 16, 40, 1000],  # m
        [64, 1001, 20000, 600000],  # phase points
        [True, False],  # overlapping
        [True, False],  # modified
    )
)


def test_greenhall_edf_agrees_with_allantools_on_every_case_it_covers():
    compared = 0
    for alpha, d, m, n, overlapping, modified in CASES:
        if alpha + 2 * d <= 1 or n - (d + 1) * m < 1:
            continue
        try:
            want = allantools_ci.edf_greenhall(alpha, d, m, n, overlapping, modified)
        except NotImplementedError:
            continue  # alpha = 2 with fewer than d+1 independent spans: not in allantools
        got = greenhall_edf(alpha, d, m, n, overlapping, modified)
        assert got == pytest.approx(want, rel=1e-10), (alpha, d, m, n, overlapping, modified)
        compared += 1
    assert compared > 250


def test_white_phase_short_record_uses_the_exact_sum():
    # alpha = 2, unmodified, overlapping, r = M/S <= d: 1/edf = (1 + 2 sum (1 - k/r) c_k^2) / M
    d, m, n = 2, 40, 110
    big_m = 1 + (m * (n - d * m - 1)) // m
    r = big_m / m
    ks = np.arange(1, min(int(np.ceil(r)) - 1, d) + 1)
    c = special.comb(2 * d, d - ks) / special.comb(2 * d, d)
    want = big_m / (1 + 2 * np.sum((1 - ks / r) * c**2))
    assert greenhall_edf(2, d, m, n, True, False) == pytest.approx(want, rel=1e-12)


def test_white_fm_nonoverlapped_allan_edf_is_two_thirds_of_the_term_count():
    # Consecutive non-overlapped Allan differences of white FM have correlation -1/2, so
    # var(sum z^2) = 2 s^4 M (1 + 2 / 4) and edf = 2 M^2 s^4 / (3 M s^4) = 2M/3.
    n, m = 4_000_001, 40
    terms = (n - 1) // m - 1
    assert greenhall_edf(0, 2, m, n, False, False) == pytest.approx(2 * terms / 3, rel=1e-4)


def test_edf_rejects_undefined_noise_and_reports_too_short_records():
    with pytest.raises(ValueError, match="undefined"):
        greenhall_edf(-3, 2, 1, 100, True, False)
    assert np.isnan(greenhall_edf(0, 2, 60, 100, True, False))


def test_chi2_interval_is_the_chi_square_quantile_interval():
    dev = np.array([2.0, 2.0])
    edf = np.array([10.0, 1e6])
    low, high = chi2_interval(dev, edf, ci=0.9)
    assert low[0] == pytest.approx(2.0 * np.sqrt(10.0 / stats.chi2.ppf(0.95, 10.0)))
    assert high[0] == pytest.approx(2.0 * np.sqrt(10.0 / stats.chi2.ppf(0.05, 10.0)))
    z = stats.norm.ppf(0.95)
    assert high[1] / 2.0 - 1 == pytest.approx(z / np.sqrt(2e6), rel=0.01)
    low, high = chi2_interval(np.array([1.0]), np.array([np.nan]))
    assert np.isnan(low[0]) and np.isnan(high[0])
    with pytest.raises(ValueError, match="confidence"):
        chi2_interval(dev, edf, ci=1.5)


@pytest.mark.parametrize(("alpha", "seed"), [(2, 1), (1, 2), (0, 3), (-1, 4), (-2, 5)])
def test_lag1_identifies_power_law_noise(alpha, seed):
    y = _power_law(alpha, 1 << 16, seed)
    ms = np.array([1, 4, 16, 64])
    got = noise_id_lag1(y, ms, "freq", dmax=2, alpha_range=(-2, 2))
    # flicker and its neighbours sit between integer types at finite length; allow one step
    assert np.all(np.abs(got - alpha) <= (0 if alpha in (2, 0, -2) else 1)), got


def test_lag1_on_phase_data_matches_rate_data():
    y = _power_law(0, 1 << 14, 7)
    x = np.concatenate(([0.0], np.cumsum(y)))
    res_freq = noise_id_lag1_series(y, "freq")
    res_phase = noise_id_lag1_series(x, "phase")
    assert res_freq[0] == res_phase[0] == 0


def test_lag1_too_few_points_carries_the_last_identified_alpha():
    y = _power_law(-2, 3000, 8)
    ms = np.array([1, 10, 100, 1000])  # 3000 // 100 = 30 averages still usable, 3 at m=1000
    assert 3000 // 1000 < LAG1_MIN_POINTS <= 3000 // 100
    got = noise_id_lag1(y, ms)
    assert got[3] == got[2]
    assert noise_id_lag1_series(y[: LAG1_MIN_POINTS - 1]) is None
    # nothing identifiable at all: white rate noise is assumed
    np.testing.assert_array_equal(noise_id_lag1(y[:20], np.array([1, 2])), [0, 0])


@pytest.mark.parametrize("n", [31, 1000, 200_000])
def test_fast_detrended_acf_equals_the_explicit_one(n):
    from imunoise.analysis.edf import _detrend, lag1_acf, lag1_acf_detrended_from_phase

    rng = np.random.default_rng(n)
    for z in (
        rng.standard_normal(n) + 0.3,
        np.cumsum(rng.standard_normal(n)) * 0.1 + 5e-3 * np.arange(n),
    ):
        v = np.concatenate(([0.0], np.cumsum(z))) + 7.0
        want = lag1_acf(_detrend(np.diff(v), 1))
        assert lag1_acf_detrended_from_phase(v) == pytest.approx(want, rel=1e-9, abs=1e-12)


@pytest.mark.parametrize(("alpha", "dmax"), [(-2, 2), (-3, 3), (-4, 3), (-1, 2)])
def test_differenced_path_matches_the_explicit_series(alpha, dmax):
    """Noise steep enough to need differencing: the phase-based identification (which skips
    the detrending before differencing) gives the explicit series' alpha at every m."""
    from imunoise.analysis.edf import _lag1_differenced, noise_id_lag1_phase

    y = _power_law(alpha, 1 << 15, 20 - alpha)
    y += 1e-3 * np.arange(y.size) / y.size  # a trend, which the detrending would remove
    u = np.concatenate(([0.0], np.cumsum(y - y.mean())))
    ms = np.array([1, 2, 5, 16, 50, 200, 1000])
    want = []
    for m in ms:
        res = noise_id_lag1_series(np.diff(u[::m]) / m, "freq", dmax)
        want.append(res[0] if res is not None else want[-1])
    got = noise_id_lag1_phase(u, ms, "freq", dmax=dmax, alpha_range=(-10, 10))
    np.testing.assert_array_equal(got, want)
    assert np.any(got <= -2)  # the differenced path was taken
    res = _lag1_differenced(np.diff(u), dmax)
    ref = noise_id_lag1_series(np.diff(u), "freq", dmax)
    assert res[0] == ref[0]
    assert res[1] == pytest.approx(ref[1], rel=1e-9, abs=1e-12)
