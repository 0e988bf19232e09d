"""PSD estimators against known spectra.

Tolerances come from the estimator's own spread: with about 300 points the fraction inside 95 %
intervals has a standard deviation near 0.012 (measured over 30 seeds, points are mildly
correlated), and the normalised dispersion mean((P/S - 1)^2 dof/2) is 1 with a spread near 0.09.
"""

import json

import numpy as np
import pytest
import scipy.signal

from imunoise.analysis.psd import StreamingPsd, default_nperseg, log_psd, welch_psd

FS = 100.0


def _white(n, sigma=0.3, seed=1, offset=0.0):
    return np.random.default_rng(seed).normal(offset, sigma, n)


def _coverage(est, truth):
    return float(np.mean((est.ci_low <= truth) & (truth <= est.ci_high)))


def _dispersion(est, truth):
    return float(np.mean((est.psd / truth - 1.0) ** 2 * est.dof / 2.0))


@pytest.fixture(scope="module")
def white_1m():
    x = _white(2**20, offset=1.5)
    return x, log_psd(x, FS, points_per_decade=None)


def test_white_noise_level_recovered_within_interval(white_1m):
    x, est = white_1m
    truth = 2 * 0.3**2 / FS  # one-sided white level
    assert len(est) > 250
    cov = _coverage(est, truth)
    assert 0.92 <= cov <= 0.98, cov
    # degrees of freedom right: a factor-2 error in dof would give 0.5 or 2
    assert 0.73 <= _dispersion(est, truth) <= 1.27
    grouped = log_psd(x, FS, points_per_decade=40)
    assert 0.90 <= _coverage(grouped, truth) <= 0.99
    assert 0.7 <= _dispersion(grouped, truth) <= 1.35
    assert 150 <= len(grouped) <= 250


def test_frequency_axis_reaches_ten_over_t_and_bands_do_not_overlap(white_1m):
    x, est = white_1m
    T = len(x) / FS
    assert est.f_hz[0] == pytest.approx(10.0 / T, rel=0.05)
    assert est.f_hz[-1] < FS / 2
    assert np.all(np.diff(est.f_hz) > 0)
    # each method occupies one contiguous frequency range; Welch is the top one, from fs/16
    methods = list(dict.fromkeys(est.method))
    assert methods[-1] == "welch"
    assert est.f_hz[est.method == "welch"][0] == pytest.approx(FS / 16)
    # cascade level with decimation D covers fs/(16 D) .. fs/(8 D) (except the deepest)
    sel = est.method == "decimate4"
    assert est.f_hz[sel][0] == pytest.approx(FS / 64) and est.f_hz[sel][-1] < FS / 32
    # bandwidths tile the axis without overlap: from half a bin below the lowest point of the
    # deepest level to half a bin below Nyquist
    deep_bin = FS / 2048 / 256
    expected = (FS / 2 - FS / 512) - (est.f_hz[0] - deep_bin / 2)
    assert np.sum(est.df_hz) == pytest.approx(expected, rel=1e-12)


def test_parseval_integral_equals_variance(white_1m):
    x, est = white_1m
    # spread of sum(psd*df) from the per-point chi-square dof
    rel_sd = np.sqrt(np.sum((est.psd * est.df_hz) ** 2 * 2.0 / est.dof)) / np.var(x)
    missing = est.f_hz[0] * 2 / FS + 1.5 / 256  # band below f_min and the half bin at Nyquist
    assert abs(est.band_power() / np.var(x) - 1.0) <= 4 * rel_sd + missing
    assert rel_sd < 2e-3


def test_parseval_with_coloured_noise_and_line():
    rng = np.random.default_rng(7)
    n = 2**19
    t = np.arange(n) / FS
    x = scipy.signal.lfilter([1.0], [1.0, -0.9], rng.normal(0, 0.01, n))
    x += 0.02 * np.sin(2 * np.pi * 4.4 * t)  # mid-band: see docs/psd.md on lines at band edges
    est = log_psd(x, FS)
    true_var = 0.01**2 / (1 - 0.9**2) + 0.02**2 / 2
    rel_sd = np.sqrt(np.sum((est.psd * est.df_hz) ** 2 * 2.0 / est.dof)) / true_var
    assert rel_sd < 0.01
    assert est.band_power() / true_var == pytest.approx(1.0, abs=4 * rel_sd)


