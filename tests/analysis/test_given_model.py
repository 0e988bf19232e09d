"""A model whose every parameter is given is evaluated as it stands: nothing is fitted."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.allan import oadev
from imunoise.analysis.fit import fit_allan
from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.terms import TermError, model_avar

FS = 100.0
TRUE = [("white", {"N": 1e-3}), ("gauss_markov", {"sigma": 1e-3, "T": 0.5}),
        ("gauss_markov", {"sigma": 3e-4, "T": 30.0}), ("random_walk", {"K": 1e-5})]
SPEC = "white:N=1e-3,gauss_markov:sigma=1e-3:T=0.5,gauss_markov:sigma=3e-4:T=30,random_walk:K=1e-5"


@pytest.fixture(scope="module")
def curve():
    return oadev(simulate(TRUE, 1 << 19, FS, rng=5), FS, m="octave")


def test_the_true_model_given_is_evaluated_not_fitted(curve):
    res = fit_allan(curve, SPEC)
    assert [t.term for t in res.terms] == ["white", "gauss_markov", "gauss_markov", "random_walk"]
    for got, (_, want) in zip(res.terms, TRUE, strict=True):
        assert got.params == pytest.approx(want, rel=1e-12)
        assert all(lo == hi == got.params[k] for k, (lo, hi) in got.ci95.items())
    assert res.free_params == []
    assert np.allclose(res.avar_fit, model_avar(TRUE, res.tau_s, FS), rtol=1e-12)
    assert res.misfit.dof == len(res.tau_s)  # no parameter was fitted
    assert 0.2 < res.chi2_per_dof < 2.0


def test_a_wrong_given_model_reports_its_error(curve):
    wrong = SPEC.replace("N=1e-3", "N=2e-3")
    res = fit_allan(curve, wrong)
    assert res.terms[0].params["N"] == 2e-3
    assert res.chi2_per_dof > 100 and res.failures


def test_a_model_of_only_a_regressor_is_still_refused(curve):
    with pytest.raises(TermError, match="no noise term"):
        fit_allan(curve, "temperature:coef=0.1")
