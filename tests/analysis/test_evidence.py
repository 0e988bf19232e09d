"""Evidence tests: present -> found, absent -> not significant in >= 95 % of seeds."""

import numpy as np
import pytest
from scipy import stats
from scipy.signal import lfilter

from imunoise.analysis.evidence.finding import family_p
from imunoise.analysis.evidence.lines import spectral_lines, welch_bins
from imunoise.analysis.evidence.outliers import gaps, outliers
from imunoise.analysis.evidence.slow import drift, temperature_correlation
from imunoise.analysis.evidence.slowgrid import bin_means, slow_grid
from imunoise.analysis.evidence.stationarity import noise_level_windows

FS = 100.0
N_SEEDS = 40
# A test whose false-alarm rate is 5 % flags more than 4 of 40 seeds with probability 5 %;
# one at 20 % flags at most 4 with probability 8 %.
MAX_FALSE = 4
SLOW_FS = 10.0      # slow effects need records long against the bias's correlation times
SLOW_N = 36000      # 1 h at 10 Hz


def colored_noise(rng: np.random.Generator, n: int, fs: float = FS, n_white: float = 3e-4,
                  k: float = 2e-5, flicker: float = 5e-5) -> np.ndarray:
    """White + rate random walk + a flicker-like sum of Markov terms (T = 1..1000 s), rad/s."""
    x = rng.standard_normal(n) * n_white * np.sqrt(fs)
    x += np.cumsum(rng.standard_normal(n)) * k / np.sqrt(fs)
    for t_corr in (1.0, 10.0, 100.0, 1000.0):
        a = np.exp(-1.0 / (fs * t_corr))
        x += lfilter([1.0], [1.0, -a], rng.standard_normal(n)) * flicker * np.sqrt(1 - a * a)
    return x


def temperature_profile(t_s: np.ndarray) -> np.ndarray:
    """A warm-up then a slow oscillation of the room, degC."""
    dur = t_s[-1] - t_s[0]
    warm = 8.0 * (1 - np.exp(-t_s / (0.15 * dur)))
    return 25.0 + warm + 1.5 * np.sin(2 * np.pi * t_s / (0.4 * dur))


def false_alarms(make_finding) -> int:
    return sum(bool(make_finding(np.random.default_rng(1000 + s)).significant)
               for s in range(N_SEEDS))


# ---- spectral lines --------------------------------------------------------------------------

