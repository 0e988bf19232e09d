"""The model-free parts of the covariance and filter integrals, kept between calls: the same
numbers as computing them afresh, keyed by the values of their inputs."""

from __future__ import annotations

import numpy as np

from imunoise.analysis import bin_average, misfit
from imunoise.analysis.bin_average import sin4_table, sin4_table_shared
from imunoise.analysis.misfit import avar_covariance
from imunoise.analysis.terms import get_term, model_avar
from imunoise.analysis.terms.output_filter import _bins

FS = 100.0
MODELS = [
    [("white", {"N": 1e-3}), ("bias_instability", {"B": 3e-4}), ("random_walk", {"K": 3e-4})],
    [("white", {"N": 1e-3}), ("random_walk", {"K": 1e-3}), ("rate_ramp", {"R": 1e-3})],
    [("quantization", {"Q": 1e-4}), ("gauss_markov", {"sigma": 3e-3, "T": 1.0}),
     ("sinusoid", {"A": 3e-3, "f": 2.3}), ("moving_average", {"taps": 3.5})],
]


def test_covariance_from_the_kept_grid_equals_a_fresh_one():
    m = (2 ** np.arange(0, 15)).astype(float)
    n_terms = 2**20 - 2 * m + 1
    for model in MODELS:
        misfit._GRID_CACHE.clear()
        fresh = avar_covariance(model, FS, m, n_terms)
        assert len(misfit._GRID_CACHE) == 1
        again = avar_covariance(model, FS, m.copy(), n_terms)  # same values, other array
        assert len(misfit._GRID_CACHE) == 1
        assert np.array_equal(fresh, again)
    # other averaging factors: a grid of their own
    avar_covariance(MODELS[0], FS, m[:-1], n_terms[:-1])
    assert len(misfit._GRID_CACHE) == 2


def test_kept_grid_cannot_be_changed_by_a_caller():
    m = (2 ** np.arange(0, 10)).astype(float)
    grid = misfit._cov_grid(m)
    for a in (grid.ua, grid.ub, grid.um, grid.width, grid.factors):
        assert not a.flags.writeable


def test_shared_sin4_table_is_the_table_and_keyed_by_values():
    bin_average._TABLES.clear()
    ua, ub, um, width, sin2 = _bins(1e-3 / 2**14, 512)
    assert np.array_equal(width, ub - ua) and np.array_equal(sin2, np.sin(np.pi * um) ** 2)
    m = np.array([[1.0], [2.0], [64.0], [4096.0]])
    got = sin4_table_shared(m, um, ua, ub)
    assert np.array_equal(got, sin4_table(m, um, ua, ub))
    assert sin4_table_shared(m.copy(), um.copy(), ua.copy(), ub.copy()) is got
    assert not got.flags.writeable
    other = sin4_table_shared(m * 2.0, um, ua, ub)
    assert other is not got and len(bin_average._TABLES) == 2
    # bins named by a key: found by the key and m, the same table as by their values
    named = sin4_table_shared(m, um, ua, ub, (1e-3 / 2**14, 512))
    assert np.array_equal(named, got) and len(bin_average._TABLES) == 3
    assert sin4_table_shared(m.copy(), um, ua, ub, (1e-3 / 2**14, 512)) is named


def test_filtered_model_is_the_same_whatever_was_evaluated_before():
    # a fit evaluates the filter at many taps; the kept bins and tables must not leak
    # between them
    tau = 2.0 ** np.arange(0, 16) / FS
    model = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
             ("random_walk", {"K": 2e-6})]
    bin_average._TABLES.clear()
    _bins.cache_clear()
    first = {t: model_avar(model + [("moving_average", {"taps": t})], tau, FS)
             for t in (1.5, 3.7, 4.0, 20.25, 100.5)}
    rng = np.random.default_rng(0)
    for t in rng.uniform(1.0, 30.0, 40):
        model_avar(model + [("bartlett", {"taps": float(t)})], tau, FS)
        model_avar(model + [("moving_average", {"taps": float(t)})], tau, FS)
    get_term("moving_average")._cache.clear()  # recomputed from the kept bins and tables
    for t, want in first.items():
        assert np.array_equal(model_avar(model + [("moving_average", {"taps": t})], tau, FS),
                              want)


def test_one_blas_thread_limits_every_loaded_blas_during_the_call():
    from threadpoolctl import threadpool_info

    from imunoise.analysis.blas import one_blas_thread

    seen = []

    @one_blas_thread
    def inside() -> None:
        seen.extend(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")

    inside()
    assert seen and all(n == 1 for n in seen)
