"""A model whose output filter is the wrong kind gets the right kind in its place; a model
with the right filter keeps it."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.fit import fit_series
from imunoise.analysis.noise_stream import simulate

FS = 50.0
N = int(2 * 3600 * FS)  # 2 h at 50 Hz, as bench/calibrate.py
BASE = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
        ("random_walk", {"K": 2e-6})]
GIVEN = ["white", "bias_instability", "random_walk"]
FILTERS = {"bartlett": {"taps": 3.0}, "lowpass": {"fc": 3.0}}


def _record(filt: str, seed: int, line: bool = False) -> np.ndarray:
    x = simulate(BASE + [(filt, FILTERS[filt])], N, FS, rng=seed)
    if line:  # a 0.55 Hz bench line the model lacks: the model fails, its filter is right
        x = x + 2e-4 * np.sin(2.0 * np.pi * 0.55 * np.arange(N) / FS + 0.3)
    return x


def test_a_lowpass_given_for_a_bartlett_filter_is_replaced() -> None:
    x = _record("bartlett", seed=2)
    d = diagnose(x, FS, GIVEN + ["lowpass"])
    assert d.fit.chi2_per_dof > 100  # a one-pole roll-off cannot follow the window's
    top = d.suggestions[0]
    assert top.significant and top.action == "replace" and top.term == "bartlett"
    assert top.label == "lowpass by bartlett"
    assert top.apply["model"] == "white,bias_instability,random_walk,bartlett"
    assert top.params["taps"] == pytest.approx(3.0, rel=0.05)
    assert top.chi2_per_dof_after < 3.0
    assert top.error_after["psd"]["deviance_per_bin"] < d.error_parts["psd"][
        "deviance_per_bin"]
    assert top.to_dict()["action"] == "replace"
    res, _ = fit_series(x, FS, top.apply["model"])
    assert res.chi2_per_dof == pytest.approx(top.chi2_per_dof_after, rel=1e-9)


@pytest.mark.parametrize("filt", ["lowpass", "bartlett"])
def test_the_right_filter_stays_when_something_else_is_missing(filt: str) -> None:
    d = diagnose(_record(filt, seed=1, line=True), FS, GIVEN + [filt])
    assert d.fit.failures  # the line is missing: the other filters are tried
    swaps = [s for s in d.suggestions if s.action == "replace"]
    assert len(swaps) == 2 and not any(s.significant for s in swaps)
    top = d.suggestions[0]
    assert top.term == "sinusoid" and top.significant
    # nor is another filter applied with the line
    assert top.label == "" and top.apply["model"].split(",")[3] == filt


def test_a_model_that_passes_is_offered_no_other_filter() -> None:
    d = diagnose(_record("lowpass", seed=3), FS, GIVEN + ["lowpass"])
    assert not d.fit.failures
    assert not any(s.action == "replace" for s in d.suggestions)
