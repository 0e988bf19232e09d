"""A term's Allan-variance shape remembered across a fit's finite-difference steps gives the
numbers computed without the memo, and the memo stays bounded."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.terms import get_term
from imunoise.analysis.terms.shape_memo import ShapeMemo


def test_a_shape_is_computed_once_and_cannot_be_changed() -> None:
    memo = ShapeMemo(kept=3)
    calls = []

    def make() -> np.ndarray:
        calls.append(1)
        return np.arange(4.0)

    first = memo.get(("a", 1.0), make)
    assert memo.get(("a", 1.0), make) is first and len(calls) == 1
    with pytest.raises(ValueError):
        first[0] = 9.0
    for k in range(3):  # full: emptied, then refilled
        memo.get(("b", k), make)
    memo.get(("a", 1.0), make)
    assert len(calls) == 5


@pytest.mark.parametrize("name, params", [
    ("resonance", {"sigma": 2e-3, "f0": 17.3, "Q": 18.0}),
    ("gauss_markov", {"sigma": 1e-4, "T": 3.0}),
])
def test_a_remembered_shape_gives_the_computed_avar(name: str, params: dict) -> None:
    term = get_term(name)
    tau = np.geomspace(0.01, 1000.0, 18)
    again = term.avar(tau, 100.0, **params)
    first = term.avar(tau.copy(), 100.0, **params)  # equal times: the remembered shape
    np.testing.assert_array_equal(again, first)
    other = {**params, "sigma": 2.0 * params["sigma"]}  # amplitude only: the same shape
    np.testing.assert_allclose(term.avar(tau, 100.0, **other), 4.0 * first, rtol=1e-15)
    shape_param = "f0" if name == "resonance" else "T"
    moved = term.avar(tau, 100.0, **{**params, shape_param: 1.1 * params[shape_param]})
    assert not np.allclose(moved, first, rtol=1e-3, atol=0.0)
