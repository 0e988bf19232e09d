"""A record made through a moving-average output filter (what many IMUs do): the filter's
notch at fs/4 bends the spectrum, yet the diagnosis completes and never offers a term whose
refit raises the error."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.evidence import spectral_lines
from imunoise.analysis.noise_stream import NoiseStream, simulate
from imunoise.analysis.terms import model_psd

FS = 100.0
MODEL = [("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-4}), ("random_walk", {"K": 1e-5})]


def _four_tap(seed: int, n: int = 200_000) -> np.ndarray:
    x = NoiseStream(MODEL, FS, seed).take(n)
    return np.convolve(x, np.ones(4) / 4.0, mode="valid")


@pytest.mark.parametrize("seed", [0, 2])
def test_a_notch_is_not_a_line(seed: int) -> None:
    # seeds where the slope into the notch once made the line search significant with no line
    f = spectral_lines([_four_tap(seed)], FS)
    assert f.significant == bool(f.details["lines"])
    assert not f.significant or "f" in f.params


def test_diagnose_completes_on_a_four_tap_moving_average_record() -> None:
    d = diagnose(_four_tap(0), FS, "white,bias_instability,random_walk")
    assert d.suggestions
    for s in d.suggestions:
        assert s.apply["model"].startswith("white,bias_instability,random_walk,")
        if s.significant:
            assert s.chi2_per_dof_after < s.chi2_per_dof_before


# The calibration setting of the model loop: a two-hour, 50 Hz record whose noise passed a
# 4-tap moving average, and the filter in the model (its zero at fs/4 = 12.5 Hz).
_CAL_FS = 50.0
_CAL_MODEL = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
              ("random_walk", {"K": 2e-6}), ("moving_average", {"taps": 4})]


def _cal_model_psd(f: np.ndarray) -> np.ndarray:
    return model_psd(_CAL_MODEL, f, _CAL_FS, continuous_only=True)


def test_a_modelled_notch_is_no_line_in_95_percent_of_40_seeds() -> None:
    n = int(2 * 3600 * _CAL_FS)
    blind = aware = 0
    for seed in range(40):
        x = simulate(_CAL_MODEL, n, _CAL_FS, rng=1000 + seed)
        blind += spectral_lines([x], _CAL_FS).significant
        found = spectral_lines([x], _CAL_FS, model_psd=_cal_model_psd)
        aware += found.significant
        assert found.details["bins_skipped"] < 60  # about 0.04 Hz either side of 12.5 Hz
    # without the model the Hann leakage filling the notch reads as a line in most seeds
    assert blind >= 20
    assert aware <= 2


def test_a_line_beside_a_modelled_notch_is_still_found() -> None:
    n = int(2 * 3600 * _CAL_FS)
    t = np.arange(n) / _CAL_FS
    x = simulate(_CAL_MODEL, n, _CAL_FS, rng=7) + 2e-5 * np.sin(2 * np.pi * 12.3 * t)
    found = spectral_lines([x], _CAL_FS, model_psd=_cal_model_psd)
    assert found.significant
    assert found.params["f"] == pytest.approx(12.3, abs=0.003)
    assert found.params["A"] == pytest.approx(2e-5, rel=0.3)
