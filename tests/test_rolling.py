"""Rolling analyzer: streaming estimators against batch references, fit, diagnosis, history."""

from __future__ import annotations

import allantools
import numpy as np
import pytest

from analysis.live_estimators import OctaveAllan
from analysis.rolling import ChannelAnalyzer, RollingAnalyzer
from daq.blocks import SampleBlock

FS = 100.0
N_TRUE = 3e-3   # rad/s/sqrt(Hz)
K_TRUE = 2e-5   # rad/s/sqrt(s)


def _white_rw(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    white = rng.normal(0, N_TRUE * np.sqrt(FS), n)
    return white + np.cumsum(rng.normal(0, K_TRUE / np.sqrt(FS), n))


def _feed_random_blocks(est, y: np.ndarray, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    i = 0
    while i < y.size:
        k = int(rng.integers(1, 997))
        est.update(y[i:i + k])
        i += k


def test_octave_allan_matches_allantools_whatever_the_block_sizes() -> None:
    y = _white_rw(200_000, 1)
    est = OctaveAllan(FS)
    _feed_random_blocks(est, y)
    curve = est.curve()
    taus, adev, _, _ = allantools.adev(y, rate=FS, data_type="freq", taus=curve.tau_s)
    np.testing.assert_allclose(taus, curve.tau_s)
    np.testing.assert_allclose(curve.dev, adev, rtol=1e-9)
    assert np.all(curve.ci_low < curve.dev) and np.all(curve.dev < curve.ci_high)


def test_octave_allan_never_bridges_a_gap() -> None:
    y = _white_rw(100_000, 2)
    jumped = np.concatenate((y[:50_000], y[50_000:] + 5.0))  # a bias step during a gap
    est = OctaveAllan(FS)
    est.update(jumped[:50_000])
    est.new_segment()
    est.update(jumped[50_000:])
    joined = OctaveAllan(FS)
    joined.update(jumped)
    ref_a, ref_b = OctaveAllan(FS), OctaveAllan(FS)
    ref_a.update(y[:50_000])
    ref_b.update(y[50_000:])
    c, j = est.curve(), joined.curve()
    # Segment-wise sums equal the sum over the two separate halves (same cluster alignment).
    for k in range(len(c.tau_s)):
        o, a, b = est._octaves[k], ref_a._octaves[k], ref_b._octaves[k]
        assert o.count == a.count + b.count
        assert o.sumsq == pytest.approx(a.sumsq + b.sumsq, rel=1e-12)
    assert np.all(j.avar[:8] > c.avar[:8])  # bridging the step inflates every short tau


def test_psd_view_matches_the_fitted_model_and_survives_non_finite_samples() -> None:
    y = _white_rw(200_000, 3)
    y[100_000:100_010] = np.nan  # a burst of bad samples is a gap, not a crash
    a = ChannelAnalyzer("gyro_x", FS)
    _feed_random_blocks(a, y, seed=5)
    assert a.n_samples == 200_000 - 10 and a.n_segments == 2
    a.refresh(force=True)
    p = a.psd()
    f, psd, model = (np.array(p[k]) for k in ("f_hz", "psd", "model_psd"))
    assert p["units"] == "(rad/s)^2/Hz" and np.all(np.isfinite(psd))
    # Above 1 Hz white noise dominates: the estimate scatters around the fitted model within
    # its own band (about 95 % of the points).
    hi = f > 1.0
    inside = (np.array(p["ci_low"]) <= model) & (model <= np.array(p["ci_high"]))
    assert inside[hi].mean() > 0.85
    assert np.median(psd[hi] / (2 * N_TRUE**2)) == pytest.approx(1.0, abs=0.05)


def test_default_fit_recovers_coefficients_within_their_intervals() -> None:
    y = _white_rw(360_000, 4)
    a = ChannelAnalyzer("gyro_x", FS)
    _feed_random_blocks(a, y)
    assert a.refresh(force=True)
    c = a.coefficients()
    terms = {t["term"]: t for t in c["model"]}
    lo, hi = terms["white"]["ci95"]["N"]
    assert lo <= N_TRUE <= hi and (hi - lo) / N_TRUE < 0.1
    lo, hi = terms["random_walk"]["ci95"]["K"]
    assert lo <= K_TRUE <= hi
    assert c["error"]["chi2_per_dof"] < 3.0
    assert terms["white"]["conventional"]["N"]["units"] == "deg/sqrt(h)"
    assert terms["white"]["conventional"]["N"]["value"] == pytest.approx(
        terms["white"]["params"]["N"] * 180 / np.pi * 60)
    # Nothing is missing from this model: no significant suggestion.
    assert not [s for s in a.diagnosis()["suggestions"] if s["significant"]]


def test_sinusoid_is_diagnosed_and_adding_it_lowers_the_error() -> None:
    t = np.arange(360_000) / FS
    y = _white_rw(t.size, 6) + 0.01 * np.sin(2 * np.pi * 2.7 * t)
    a = ChannelAnalyzer("gyro_x", FS)
    a.update(y)
    a.refresh(force=True)
    d = a.diagnosis()
    top = d["suggestions"][0]
    assert top["term"] == "sinusoid" and top["significant"]
    assert top["params"]["f"] == pytest.approx(2.7, rel=0.03)
    assert top["params"]["A"] == pytest.approx(0.01, rel=0.1)
    before = d["error"]["chi2_per_dof"]
    change = a.add_term("sinusoid")
    assert change["error_before"]["chi2_per_dof"] == before
    assert change["error_after"]["chi2_per_dof"] < before / 10
    hist = a.history()
    assert [h["revision"] for h in hist] == [0, 1]
    assert hist[1]["chi2_per_dof"] < hist[0]["chi2_per_dof"]
    assert "sinusoid" not in [s["term"] for s in a.diagnosis()["suggestions"]]
    removed = a.remove_term("sinusoid")
    assert removed["error_after"]["chi2_per_dof"] == pytest.approx(before, rel=1e-9)


def test_model_errors_name_the_valid_terms() -> None:
    a = ChannelAnalyzer("gyro_x", FS)
    with pytest.raises(ValueError, match="valid terms: white, quantization"):
        a.add_term("flicker")
    with pytest.raises(ValueError, match="not in the model"):
        a.remove_term("sinusoid")
    with pytest.raises(ValueError, match="at least one term"):
        a.set_model([])


def test_rolling_set_routes_channels_and_segments_on_gaps() -> None:
    rs = RollingAnalyzer(refit_interval_s=0.0)
    y = _white_rw(3000, 7)
    for i, gap in ((0, 0), (1000, 0), (2000, -1)):
        rs.update(SampleBlock(stream="/a/imu", t=np.arange(1000) / FS, fs_hz=FS, gap_before=gap,
                            channels={"gyro_x": y[i:i + 1000], "temp": np.full(1000, 25.0)}))
    rs.update(SampleBlock(stream="/b/imu", t=np.arange(10) / FS, fs_hz=FS,
                        channels={"gyro_x": np.zeros(10)}))
    assert rs.channels == ["gyro_x", "/b/imu:gyro_x"]
    a = rs.get("gyro_x")
    assert a.n_samples == 3000 and a.n_segments == 2
    with pytest.raises(KeyError, match="valid channels: gyro_x, /b/imu:gyro_x"):
        rs.get("temp")


def test_a_stuck_sensor_gives_no_curve_and_no_fit_rather_than_zeros() -> None:
    a = ChannelAnalyzer("gyro_x", FS)
    a.update(np.full(10_000, 0.25))
    assert a.refresh(force=True) is False
    assert a.allan()["tau_s"] == [] and a.coefficients()["error"] is None
    assert "waiting for data" in a.diagnosis()["note"]
