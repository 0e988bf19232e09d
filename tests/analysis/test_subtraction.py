"""Subtraction of the common part and the three-cornered hat, on simulated benches with known
own noise; ADIS16405 run 1 after subtraction."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from imunoise.analysis.coherence import cross_spectra
from imunoise.analysis.fit import fit_series
from imunoise.analysis.hat import hat_variances, three_cornered_hat, two_sensor_bounds
from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.subtraction import multiple_coherence_threshold, subtract_common
from tests.analysis.bench_records import NAMES, bench_record

OWN_MODELS = {"accel_x": "white,resonance", "accel_y": "white", "accel_z": "white,sinusoid"}


def test_own_white_levels_within_their_intervals_after_subtraction():
    covered = []
    for seed in range(8):
        x, truth = bench_record(100 + seed, n=1 << 16)
        cs = cross_spectra(x, 100.0, NAMES, nperseg=4096)
        for k in (3, 4, 5):
            sub = subtract_common(x, 100.0, NAMES, NAMES[k], cross=cs)
            fit, _ = fit_series(sub.residual, 100.0, OWN_MODELS[NAMES[k]])
            lo, hi = fit.terms[0].ci95["N"]
            covered.append(lo <= truth["N"][k] <= hi)
    # 95 % intervals, 24 trials: P(at most 19 covered) < 0.01
    assert sum(covered) >= 20, covered
    assert stats.binom.cdf(sum(covered) - 1, len(covered), 0.95) > 0.01 or sum(covered) >= 22


def test_residual_needs_no_line_and_the_raw_one_does():
    x, truth = bench_record(7, n=1 << 16)
    sub = subtract_common(x, 100.0, NAMES, "accel_y")
    raw, _ = fit_series(x[:, 4], 100.0, "white")
    own, _ = fit_series(sub.residual, 100.0, "white")
    assert raw.chi2_per_dof > 30 and own.chi2_per_dof < 3
    # the subtracted bands are the common lines' (0.56 Hz, the 1.5 Hz rocking)
    bands = sub.to_dict()["bands_subtracted_hz"]
    assert any(a <= 0.56 <= b + 0.03 for a, b in bands)
    assert any(a <= 1.5 <= b + 0.03 for a, b in bands)
    err = sub.error
    assert 0 < err["bias_factor"] < 1
    assert err["leak_share"] < 0.02 and err["removed_share"] > 4 * err["leak_share"]
    assert err["removed_var"] == pytest.approx(0.01**2 / 2 * 0.45**2 / np.sum(
        np.array([0.72, 0.45, 0.52]) ** 2) + (9.80665 * 2e-3 / (2 * np.pi * 1.5)) ** 2 / 2,
        rel=0.15)


def test_own_line_of_one_channel_is_left_in_its_residual():
    x, _ = bench_record(8, n=1 << 16)
    sub = subtract_common(x, 100.0, NAMES, "accel_z")
    k = np.argmin(np.abs(sub.f_hz - 3.3))
    assert not np.any(sub.subtracted[k - 2:k + 3])
    own, _ = fit_series(sub.residual, 100.0, "white,sinusoid")
    assert own.terms[1].params["A"] == pytest.approx(4e-3, rel=0.1)


def test_independent_channels_are_left_alone():
    rng = np.random.default_rng(3)
    x = rng.normal(size=(1 << 15, 3))
    sub = subtract_common(x, 100.0, ["a", "b", "c"], "a", nperseg=512)
    # family-wise 5 %: at most a few bins, and the residual is the input nearly exactly
    assert np.count_nonzero(sub.subtracted) <= 2
    assert np.std(sub.residual - x[:, 0]) < 0.05


def test_multiple_coherence_threshold_reduces_to_the_single_one():
    from imunoise.analysis.coherence import msc_threshold
    assert multiple_coherence_threshold(50.0, 1, 0.05) == pytest.approx(
        float(msc_threshold(50.0, 0.05)), rel=1e-9)


def test_bad_target_or_references_are_value_errors():
    x = np.zeros((2048, 2))
    with pytest.raises(ValueError, match="no channel"):
        subtract_common(x, 100.0, ["a", "b"], "c")
    with pytest.raises(ValueError, match="references"):
        subtract_common(x, 100.0, ["a", "b"], "a", references=["z"])


def _three_sensors(seed: int, own_n: np.ndarray, n: int = 1 << 16) -> np.ndarray:
    rng = np.random.default_rng(seed)
    common = simulate([("white", {"N": 3e-3}), ("random_walk", {"K": 1e-4}),
                       ("resonance", {"sigma": 0.02, "f0": 2.0, "Q": 5.0})], n, 100.0, rng)
    common += 0.01 * np.sin(2 * np.pi * 0.56 * np.arange(n) / 100.0 + rng.uniform(0, 6.3))
    return np.column_stack([common + simulate([("white", {"N": v})], n, 100.0, rng)
                            for v in own_n])


def test_three_cornered_hat_recovers_own_white_levels_in_40_seeds():
    own_n = np.array([1e-3, 2e-3, 0.5e-3])
    covered = []
    for seed in range(40):
        hat = three_cornered_hat(_three_sensors(seed, own_n), 100.0, ("a", "b", "c"))
        for i in range(3):
            _, (lo, hi) = hat.white_level(i, 0.1)
            covered.append(lo <= own_n[i] <= hi)
    share = np.mean(covered)
    assert share >= 0.9, share


def test_hat_on_sensors_sampled_at_their_own_instants_after_alignment():
    """Three sensors that sample 0, 0.31 and 0.74 of a period apart (as devices recorded
    together do), the second and third interpolated onto the first's times: the own white
    levels stay within their intervals in at least 90 % of 40 seeds."""
    from imunoise.analysis.alignment import align
    from imunoise.core.series import ChannelSeries

    own_n = np.array([1e-3, 2e-3, 0.5e-3])
    offsets = (0.0, 0.31, 0.74)
    n = 1 << 16
    k = np.arange(n // 2 + 1)
    covered = []
    for seed in range(40):
        rng = np.random.default_rng(seed)
        common = simulate([("white", {"N": 3e-3}), ("resonance", {"sigma": 0.02, "f0": 2.0,
                                                                   "Q": 5.0})], n, 100.0, rng)
        spectrum = np.fft.rfft(common)
        series = {}
        for i, (v, frac) in enumerate(zip(own_n, offsets, strict=True)):
            seen = np.fft.irfft(spectrum * np.exp(2j * np.pi * k * frac / n), n)
            x = seen + simulate([("white", {"N": v})], n, 100.0, rng)
            series[str(i)] = ChannelSeries("gyro_x", "rad/s", 100.0, x,
                                           t0_s=5.0 + frac / 100.0)
        got = align(series, "0")
        x = np.column_stack([got.series[str(i)].values for i in range(3)])
        hat = three_cornered_hat(x, 100.0, ("a", "b", "c"))
        for i in range(3):
            _, (lo, hi) = hat.white_level(i, 0.1)
            covered.append(lo <= own_n[i] <= hi)
    share = np.mean(covered)
    assert share >= 0.9, share


def test_hat_variance_formula_matches_monte_carlo():
    """Chi-square pair estimates sharing components: the stated variance of the own-variance
    estimate is the Monte Carlo one."""
    rng = np.random.default_rng(9)
    nu, trials = 40, 20000
    s = np.array([1.0, 2.0, 0.5])
    # nu independent Gaussian draws per sensor give chi-square estimates with shared parts
    e = rng.normal(size=(trials, nu, 3)) * np.sqrt(s)
    def q(i, j):
        return np.mean((e[:, :, i] - e[:, :, j]) ** 2, axis=1)
    est, lo, hi, edf = hat_variances(q(0, 1), q(0, 2), q(1, 2), np.full(trials, nu))
    var_theory = (2 * s[0] ** 2 + s[0] * s[1] + s[0] * s[2] + s[1] * s[2]) / nu
    assert np.var(est) == pytest.approx(var_theory, rel=0.05)
    assert np.mean(est) == pytest.approx(s[0], rel=0.01)
    assert 0.9 < np.mean((lo <= s[0]) & (s[0] <= hi)) < 0.98


def test_two_sensors_bound_the_common_part():
    x = _three_sensors(4, np.array([1e-3, 1e-3, 1e-3]))[:, :2]
    cs = cross_spectra(x, 100.0, ["a", "b"], nperseg=1024)
    b = two_sensor_bounds(cs, "a", "b")
    own_psd = 2 * (1e-3) ** 2  # one-sided PSD of white noise with N = 1e-3
    hi = (b["f_hz"] > 10) & (b["f_hz"] < 40)
    # band means: the estimates are unbiased there (medians of chi-square values are not)
    assert np.mean(b["own_equal_gain"][hi]) == pytest.approx(own_psd, rel=0.1)
    assert np.mean(b["own_at_most"][hi]) >= np.mean(b["own_equal_gain"][hi])
    assert np.all(b["common_at_least"] <= b["psd"])


def test_adis16405_run1_accelerometers_need_no_line_after_subtraction(shared_data):
    from imunoise.analysis import evidence

    d = np.load(shared_data / "adis16405" / "run1.npz")
    x = np.column_stack([d["gyro_counts"] * float(d["gyro_scale_dps"]) * np.pi / 180,
                         d["accel_counts"] * float(d["accel_scale_g"]) * 9.80665])
    cs = cross_spectra(x, 100.0, NAMES, nperseg=8192)
    for k in (3, 4, 5):
        raw = evidence.spectral_lines([x[:, k]], 100.0, units="m/s^2")
        assert raw.significant and abs(raw.params["f"] - 0.564) < 0.002
        sub = subtract_common(x, 100.0, NAMES, NAMES[k], cross=cs)
        own = evidence.spectral_lines([sub.residual], 100.0, units="m/s^2")
        assert not own.significant, own.why


def test_white_level_of_the_residual_states_the_subtraction_error():
    """Read at tau = 1 s (next to the 0.56 Hz line's Allan bump) the raw white level is twice
    the truth; the residual's lies within its interval, whose lower end allows for the
    references' noise passed in."""
    from imunoise.analysis.allan import oadev

    covered = 0
    for seed in range(6):
        x, truth = bench_record(200 + seed, n=1 << 16)
        sub = subtract_common(x, 100.0, NAMES, "accel_y")
        n_true = truth["N"][4]
        value, (lo, hi) = sub.white_level(100.0, 1.0)
        covered += lo <= n_true <= hi
        assert value == pytest.approx(n_true, rel=0.08)
        raw = oadev(x[:, 4], 100.0, m=[100], ci=0.95).dev[0]
        assert raw > 1.5 * n_true
        # the bound on the references' noise passed in: real here (|H| about 0.6 on the line
        # bins), a fifth of the Allan variance at most
        assert 0 < sub.avar_of(sub.psd_leak, 1.0)[0] < 0.25 * value**2
    assert covered >= 5


def test_three_channel_own_psd_with_unequal_gains():
    from imunoise.analysis.hat import three_channel_own_psd

    rng = np.random.default_rng(12)
    n = 1 << 16
    common = simulate([("white", {"N": 5e-3}), ("resonance", {"sigma": 0.05, "f0": 3.0,
                                                               "Q": 3.0})], n, 100.0, rng)
    own_n = np.array([1e-3, 2e-3, 1.5e-3])
    gains = np.array([0.72, -0.45, 0.52])
    x = np.column_stack([g * common + simulate([("white", {"N": v})], n, 100.0, rng)
                         for g, v in zip(gains, own_n, strict=True)])
    cs = cross_spectra(x, 100.0, ["a", "b", "c"], nperseg=1024)
    band = (cs.f_hz > 1) & (cs.f_hz < 20)
    for a, b, c, v in (("a", "b", "c", own_n[0]), ("b", "a", "c", own_n[1]),
                       ("c", "a", "b", own_n[2])):
        own = three_channel_own_psd(cs, a, b, c)
        # one-sided own PSD of white noise N is 2 N^2; the raw PSD is several times more
        assert np.mean(own[band]) == pytest.approx(2 * v**2, rel=0.1)
        assert np.mean(cs.psd(a)[band]) > 2 * np.mean(own[band])


def test_sensors_document_hat_for_three_bounds_for_two():
    from imunoise.analysis.hat import sensors_document

    own_n = np.array([1e-3, 2e-3, 0.5e-3])
    x = _three_sensors(77, own_n)
    values = {f"/imu{i}:gyro_x": x[:, i] for i in range(3)}
    values["/imu0:gyro_y"] = x[:, 0] * 0.5
    values["/imu1:gyro_y"] = x[:, 1] * 0.5
    doc = sensors_document(values, 100.0, white_tau_s=0.1)
    hat = doc["gyro_x"]
    assert hat["method"].startswith("three-cornered hat")
    for i, key in enumerate(values):
        if key.endswith("gyro_x"):
            lo, hi = hat["white_level"][key]["ci"]
            assert lo <= own_n[i] <= hi
    two = doc["gyro_y"]
    assert two["sensors"] == ["/imu0:gyro_y", "/imu1:gyro_y"]
    assert len(two["f_hz"]) == len(two["own_at_most"])
    assert all(c <= p for c, p in zip(two["common_at_least"], two["psd"], strict=True))
