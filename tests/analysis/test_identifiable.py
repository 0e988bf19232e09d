"""Identifiable models: no term may imitate another in the sampled band."""

from __future__ import annotations

import numpy as np
import pytest

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


BASE = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}), ("random_walk", {"K": 2e-6})]


def test_a_term_the_record_does_not_resolve_is_offered_for_removal():
    """A Markov term the data do not hold: its sigma's interval reaches zero, nothing is
    missing, so the diagnosis offers to drop it, and its apply.model is the model without it
    (seeds 0-1: chi2 rises by 1.3 and 0.7 on two parameters without it)."""
    for seed in (0, 1):
        x = simulate(BASE, 1 << 18, 50.0, rng=seed)
        d = diagnose(x, 50.0, "white,bias_instability,random_walk,gauss_markov")
        top = d.suggestions[0]
        assert (top.action, top.term, top.label, top.significant) == \
            ("remove", "gauss_markov", "gauss_markov", True)
        assert top.apply["model"] == "white,bias_instability,random_walk"
        assert top.p_value > 0.05
        assert top.ci95["sigma"][0] == 0.0
        doc = top.to_dict()
        assert doc["action"] == "remove" and doc["label"] == "gauss_markov"
        assert "does not resolve gauss_markov" in doc["why"]


def test_a_removal_that_would_raise_the_chi2_per_dof_is_not_significant():
    """Seed 2: the unresolved Markov term's removal raises chi2 by 2.2 on two parameters
    (p 0.34, not needed) but chi2/dof from 0.52 to 0.60: applied, the user would see the
    error rise, so it is offered and not significant."""
    x = simulate(BASE, 1 << 18, 50.0, rng=2)
    d = diagnose(x, 50.0, "white,bias_instability,random_walk,gauss_markov")
    removal = next(s for s in d.suggestions if s.action == "remove")
    assert removal.p_value > 0.05
    assert removal.chi2_per_dof_after > removal.chi2_per_dof_before
    assert not removal.significant and "keep it as an upper bound" in removal.why


def test_a_term_asked_for_by_a_held_parameter_or_the_default_model_is_kept():
    """The same Markov term with its time constant held was asked for; the default model's
    terms are the coefficients a datasheet quotes: neither is offered for removal, although
    its amplitude is not resolved."""
    from imunoise.analysis.terms import get_term

    def unresolved(fit, i):
        term = get_term(fit.terms[i].term)
        return not term.resolved(term.amplitude, fit.terms[i].ci95.get(term.amplitude))

    x = simulate(BASE, 1 << 18, 50.0, rng=0)
    d = diagnose(x, 50.0, "white,bias_instability,random_walk,gauss_markov:T=183")
    assert unresolved(d.fit, 3)
    assert not any(s.action == "remove" for s in d.suggestions)
    x = simulate([("white", {"N": 3e-4})], 1 << 18, 50.0, rng=3)
    d = diagnose(x, 50.0, "white,bias_instability,random_walk")
    assert unresolved(d.fit, 1) or unresolved(d.fit, 2)
    assert not any(s.action == "remove" for s in d.suggestions)


def test_of_two_unresolved_terms_the_one_the_data_need_least_goes_first():
    """Seed 1 given a Markov term and a resonance the record does not hold: both sigmas'
    intervals reach zero; dropping the Markov term raises chi2 by 0.25 on two parameters
    (p 0.88), the resonance by 2.5 on three (p 0.47): the Markov term is offered first."""
    x = simulate(BASE, 1 << 18, 50.0, rng=1)
    d = diagnose(x, 50.0, "white,bias_instability,random_walk,gauss_markov,resonance")
    removals = [s for s in d.suggestions if s.action == "remove"]
    assert [s.term for s in removals] == ["gauss_markov", "resonance"]
    assert removals[0].p_value > removals[1].p_value
    assert d.suggestions[0] is removals[0] and removals[0].significant
    assert removals[0].apply["model"] == "white,bias_instability,random_walk,resonance"


def test_a_markov_term_at_two_sample_periods_is_not_identifiable():
    """A critically damped vibration (f0 8 Hz, Q 0.5) at 100 Hz: a Markov term fitted in its
    place runs to the shortest time the fit allows, two sample periods (a spectrum falling
    towards Nyquist, no correlation time of its own). Output filters are significant too,
    so it is held back and the resonance is named; without the rule the Markov term came
    first (log p -20.4 against -18.9)."""
    model = [("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5}),
             ("resonance", {"sigma": 1e-3, "f0": 8.0, "Q": 0.5})]
    x = simulate(model, 1 << 19, FS, rng=23)
    d = diagnose(x, FS, "white,random_walk", holdout=False, transients=False)
    markov = next(s for s in d.suggestions if s.term == "gauss_markov")
    assert markov.params["T"] == pytest.approx(2.0 / FS, rel=1e-3)
    assert not markov.significant and markov.held_by == "identifiability"
    assert "shortest the fit allows (0.02 s, 2 sample periods)" in markov.why
    assert any(s.significant and s.term in ("moving_average", "bartlett", "lowpass")
               for s in d.suggestions)
    top = next(s for s in d.suggestions if s.significant)
    assert top.term == "resonance"
    assert 5.0 < top.params["f0"] < 11.0

