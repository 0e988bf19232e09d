"""Identifiable models: no term may imitate another in the sampled band."""

from __future__ import annotations

import numpy as np

from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.fit import fit_series
from imunoise.analysis.noise_stream import simulate

FS = 100.0


def test_a_markov_term_is_not_fitted_below_two_sample_periods():
    """On white noise a free Markov term would take a sub-sample T and the white level's
    part; it is held at two sample periods or more, and the white level stays resolved."""
    x = simulate([("white", {"N": 1e-3})], 1 << 18, FS, rng=21)
    fit, _ = fit_series(x, FS, "white,gauss_markov")
    assert fit.terms[1].params["T"] >= 2.0 / FS * (1 - 1e-9)
    lo, hi = fit.terms[0].ci95["N"]
    assert lo > 0.9e-3 and hi < 1.1e-3


def test_suggestions_carry_their_error_after_and_the_diagnosis_its_parts():
    model = [("white", {"N": 1e-3}), ("gauss_markov", {"sigma": 1e-3, "T": 0.5}),
             ("random_walk", {"K": 1e-5})]
    x = simulate(model, 1 << 18, FS, rng=22)
    d = diagnose(x, FS, "white,random_walk")
    top = d.suggestions[0]
    assert top.term == "gauss_markov" and top.significant
    assert top.error_after["chi2_per_dof"] == top.chi2_per_dof_after
    assert top.error_after["psd"]["deviance_per_bin"] < d.error_parts["psd"]["deviance_per_bin"]
    assert top.error_after["holdout"]["chi2_per_dof"] < d.error_parts["holdout"]["chi2_per_dof"]
    assert d.psd is not None and len(d.psd["model_psd"]) == d.error_parts["psd"]["bins"]
    assert set(d.error_parts) == {"psd", "holdout", "time_domain"}
    for s in d.suggestions:
        if s.fit is not None:
            assert s.error_after["psd"]["bins"] > 0
    # every suggestion's time_domain says why it is missing
    assert all("reason" in s.error_after["time_domain"] for s in d.suggestions if s.fit)


def test_nothing_significant_on_a_record_the_model_explains():
    model = [("white", {"N": 1e-3}), ("gauss_markov", {"sigma": 1e-3, "T": 0.5}),
             ("random_walk", {"K": 1e-5})]
    x = simulate(model, 1 << 18, FS, rng=23)
    d = diagnose(x, FS, "white,gauss_markov,random_walk")
    assert not any(s.significant for s in d.suggestions), [
        (s.term, s.p_value) for s in d.suggestions[:3]]
    assert 0.6 < d.error_parts["psd"]["deviance_per_bin"] < 1.5
    assert np.isfinite(d.error_parts["holdout"]["chi2_per_dof"])
