"""The distributions module gives scipy.stats' numbers, edges included."""

import numpy as np
import pytest
from scipy import stats

from imunoise.analysis import distributions as d

X = np.array([-1.0, 0.0, 1e-6, 0.5, 3.0, 40.0, 1e3, np.inf, np.nan])
Q = np.array([-0.1, 0.0, 1e-300, 1e-9, 0.025, 0.3, 0.5, 0.975, 1 - 1e-12, 1.0, 1.1, np.nan])
DFS = [0.7, 1.0, 2.0, 7.5, 300.0]


def same(a, b):
    np.testing.assert_allclose(np.asarray(a, dtype=float), np.asarray(b, dtype=float),
                               rtol=1e-13, atol=0.0, equal_nan=True)


@pytest.mark.parametrize("df", DFS)
def test_chi2_matches_scipy_stats(df):
    for name in ("sf", "cdf", "logsf", "logcdf"):
        with np.errstate(divide="ignore"):
            same(getattr(d.chi2, name)(X, df), getattr(stats.chi2, name)(X, df))
    for name in ("isf", "ppf"):
        same(getattr(d.chi2, name)(Q, df), getattr(stats.chi2, name)(Q, df))


@pytest.mark.parametrize("df", DFS)
def test_t_matches_scipy_stats(df):
    x = np.concatenate([X, -X])
    same(d.t.sf(x, df), stats.t.sf(x, df))
    same(d.t.isf(Q, df), stats.t.isf(Q, df))
    same(d.t.ppf(Q, df), stats.t.ppf(Q, df))


def test_norm_and_f_match_scipy_stats():
    x = np.concatenate([X, -X, [38.0, -38.0]])
    same(d.norm.sf(x), stats.norm.sf(x))
    same(d.norm.cdf(x), stats.norm.cdf(x))
    same(d.norm.isf(Q), stats.norm.isf(Q))
    same(d.norm.ppf(Q), stats.norm.ppf(Q))
    for dfn, dfd in [(1, 1), (3, 7), (20.5, 400)]:
        same(d.f.sf(X, dfn, dfd), stats.f.sf(X, dfn, dfd))


def test_degrees_of_freedom_that_are_not_positive_give_nan():
    assert np.isnan(d.chi2.sf(3.0, 0)) and np.isnan(d.chi2.isf(0.05, 0))
    assert np.isnan(d.t.isf(0.05, -1)) and np.isnan(d.f.sf(1.0, 0, 3))


def test_scalars_in_give_numpy_scalars_out():
    v = d.chi2.isf(0.05, 1)
    assert isinstance(v, np.float64) and v == pytest.approx(3.841458820694124, rel=1e-14)
    assert isinstance(d.norm.isf(0.025), np.float64)
    assert d.chi2.ppf([0.025, 0.975], 4).shape == (2,)