def test_welch_bins_white_level_and_dof():
    rng = np.random.default_rng(0)
    x = rng.standard_normal(2**16) * 0.1
    wb = welch_bins([x], FS)
    assert wb.nu == 2 * (2**16 // (wb.f_hz.size - 1) // 2)
    # One-sided white PSD = 2 sigma^2 / fs; bins average to it within a few percent.
    assert np.mean(wb.psd[10:-10]) == pytest.approx(2 * 0.01 / FS, rel=0.03)
    assert wb.enbw_hz == pytest.approx(1.5 * wb.df_hz)


def test_line_found_with_frequency_and_amplitude():
    rng = np.random.default_rng(7)
    n = 60000
    t = np.arange(n) / FS
    x = colored_noise(rng, n) + 3e-4 * np.sin(2 * np.pi * 7.31 * t + 0.4)
    f = spectral_lines([x], FS)
    assert f.significant and f.term == "sinusoid"
    df = f.details["df_hz"]
    assert abs(f.params["f"] - 7.31) < 0.25 * df
    # Amplitude from integrated excess power: within 15 % (noise in 5 Hann bins).
    assert f.params["A"] == pytest.approx(3e-4, rel=0.15)
    assert "7.31" in f.why and f.details["lines"][0]["mains"] == ""


def test_mains_line_and_harmonic_are_labelled():
    rng = np.random.default_rng(3)
    fs = 400.0
    n = 80000
    t = np.arange(n) / fs
    x = colored_noise(rng, n, fs) + 1e-3 * np.sin(2 * np.pi * 50.0 * t) \
        + 8e-4 * np.sin(2 * np.pi * 150.0 * t)
    f = spectral_lines([x], fs)
    labels = {round(l["f_hz"]): l["mains"] for l in f.details["lines"]}
    assert labels[50] == "50 Hz mains"
    assert labels[150] == "harmonic 3 of 50 Hz mains"


def test_a_line_the_model_holds_is_passed_over_for_the_next():
    rng = np.random.default_rng(11)
    n = 60000
    t = np.arange(n) / FS
    x = colored_noise(rng, n) + 6e-4 * np.sin(2 * np.pi * 7.31 * t) \
        + 3e-4 * np.sin(2 * np.pi * 2.2 * t + 1.0)
    assert abs(spectral_lines([x], FS).params["f"] - 7.31) < 0.05
    further = spectral_lines([x], FS, exclude_hz=[7.3])
    assert further.significant and abs(further.params["f"] - 2.2) < 0.05
    assert all(abs(line["f_hz"] - 7.31) > 0.1 for line in further.details["lines"])
    assert not spectral_lines([x], FS, exclude_hz=[7.3, 2.21]).significant


def test_passing_over_held_lines_adds_no_false_alarm():
    # the bins left out shrink the family, so the corrected p-values stay honest
    assert false_alarms(lambda rng: spectral_lines([colored_noise(rng, 30000)], FS,
                                                   exclude_hz=[3.0, 11.0])) <= MAX_FALSE


def test_no_line_in_noise_in_95_percent_of_seeds():
    assert false_alarms(lambda rng: spectral_lines([colored_noise(rng, 30000)], FS)) <= MAX_FALSE


# ---- temperature -----------------------------------------------------------------------------

def _temp_case(rng, coef: float, n: int = SLOW_N):
    t = np.arange(n) / SLOW_FS
    tt = np.arange(0.0, t[-1], 1.0)  # temperature at 1 Hz
    temp = temperature_profile(tt) + rng.standard_normal(tt.size) * 0.05
    x = colored_noise(rng, n, SLOW_FS) + coef * (np.interp(t, tt, temperature_profile(tt)) - 25.0)
    return t, x, tt, temp


def test_temperature_found_with_coefficient():
    rng = np.random.default_rng(11)
    t, x, tt, temp = _temp_case(rng, 1e-3)
    f = temperature_correlation(t, x, tt, temp)
    assert f.significant and f.term == "temperature"
    lo, hi = f.details["coef_ci95"]
    assert lo < 1e-3 < hi
    assert f.params["coef"] == pytest.approx(1e-3, rel=0.25)


def test_temperature_absent_not_significant_in_95_percent_of_seeds():
    def one(rng):
        t, x, tt, temp = _temp_case(rng, 0.0)
        return temperature_correlation(t, x, tt, temp)
    assert false_alarms(one) <= MAX_FALSE


def test_naive_pearson_would_be_fooled_but_batch_means_is_not():
    # The slow bias wanders (random walk, long Markov terms): a naive correlation with the
    # temperature is "significant" in most seeds, the batch-means test in few.
    hits = naive = 0
    for s in range(N_SEEDS):
        t, x, tt, temp = _temp_case(np.random.default_rng(2000 + s), 0.0)
        f = temperature_correlation(t, x, tt, temp)
        hits += f.significant
        edges = slow_grid(0.0, tt[-1], f.details["bin_s"])
        xb, yb = bin_means(tt, temp, edges)[0], bin_means(t, x, edges)[0]
        ok = np.isfinite(xb) & np.isfinite(yb)
        naive += stats.pearsonr(xb[ok], yb[ok]).pvalue < 0.05
    assert hits <= MAX_FALSE
    assert naive > N_SEEDS // 2


def test_flat_temperature_is_reported_not_crashed():
    t = np.arange(1000) / FS
    f = temperature_correlation(t, np.zeros(1000), t, np.full(1000, 25.0))
    assert not f.significant and "did not change" in f.why


# ---- drift -----------------------------------------------------------------------------------

def test_drift_found_with_rate():
    rng = np.random.default_rng(5)
    t = np.arange(SLOW_N) / SLOW_FS
    r = 3e-6  # rad/s^2: 1.1e-2 rad/s over the hour, ten times the random walk's excursion
    f = drift(t, colored_noise(rng, SLOW_N, SLOW_FS) + r * t)
    assert f.significant and f.term == "rate_ramp"
    lo, hi = f.details["R_ci95"]
    assert lo < r < hi


def test_drift_absent_not_significant_in_95_percent_of_seeds():
    t = np.arange(SLOW_N) / SLOW_FS
    assert false_alarms(lambda rng: drift(t, colored_noise(rng, t.size, SLOW_FS))) <= MAX_FALSE


# ---- non-stationarity --------------------------------------------------------------------------

def test_warm_up_noise_level_found():
    rng = np.random.default_rng(2)
    n = 40000
    x = colored_noise(rng, n)
    x[: n // 8] += rng.standard_normal(n // 8) * 3e-4 * np.sqrt(FS) * 0.4  # noisier start
    f = noise_level_windows([x], FS)
    assert f.significant and "warm-up" in f.why
    assert f.details["window_N"][0] > 1.05 * f.details["window_N"][-1]


def test_stationary_not_significant_in_95_percent_of_seeds():
    def one(rng):
        return noise_level_windows([colored_noise(rng, 20000)], FS)
    assert false_alarms(one) <= MAX_FALSE


# ---- outliers and gaps -----------------------------------------------------------------------

def test_outliers_found_where_placed():
    rng = np.random.default_rng(4)
    x = colored_noise(rng, 50000)
    sigma = 3e-4 * np.sqrt(FS)
    where = [1234, 20000, 45001]
    x[where] += 9 * sigma
    f = outliers([x], FS)
    assert f.significant
    assert f.details["indices"] == where


def test_outliers_absent_in_95_percent_of_seeds():
    assert false_alarms(lambda rng: outliers([colored_noise(rng, 50000)], FS)) <= MAX_FALSE


def test_outlier_threshold_grows_with_length():
    rng = np.random.default_rng(0)
    short = outliers([rng.standard_normal(1000)], FS).details["threshold_z"]
    long = outliers([rng.standard_normal(100000)], FS).details["threshold_z"]
    assert 3.5 < short < long < 5.5


def test_gaps_counted_with_missing_time():
    f = gaps(np.array([0, 100, 250]), 300, 10.0, segment_t0_s=np.array([0.0, 12.0, 30.0]))
    assert f.details == {"count": 2, "missing_s": pytest.approx(2.0 + 3.0)}
    assert gaps(np.array([0]), 300, 10.0).details["count"] == 0


def test_family_p_matches_sidak_and_keeps_tiny_values():
    assert family_p(0.01, 1) == pytest.approx(0.01)
    assert family_p(0.01, 5) == pytest.approx(1 - 0.99**5)
    assert family_p(1e-18, 1000) == pytest.approx(1e-15, rel=1e-6)
