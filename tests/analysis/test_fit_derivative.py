"""The Allan fit's derivative (analysis.fit.layout._AvarModel): exact for amplitudes, a
difference of the moved term's group for the other parameters, equal to a central difference
of the whole model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from imunoise.analysis.fit.layout import _AvarModel, _layout
from imunoise.analysis.terms import model_avar

FS = 100.0
TAU = np.geomspace(1.0 / FS, 2000.0, 40)

MODELS = {
    "additive": [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
                 ("random_walk", {"K": 2e-6}), ("resonance", {"sigma": 2e-3, "f0": 13.0,
                                                              "Q": 1.4}),
                 ("sinusoid", {"A": 9e-3, "f": 0.56}), ("gauss_markov", {"sigma": 3e-4,
                                                                         "T": 4.0})],
    "filtered": [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
                 ("random_walk", {"K": 2e-6}), ("moving_average", {"taps": 3.3}),
                 ("resonance", {"sigma": 5e-3, "f0": 20.4, "Q": 20.0}),
                 ("sinusoid", {"A": 9e-3, "f": 0.56})],
}


@pytest.mark.parametrize("case", sorted(MODELS))
def test_the_derivative_is_the_whole_models_central_difference(case):
    model = MODELS[case]
    names = [n for n, _ in model]
    layout = _layout(names, FS, 3e4, {})
    theta = np.array([math.log(model[i][1][k]) for i, k in layout.keys])
    am = _AvarModel(layout, TAU, FS)

    def whole(th):
        params = [dict(p) for _, p in model]
        for (i, k), v in zip(layout.keys, th, strict=True):
            params[i][k] = math.exp(v)
        return model_avar(list(zip(names, params, strict=True)), TAU, FS, checked=False)

    assert np.allclose(am.value(theta), whole(theta), rtol=1e-14, atol=0)
    d = am.derivative(theta)
    h = 1e-5
    for k, (i, name) in enumerate(layout.keys):
        up, down = theta.copy(), theta.copy()
        up[k] += h
        down[k] -= h
        ref = (whole(up) - whole(down)) / (2 * h)
        scale = float(np.max(np.abs(ref))) or 1.0
        # forward difference with a 1.5e-8 relative step: error of order that step
        assert np.max(np.abs(d[:, k] - ref)) <= 1e-5 * scale + 1e-7 * float(
            np.max(am.value(theta))), (names[i], name)


def _column(case: str, term: int, param: str) -> np.ndarray:
    """The fit's derivative column of ``param`` of term ``term`` in model ``case``."""
    model = MODELS[case]
    layout = _layout([n for n, _ in model], FS, 3e4, {})
    theta = np.array([math.log(model[i][1][k]) for i, k in layout.keys])
    return _AvarModel(layout, TAU, FS).derivative(theta)[:, layout.keys.index((term, param))]


def test_an_amplitudes_column_is_twice_its_terms_allan_variance():
    own = model_avar([MODELS["additive"][3]], TAU, FS)
    assert np.allclose(_column("additive", 3, "sigma"), 2.0 * own, rtol=1e-12, atol=0)


def test_behind_a_filter_an_amplitudes_column_is_twice_its_filtered_part():
    model = MODELS["filtered"]
    white_alone = model_avar([model[0], model[3]], TAU, FS)  # white behind the window
    assert np.allclose(_column("filtered", 0, "N"), 2.0 * white_alone, rtol=1e-12, atol=0)
    # the parts are the filtered Allan variance split by term: they add up to it exactly
    from imunoise.analysis.terms import get_term

    noise = [(get_term(n), p) for n, p in model if get_term(n).role == "noise"
             and get_term(n).kind != "filter"]
    ma = get_term("moving_average")
    total, parts = ma.filtered_parts(noise, TAU, FS, model[3][1])
    assert len(parts) == len(noise) == 4
    assert np.array_equal(total, ma.filtered_avar(noise, TAU, FS, model[3][1]))
    assert np.allclose(np.sum(parts, axis=0), total, rtol=1e-14, atol=0)


@pytest.mark.parametrize("step", [1.5e-8, 0.5, 8.0])
def test_a_filtered_term_moved_alone_is_the_whole_filtered_sum_to_the_bit(step):
    """The derivative's shortcut: one term behind the filter moved, the others taken from the
    result before the move. A large move shifts the total enough that another term's
    correction is left out at other tau, which the shortcut must notice."""
    from imunoise.analysis.terms import get_term

    model = MODELS["filtered"]
    noise = [(get_term(n), dict(p)) for n, p in model if get_term(n).role == "noise"
             and get_term(n).kind != "filter"]
    ma = get_term("moving_average")
    taps = model[3][1]
    before = ma.filtered_noise(noise, TAU, FS, taps)
    at = [i for i, (t, _) in enumerate(noise) if t.name == "resonance"][0]
    for name in ("f0", "sigma"):
        moved = list(noise)
        moved[at] = (noise[at][0], {**noise[at][1], name: noise[at][1][name] * (1 + step)})
        fresh = ma.filtered_noise(moved, TAU, FS, taps)
        short = ma.filtered_noise(moved, TAU, FS, taps, like=before, moved=at)
        assert np.array_equal(short.total, fresh.total)
        assert all(np.array_equal(a, b) for a, b in zip(short.parts, fresh.parts, strict=True))
        if name == "sigma" and step == 8.0:
            # the resonance (81 times the power) now hides part of the random walk
            kept = [i for i, (t, _) in enumerate(noise) if t.name == "random_walk"][0]
            assert not np.array_equal(fresh.matters[kept], before.matters[kept])
