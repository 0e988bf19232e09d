"""A resonance whose frequency moves through the record is named, with where it went; a
steady one is not."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.evidence.resonance_drift import (
    permutation_p,
    resonance_drift,
    von_neumann_ratio,
)
from imunoise.analysis.fit import fit_series
from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.terms import model_psd

FS = 100.0
N = 2**19
REST = [("white", {"N": 6e-4})]
PEAK = {"sigma": 5e-3, "f0": 20.0, "Q": 15.0}
N_SEEDS = 40
# the permutation test is exact for exchangeable blocks: at 5 % it flags more than 4 of 40
# seeds with probability 4.8 %
MAX_FALSE = 4


def _rest_psd(f: np.ndarray) -> np.ndarray:
    return model_psd(REST, f, FS, continuous_only=True)


def _swept(seed: int, f_start: float, f_end: float, chunks: int = 16) -> np.ndarray:
    """The resonance held at each of ``chunks`` frequencies in turn, from ``f_start`` to
    ``f_end`` Hz, over white noise."""
    return np.concatenate([
        simulate(REST + [("resonance", {**PEAK, "f0": float(f)})], N // chunks, FS,
                 seed * 100 + k)
        for k, f in enumerate(np.linspace(f_start, f_end, chunks))])


def test_von_neumann_ratio_is_two_apart_and_small_along_a_trend() -> None:
    rng = np.random.default_rng(3)
    iid = rng.standard_normal(20000)
    # the ratio of independent values has mean 2 n/(n-1) and sd about 2/sqrt(n)
    assert von_neumann_ratio(iid) == pytest.approx(2.0, abs=4 * 2 / math.sqrt(20000))
    # along a straight line of n points it is 12/(n (n + 1))
    assert von_neumann_ratio(np.linspace(0.0, 1.0, 20)) == pytest.approx(12 / 420)
    assert permutation_p(np.linspace(0.0, 1.0, 20)) == pytest.approx(1e-4)
    assert permutation_p(np.full(20, 3.0)) == 1.0


def test_a_steady_resonance_is_not_named_as_moving_in_95_percent_of_seeds() -> None:
    found = [resonance_drift([simulate(REST + [("resonance", PEAK)], N, FS, 2000 + s)], FS,
                             PEAK["f0"], PEAK["Q"], _rest_psd)
             for s in range(N_SEEDS)]
    assert sum(f.significant for f in found) <= MAX_FALSE
    # and the p-values are uniform: their mean is 1/2 within 3.5 of its standard deviations
    # sqrt(1/12/40)
    assert np.mean([f.p_value for f in found]) == pytest.approx(0.5, abs=3.5 * math.sqrt(1 / 480))
    assert all("keeps its frequency" in f.why for f in found if not f.significant)


def test_a_swept_resonance_is_named_with_where_it_went() -> None:
    for seed in range(6):
        f = resonance_drift([_swept(seed, 20.5, 19.5)], FS, 20.0, PEAK["Q"], _rest_psd)
        assert f.significant and f.p_value < 1e-3, (seed, f.p_value)
        assert f.kind == "resonance_drift" and f.term is None
        # the first and last quarters hold 20.4 and 19.6 Hz on average; a centroid over a band
        # centred on the fitted f0 is pulled toward it by the tails it cuts (by 12-24 % here)
        moved = f.params["f0_first_hz"] - f.params["f0_last_hz"]
        assert 0.6 < moved < 0.85, (seed, f.params)
        assert f.params["wander_hz"] > 2 * f.params["noise_hz"]
        assert len(f.details["f0_hz"]) == 20 and f.details["block_s"] == pytest.approx(
            N / 20 / FS)
        assert "moves through the record" in f.why and "--split" in f.why


def test_a_resonance_that_jumps_is_cut_where_it_jumped() -> None:
    # 20.5 Hz over the first quarter of the record, 19.5 Hz after; times from t0_s = 100 s
    x = np.concatenate([simulate(REST + [("resonance", {**PEAK, "f0": 20.5})], N // 4, FS, 7),
                        simulate(REST + [("resonance", {**PEAK, "f0": 19.5})], 3 * N // 4,
                                 FS, 8)])
    f = resonance_drift([x], FS, 20.0, PEAK["Q"], _rest_psd, t0_s=100.0)
    assert f.significant
    block = f.details["block_s"]
    assert f.details["split_t_s"] == pytest.approx(100.0 + N / 4 / FS, abs=block)
    assert f.details["t_s"][0] == pytest.approx(100.0 + block / 2)
    assert f.range["t_s"] == pytest.approx([100.0, 100.0 + 20 * block])
    # each level's centroid, pulled toward the band's centre (20 Hz) by the tails the band
    # cuts: 0.5 Hz off centre reads as 0.35-0.45 Hz
    assert 0.65 < (f.details["f0_before_hz"] - 20.0) / 0.5 < 0.9, f.details
    assert 0.65 < (20.0 - f.details["f0_after_hz"]) / 0.5 < 0.9, f.details
    assert f"--split {f.details['split_t_s']:.0f}" in f.why


def test_blocks_never_cross_a_gap_and_a_short_record_is_not_tested() -> None:
    x = _swept(1, 20.5, 19.5)
    one = resonance_drift([x], FS, 20.0, PEAK["Q"], _rest_psd)
    # the same samples in three gap-free pieces: only the Welch segments at the joins differ
    cut = resonance_drift([x[:100_000], x[100_000:300_001], x[300_001:]], FS, 20.0,
                          PEAK["Q"], _rest_psd)
    assert cut.significant
    assert np.allclose(cut.details["f0_hz"], one.details["f0_hz"], atol=0.1)
    short = resonance_drift([x[:10_000]], FS, 20.0, PEAK["Q"], _rest_psd)
    assert not short.significant and short.p_value == 1.0
    assert "not tested" in short.why and "too short" in short.why
    beyond = resonance_drift([x], FS, 60.0, PEAK["Q"], _rest_psd)
    assert not beyond.significant and "outside the sampled band (0 .. 50 Hz)" in beyond.why
    for f0, q in ((float("nan"), 15.0), (20.0, float("inf"))):
        bad = resonance_drift([x], FS, f0, q, _rest_psd)
        assert not bad.significant and "not a number" in bad.why
    assert "no peak" in resonance_drift([x], FS, 20.0, 0.0, _rest_psd).why
    assert "not tested" in resonance_drift([], FS, 20.0, 15.0, _rest_psd).why
    # a hump (Q below 2) has no peak to place: its band would take in the whole spectrum
    hump = resonance_drift([x], FS, 10.0, 0.5, _rest_psd)
    assert not hump.significant and "no peak" in hump.why


def test_the_diagnosis_names_a_swept_resonance_of_its_model() -> None:
    x = _swept(2, 20.5, 19.5)
    d = diagnose(x, FS, "white,resonance")
    (f,) = [f for f in d.findings if f.kind == "resonance_drift"]
    assert f.significant and f.params["f0_first_hz"] > f.params["f0_last_hz"] + 0.5
    # a model without a resonance has none to follow
    assert not [f for f in diagnose(x, FS, "white").findings if f.kind == "resonance_drift"]


def test_adis16405_gyro_z_resonance_moves_through_run_1(shared_data: Path) -> None:
    d = np.load(shared_data / "adis16405" / "run1.npz")
    x = d["gyro_counts"][:, 2] * float(d["gyro_scale_dps"]) * math.pi / 180.0
    fs = float(d["fs_hz"])
    fit, _ = fit_series(x, fs, "white,bias_instability,random_walk,resonance",
                        intervals="none")
    rest = [t for t in fit.params if t[0] != "resonance"]
    (res,) = [p for n, p in fit.params if n == "resonance"]
    f = resonance_drift([x], fs, res["f0"], res["Q"],
                        lambda f: model_psd(rest, f, fs, continuous_only=True))
    # the peak starts near 21.7 Hz and settles near 19.8 Hz after the first hour (block
    # centroids measured with this test: first quarter 20.7, last quarter 19.8 Hz)
    assert f.significant and f.p_value <= 1e-3
    assert 20.3 < f.params["f0_first_hz"] < 21.2 and 19.5 < f.params["f0_last_hz"] < 20.1
    assert f.details["f0_hz"][0] > 21.0 > f.details["f0_hz"][-1]
