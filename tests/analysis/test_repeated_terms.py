"""Repeated terms: the diagnosis offers a second Markov term when the model holds one, and
its suggestion applies as written."""

from __future__ import annotations

import pytest

from analysis.diagnosis import diagnose
from analysis.fit import fit_series
from analysis.noise_stream import NoiseStream

FS = 100.0


def test_a_second_gauss_markov_is_offered_and_applies() -> None:
    x = NoiseStream([("white", {"N": 1e-3}), ("gauss_markov", {"sigma": 3e-4, "T": 2.0}),
                     ("gauss_markov", {"sigma": 2e-4, "T": 300.0})], FS, seed=2).take(1 << 20)
    d = diagnose(x, FS, "white,gauss_markov")
    second = next(s for s in d.suggestions if s.term == "gauss_markov")
    assert second.significant
    assert second.apply["model"] == "white,gauss_markov,gauss_markov"
    assert second.chi2_per_dof_after < 1.5 < d.fit.chi2_per_dof
    # the two time constants are told apart: one short, one long
    fit, _ = fit_series(x, FS, second.apply["model"], intervals="jacobian")
    assert fit.chi2_per_dof == pytest.approx(second.chi2_per_dof_after, rel=1e-6)
    times = sorted(t.params["T"] for t in fit.terms[1:])
    assert times[0] < 10.0 < 100.0 < times[1]


def test_a_term_that_cannot_repeat_is_not_offered_twice() -> None:
    x = NoiseStream([("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5})], FS,
                    seed=3).take(1 << 17)
    d = diagnose(x, FS, "white,random_walk")
    assert [s.term for s in d.suggestions].count("random_walk") == 0