@pytest.mark.parametrize("f0", [12.3, 0.0537])
def test_sinusoid_is_a_line_with_its_power(f0):
    rng = np.random.default_rng(3)
    n = 2**20
    t = np.arange(n) / FS
    amp, sigma = 0.05, 0.01
    x = rng.normal(0, sigma, n) + amp * np.sin(2 * np.pi * f0 * t + 0.3)
    est = log_psd(x, FS)
    peak = int(np.argmax(est.psd))
    assert abs(est.f_hz[peak] - f0) <= 2 * est.df_hz[peak]
    floor = 2 * sigma**2 / FS
    assert est.psd[peak] > 200 * floor
    near = np.abs(est.f_hz - f0) < 0.15 * f0
    line_power = np.sum((est.psd[near] - floor) * est.df_hz[near])
    assert line_power == pytest.approx(amp**2 / 2, rel=0.01)
    # away from the line the floor is intact
    far = np.abs(est.f_hz - f0) > 0.5 * f0
    assert np.median(est.psd[far]) == pytest.approx(floor, rel=0.1)


def test_random_walk_low_band_not_leakage_dominated():
    q = 1e-3
    x = np.cumsum(np.random.default_rng(0).normal(0, q, 2**20))
    est = log_psd(x, FS)
    # discrete random walk: S(f) = 2 q^2 / (fs |1 - exp(-i 2 pi f/fs)|^2)
    truth = 2 * q**2 / (FS * 4 * np.sin(np.pi * est.f_hz / FS) ** 2)
    assert 0.90 <= _coverage(est, truth) <= 0.99
    assert _dispersion(est, truth) < 1.4
    for m in np.unique(est.method):
        sel = est.method == m
        ratio = float(np.mean(est.psd[sel] / truth[sel]))
        # mean of n points with dof each: relative sd sqrt(2/(n dof))
        sd = np.sqrt(2.0 / np.sum(est.dof[sel]))
        assert abs(ratio - 1.0) < 4 * sd + 0.01, (m, ratio, sd)


def test_streaming_equals_batch_with_gaps():
    rng = np.random.default_rng(5)
    x = np.cumsum(rng.normal(0, 1e-3, 300_000)) + rng.normal(0, 0.01, 300_000)
    starts = np.array([0, 70_001, 200_000])
    batch = log_psd(x, FS, segment_starts=starts)
    stream = StreamingPsd(FS)
    bounds = list(starts) + [len(x)]
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        stream.new_segment()
        i = a
        while i < b:
            n = int(rng.integers(1, 5000))
            stream.update(x[i:min(i + n, b)])
            i += n
    got = stream.estimate()
    assert stream.n_samples == len(x)
    np.testing.assert_array_equal(got.method, batch.method)
    np.testing.assert_allclose(got.f_hz, batch.f_hz, rtol=1e-12)
    np.testing.assert_allclose(got.psd, batch.psd, rtol=1e-9)
    np.testing.assert_allclose(got.dof, batch.dof, rtol=1e-12)
    np.testing.assert_allclose(got.ci_high, batch.ci_high, rtol=1e-9)


def test_streaming_memory_is_bounded():
    stream = StreamingPsd(FS)
    rng = np.random.default_rng(0)
    sizes = []
    for _ in range(16):
        stream.update(rng.normal(size=65_536))
        sizes.append(stream.state_size())
    # per level: periodogram sum (129) + partial segment (< 256) + filter history (46), plus
    # fewer than 65536 samples of small blocks waiting to be processed
    assert sizes[-1] <= 20 * (129 + 256 + 46) + 65536
    assert sizes[-1] - sizes[7] <= 2 * (129 + 256 + 46)  # doubling the data adds one level


def test_gaps_are_never_bridged():
    x = _white(400_000, sigma=0.1, seed=2)
    x[200_000:] += 50.0  # a large jump across the gap
    truth = 2 * 0.1**2 / FS
    with_gap = log_psd(x, FS, segment_starts=np.array([0, 200_000]))
    assert 0.88 <= _coverage(with_gap, truth) <= 0.99
    bridged = log_psd(x, FS)
    assert np.max(bridged.psd / truth) > 100  # what bridging the jump would have done


def test_welch_matches_scipy_and_log_psd_top_band():
    x = _white(50_000, seed=4)
    est = welch_psd(x, FS, nperseg=256)
    f, p = scipy.signal.welch(x, FS, window="hann", nperseg=256, noverlap=128)
    np.testing.assert_allclose(est.f_hz, f[2:128])
    np.testing.assert_allclose(est.psd, p[2:128], rtol=1e-12)
    k = 1 + (len(x) - 256) // 128
    # Hann 50 %: rho_1^2 = 1/36 -> nu = 2K^2 / (K + 2 (K-1)/36), about 1.89 K
    assert est.dof[0] == pytest.approx(2 * k**2 / (k + 2 * (k - 1) / 36), rel=1e-3)
    top = log_psd(x, FS, points_per_decade=None)
    sel = top.method == "welch"
    np.testing.assert_allclose(top.psd[sel], p[16:128], rtol=1e-9)
    np.testing.assert_allclose(top.dof[sel], est.dof[14:], rtol=1e-12)


