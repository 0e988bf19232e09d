"""A resonance's f0 and Q from the measured spectrum (analysis.spectral_pins)."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.spectral_pins import pin_nperseg, pin_resonances

FS = 100.0
TRUE = [("white", {"N": 1e-3}), ("resonance", {"sigma": 3e-3, "f0": 20.0, "Q": 30.0}),
        ("random_walk", {"K": 1e-5})]
# where an Allan fit leaves a resonance: near the peak, Q loose
ALLAN_LIKE = [("white", {"N": 1.05e-3}), ("resonance", {"sigma": 2.5e-3, "f0": 20.6, "Q": 12.0}),
              ("random_walk", {"K": 1e-5})]


def test_intervals_cover_the_true_shape_over_40_seeds():
    # 95 % intervals: over 40 seeds the count covering the truth is binomial(40, 0.95), 35-40
    # in 98 % of runs; the Hann window's shared bins and a misfit widen the Fisher interval
    # (the power's, sigma_ci95, by the sum of the neighbouring bins' correlations)
    covered_f0 = covered_q = covered_sigma = 0
    for seed in range(40):
        x = simulate(TRUE, 1 << 18, FS, rng=seed)
        (pin,) = pin_resonances(x, FS, ALLAN_LIKE, set())
        assert pin.index == 1 and pin.band_hz[0] < 20.0 < pin.band_hz[1]
        covered_f0 += pin.ci95["f0"][0] <= 20.0 <= pin.ci95["f0"][1]
        covered_q += pin.ci95["Q"][0] <= 30.0 <= pin.ci95["Q"][1]
        covered_sigma += pin.sigma_ci95[0] <= 3e-3 <= pin.sigma_ci95[1]
        assert pin.ci95["f0"][1] - pin.ci95["f0"][0] < 0.1  # the Allan fit's was +-0.5 Hz
    assert 35 <= covered_f0 <= 40 and 35 <= covered_q <= 40 and 35 <= covered_sigma <= 40


def test_held_shapes_and_records_too_short_are_left_alone():
    x = simulate(TRUE, 1 << 18, FS, rng=1)
    assert pin_resonances(x, FS, ALLAN_LIKE, {(1, "f0")}) == []
    assert pin_resonances(x[:4000], FS, ALLAN_LIKE, set()) == []
    assert pin_nperseg(4095) == 0 and pin_nperseg(1 << 18) == 1 << 14


def test_no_peak_is_not_pinned():
    # a broad hump (Q 0.7) is a bend, not a peak: the Allan fit's values stand
    broad = [("white", {"N": 1e-3}), ("resonance", {"sigma": 3e-3, "f0": 10.0, "Q": 0.7})]
    x = simulate(broad, 1 << 18, FS, rng=2)
    assert pin_resonances(x, FS, broad, set()) == []
    white = simulate([("white", {"N": 1e-3})], 1 << 18, FS, rng=2)
    assert pin_resonances(white, FS, ALLAN_LIKE, set()) == []


def test_the_sharper_resonance_takes_the_peak():
    # a broad resonance listed first whose band holds the peak must not take it
    model = [("white", {"N": 1e-3}), ("resonance", {"sigma": 2e-3, "f0": 14.0, "Q": 0.5}),
             ("resonance", {"sigma": 3e-3, "f0": 20.5, "Q": 200.0})]
    x = simulate(TRUE, 1 << 18, FS, rng=5)
    pins = {p.index: p for p in pin_resonances(x, FS, model, set())}
    assert 2 in pins and pins[2].params["f0"] == pytest.approx(20.0, abs=0.05)
    assert 1 not in pins or abs(pins[1].params["f0"] - 20.0) > 1.0


def test_gaps_split_the_estimate():
    x = simulate(TRUE, 1 << 18, FS, rng=6)
    x[100_000] = np.nan
    starts = np.array([0, 100_001])
    (pin,) = pin_resonances(np.delete(x, 100_000), FS, ALLAN_LIKE, set(),
                            segment_starts=starts - np.array([0, 1]))
    assert pin.params["f0"] == pytest.approx(20.0, abs=0.1)
