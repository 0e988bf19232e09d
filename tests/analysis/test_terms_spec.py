"""The one model-specification parser and the registry that every caller shares."""

import numpy as np
import pytest

from imunoise.analysis.channel_state import ChannelState, check_terms
from imunoise.analysis.fit import fit_allan
from imunoise.analysis.noise_stream import NoiseStream
from imunoise.analysis.terms import (
    TERMS,
    Term,
    TermError,
    get_term,
    labels,
    parse_model,
    term_names,
)


def test_grammar_fixed_parameters_and_repeated_terms():
    spec = parse_model(" white , gauss_markov:T=100 , gauss_markov#2:T=5:sigma=0.5, random_walk")
    assert spec.names == ["white", "gauss_markov", "gauss_markov", "random_walk"]
    assert spec.labels == ["white", "gauss_markov", "gauss_markov#2", "random_walk"]
    assert spec.fixed == {1: {"T": 100.0}, 2: {"T": 5.0, "sigma": 0.5}}
    # the canonical text parses back to the same model
    assert parse_model(spec.text()) == spec
    assert labels(["sinusoid", "white", "sinusoid"]) == ["sinusoid", "white", "sinusoid#2"]


@pytest.mark.parametrize("text, message", [
    ("white,flicker", r"unknown term\(s\) flicker; valid terms: white, quantization"),
    ("white,white", "term 'white' given twice"),
    ("white:N", "PARAM=VALUE"),
    ("white:N=abc", "PARAM=VALUE"),
    ("white:Q=1", "white has no parameter 'Q'"),
    ("gauss_markov:T=-1", r"gauss_markov\.T = -1 outside"),
    ("gauss_markov#3", "occurrence 1 of gauss_markov is labelled gauss_markov"),
    ("gauss_markov,gauss_markov#3", "occurrence 2 of gauss_markov is labelled gauss_markov#2"),
    (" , ", "empty model"),
])
def test_bad_specifications_name_what_is_valid(text, message):
    with pytest.raises(TermError, match=message):
        parse_model(text)


def test_every_registered_term_carries_its_whole_description():
    assert term_names() == tuple(TERMS)
    for name, term in TERMS.items():
        assert isinstance(term, Term) and term.name == name
        assert term.amplitude in term.param_names
        assert set(term.small_default) == set(term.param_names)
        if term.kind == "filter":
            # an output filter shapes the noise terms: no Allan variance of its own
            assert term.role == "filter" and not term.live
            assert np.all(term.avar(np.array([0.1, 1.0]), 100.0, **term.small_default) == 0)
            continue
        assert term.role in ("noise", "line", "ramp", "regressor")
        assert term.kind == "additive"
        if term.linear:
            assert term.param_names == (term.amplitude,)
        # a doubled amplitude quadruples the Allan variance (white: N^2/tau, ...)
        if term.role != "regressor":
            tau = np.array([0.1, 1.0, 10.0])
            p = dict(term.small_default)
            one = term.avar(tau, 100.0, **p)
            p[term.amplitude] *= 2
            np.testing.assert_allclose(term.avar(tau, 100.0, **p), 4 * one, rtol=1e-12)
    assert term_names(live=True) == tuple(n for n, t in TERMS.items()
                                          if n != "temperature" and t.kind == "additive")
    assert get_term("gauss_markov").repeatable and not get_term("white").repeatable


def test_fit_and_live_service_accept_the_same_fixed_parameter():
    model = [("white", {"N": 1e-3}), ("gauss_markov", {"sigma": 2e-3, "T": 5.0})]
    fs = 100.0
    x = NoiseStream(model, fs, 4).take(1 << 16)
    from imunoise.analysis.allan import oadev
    curve = oadev(x, fs, m="octave")
    res = fit_allan(curve, "white,gauss_markov:T=5")
    assert res.terms[1].params["T"] == 5.0 and res.terms[1].ci95["T"] == (5.0, 5.0)
    check_terms(["white", "gauss_markov:T=5"])  # the live service's check
    a = ChannelState("gyro_x", fs, model=["white", "gauss_markov:T=5"])
    a.update(x)
    job = a.plan_refit(full=False, now=0.0)
    assert job is not None and a.finish_refit(job, job.fn(*job.args), wall_s=0.0)
    assert a.model == ["white", "gauss_markov:T=5"]
    live = a.snapshot().fit  # the published fit holds T where the specification put it
    assert live.terms[1].params["T"] == 5.0
    with pytest.raises(ValueError, match="temperature"):
        check_terms(["white", "temperature"])