def test_welch_segments_weighted_and_ci_level():
    x = _white(60_000, seed=6)
    est = welch_psd(x, FS, segment_starts=np.array([0, 20_000]), ci=0.683)
    assert est.ci == 0.683
    assert np.all(est.ci_low < est.psd) and np.all(est.psd < est.ci_high)
    wide = welch_psd(x, FS, segment_starts=np.array([0, 20_000]), ci=0.99)
    assert np.all(wide.ci_high > est.ci_high)


def test_bad_input_is_a_clear_error():
    x = _white(10_000)
    x[500] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        log_psd(x, FS)
    with pytest.raises(ValueError, match="NaN"):
        welch_psd(x, FS)
    with pytest.raises(ValueError, match="need 256 contiguous"):
        log_psd(_white(200), FS)
    with pytest.raises(ValueError, match="sampling rate"):
        StreamingPsd(0.0)
    with pytest.raises(ValueError, match="multiple of 16"):
        StreamingPsd(FS, nperseg=100)


def test_default_nperseg():
    assert default_nperseg(10**6) == 256
    assert default_nperseg(300) == 128
    assert default_nperseg(10) == 64



def _avar_from_psd(est, tau, fs):
    """Allan variance implied by a one-sided PSD: the discrete m-sample average's response,
    differenced at lag tau, averaged over each point's bandwidth."""
    u = (np.arange(64) + 0.5) / 64 - 0.5
    f = est.f_hz[:, None] + u[None, :] * est.df_hz[:, None]
    m = tau * fs
    kernel = 2 * np.sin(np.pi * f * tau) ** 2 * (
        np.sin(np.pi * f * tau) / (m * np.sin(np.pi * f / fs))) ** 2
    contrib = est.psd * est.df_hz * kernel.mean(axis=1)
    total = float(contrib.sum())
    return total, float(np.sqrt(np.sum(contrib**2 * 2.0 / est.dof))) / total


def test_real_adis16405_psd_reproduces_published_allan_variance(shared_data):
    """The PSD of real ADIS16405 data, turned into Allan variance, matches the published
    overlapping Allan variance of the same run (avar_curves adis_av) for tau <= 10 s (below
    that the PSD covers the whole band that matters)."""
    run = shared_data / "adis16405" / "run1.npz"
    curves = shared_data / "avar_curves" / "avar_curves.json"
    d = np.load(run)
    gyro = d["gyro_counts"] * float(d["gyro_scale_dps"])
    accel = d["accel_counts"] * float(d["accel_scale_g"])
    fs = float(d["fs_hz"])
    ref = json.loads(curves.read_text())["adis_av"]["channels"]
    for i, name in enumerate(ref):
        x = gyro[:, i] if i < 3 else accel[:, i - 3]
        est = log_psd(x, fs)
        tau = np.array(ref[name]["tau_s"])[:10]
        avar = np.array(ref[name]["avar"])[:10]
        for t, a in zip(tau, avar, strict=True):
            implied, rel_sd = _avar_from_psd(est, t, fs)
            assert abs(implied / a - 1) <= 4 * rel_sd, (name, t, implied / a, rel_sd)
    # data sheet: gyro noise density about 0.05 deg/s/sqrt(Hz) (sqrt of the one-sided PSD)
    top = log_psd(gyro[:, 0], fs)
    density = np.sqrt(np.median(top.psd[top.method == "welch"]))
    assert 0.04 < density < 0.065


def test_log_binning_preserves_power_and_sums_dof():
    x = _white(100_000, seed=8)
    raw = welch_psd(x, FS)
    grouped = welch_psd(x, FS, points_per_decade=20)
    assert len(grouped) < len(raw) / 3
    assert grouped.band_power() == pytest.approx(raw.band_power(), rel=1e-12)
    # merged points carry more dof than one bin, but less than the plain sum (bins correlate)
    assert np.all(grouped.dof >= raw.dof[0] - 1e-9)
    top = grouped.dof[-1]
    n_top = round(grouped.df_hz[-1] / (FS / 256))
    assert raw.dof[0] * n_top / 2 < top < raw.dof[0] * n_top
    truth = 2 * 0.3**2 / FS
    assert 0.85 <= _coverage(grouped, truth) <= 1.0
