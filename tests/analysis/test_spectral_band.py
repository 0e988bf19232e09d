"""The resonance band fitted to the spectrum: the structure it finds on a simulated record
with two wandering modes, a shelf and an output filter, none where one resonance is the
truth, and the diagnosis's suggestion on a real gyro."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.fit import fit_series
from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.spectral_band import band_fit
from imunoise.analysis.terms import parse_model

SHARED = pathlib.Path(__file__).resolve().parents[2].parent / "shared" / "data"
FS = 100.0
N = int(2 * 3600 * FS)
BASE = [("white", {"N": 6.5e-4}), ("bias_instability", {"B": 1.4e-4}),
        ("random_walk", {"K": 1.4e-5})]
# the ADIS16405 gyro_z band as the spectrum of run 1 shows it
BAND = [("moving_average", {"taps": 1.16}),
        ("resonance", {"sigma": 2.5e-3, "f0": 24.0, "Q": 4.5}),
        ("wandering_resonance", {"sigma": 3.7e-3, "f0": 19.9, "Q": 200.0, "spread": 0.5}),
        ("wandering_resonance", {"sigma": 3.2e-3, "f0": 20.7, "Q": 200.0, "spread": 0.87})]
# what an Allan fit makes of it: a peak and a broad bend
ALLAN_MODEL = [("white", {"N": 5e-4}), ("bias_instability", {"B": 1.4e-4}),
               ("random_walk", {"K": 1.4e-5}),
               ("resonance", {"sigma": 5.2e-3, "f0": 20.27, "Q": 14.4}),
               ("resonance", {"sigma": 2.2e-3, "f0": 8.8, "Q": 0.5})]


def test_two_wandering_modes_a_shelf_and_the_filter_are_found():
    x = simulate(BASE + BAND, N, FS, rng=1)
    b = band_fit(x, FS, ALLAN_MODEL)
    assert b is not None and b.structure == "moving_average, 2 wandering modes"
    assert b.replaced == (3, 4)
    assert b.added == 6  # taps, two wanders' spreads and the second mode's sigma, f0 and Q
    # the Allan fit's structure misses the band's spectrum by 20x more
    assert b.deviance_per_bin < 3.0 < 20.0 < b.given_deviance_per_bin
    terms = dict((n, ps) for n, ps in b.terms if n != "wandering_resonance")
    assert abs(terms["moving_average"]["taps"] - 1.16) < 0.03
    assert abs(terms["resonance"]["f0"] - 24.0) < 0.5
    assert 3.5 < terms["resonance"]["Q"] < 6.0
    modes = sorted(ps["f0"] for n, ps in b.terms if n == "wandering_resonance")
    # the lower mode where it was; the upper one where the record's wander put it (a 2 h
    # record realises its own wander, not the process's)
    assert abs(modes[0] - 19.9) < 0.3 and 20.4 < modes[1] < 21.8
    power = sum(ps["sigma"] ** 2 for n, ps in b.terms if n == "wandering_resonance")
    assert math.isclose(power, 3.7e-3 ** 2 + 3.2e-3 ** 2, rel_tol=0.1)


@pytest.mark.parametrize("seed", [100, 101, 102])
def test_one_resonance_is_left_as_the_model_has_it(seed: int):
    model = BASE + [("resonance", {"sigma": 4e-3, "f0": 20.0, "Q": 15.0})]
    x = simulate(model, N, FS, rng=seed)
    b = band_fit(x, FS, model)
    assert b is not None and b.structure == "as fitted" and b.added == 0
    assert 0.7 < b.deviance_per_bin < 1.3


def test_no_band_where_the_allan_curve_sees_the_resonance():
    # at 9 Hz of 100 Hz the resonance's bump lies on several octave points
    model = BASE + [("resonance", {"sigma": 4e-3, "f0": 9.0, "Q": 15.0})]
    assert band_fit(simulate(model, 200_000, FS, rng=3), FS, model) is None
    assert band_fit(np.zeros(1000), FS, BASE) is None  # no resonance at all


def _band_suggestion(d):
    return next(s for s in d.suggestions if s.label == "band from the spectrum")


def test_the_diagnosis_offers_the_band_and_it_lowers_both_parts():
    x = simulate(BASE + BAND, N, FS, rng=2)
    # the loop's model after two rounds: the peak held where the spectrum put it, a bend
    d = diagnose(x, FS, "white,bias_instability,random_walk,resonance:f0=20.27:Q=14.4,resonance")
    s = _band_suggestion(d)
    psd_before = d.error_parts["psd"]["deviance_per_bin"]
    assert psd_before > 10.0
    assert s.error_after["psd"]["deviance_per_bin"] < 2.0
    assert s.chi2_per_dof_after < s.chi2_per_dof_before
    assert s.action == "replace" and s.term == "wandering_resonance"
    names = [e.name for e in parse_model(s.apply["model"]).entries]
    assert names.count("wandering_resonance") == 2 and "moving_average" in names
    assert "Above 2.03 Hz the spectrum holds more than the Allan curve" in s.why
    # the contract: chi2_per_dof_after is what fit reports for apply.model, as it stands
    res, _ = fit_series(x, FS, s.apply["model"])
    assert res.chi2_per_dof == pytest.approx(s.chi2_per_dof_after, rel=1e-9)


@pytest.mark.skipif(not (SHARED / "adis16405" / "run4.npz").exists(),
                    reason="../shared/data (ADIS16405 recordings) not present")
def test_adis16405_run4_gyro_z_band_closes_the_psd_part():
    d = np.load(SHARED / "adis16405" / "run4.npz")
    x = d["gyro_counts"][:, 2] * float(d["gyro_scale_dps"]) * math.pi / 180.0
    # the loop's model after its first round: one resonance held at the spectrum's peak
    model = ("white,bias_instability,random_walk,"
             "resonance:f0=19.948108586848303:Q=17.648179441283887")
    s = _band_suggestion(diagnose(x, float(d["fs_hz"]), model))
    assert s.significant
    assert "moving_average, 2 wandering modes, shelf" in s.why
    assert s.chi2_per_dof_before > 1000.0 and s.chi2_per_dof_after < 1.7
    assert s.error_after["psd"]["deviance_per_bin"] < 1.6
