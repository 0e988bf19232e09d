"""A record made through a moving-average output filter (what many IMUs do): the filter's
notch at fs/4 bends the spectrum, yet the diagnosis completes and never offers a term whose
refit raises the error."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.diagnosis import diagnose
from analysis.evidence import spectral_lines
from analysis.noise_stream import NoiseStream

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
