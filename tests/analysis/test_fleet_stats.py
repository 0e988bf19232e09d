"""Replicates pooled, Cochran's agreement test, robust outliers, growth and limit verdicts."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.fleet_stats import (
    Z95,
    grew,
    limit_verdict,
    log_se,
    pool_replicates,
    robust_outliers,
)

TRIALS = 2000


def _draw(rng, k: int, se: float, tau: float, true: float = 1e-3):
    """k estimates of ``true`` (log-normal, night-to-night sd ``tau`` in log) with 95 %
    intervals of log half-width Z95 * se."""
    x = np.log(true) + rng.normal(0.0, tau, k) + rng.normal(0.0, se, k)
    return np.exp(x), np.exp(x - Z95 * se), np.exp(x + Z95 * se)


def test_log_se_from_interval_and_unresolved():
    se = log_se(np.array([1.0, 0.0, np.nan]), np.array([np.e**2, 1.0, 2.0]))
    assert se[0] == pytest.approx(1.0 / Z95)
    assert np.isnan(se[1]) and np.isnan(se[2])  # an interval reaching zero has no se


def test_agreeing_recordings_rejected_at_the_stated_rate_and_covered():
    """Six recordings of one value: Cochran's test rejects 5 % of the time (binomial sd of
    the count: sqrt(2000 * 0.05 * 0.95) = 9.7; bounds at 4 sd) and the pooled 95 % interval
    covers the truth at least 93 % of the time (the random-effects step only widens it)."""
    rng = np.random.default_rng(7)
    rejected = covered = 0
    for _ in range(TRIALS):
        v, lo, hi = _draw(rng, 6, 0.05, 0.0)
        p = pool_replicates(v, lo, hi)
        rejected += not p.agree
        covered += p.lo95 <= 1e-3 <= p.hi95
    assert 100 - 39 <= rejected <= 100 + 39
    assert covered / TRIALS >= 0.93


def test_disagreeing_recordings_flagged_and_interval_widened():
    """Nights that differ by three times their own interval: the test says so nearly always,
    and the random-effects interval covers the unit's mean far more often than the
    inverse-variance one would (which claims the precision of six nights that disagree)."""
    rng = np.random.default_rng(8)
    rejected = covered = covered_fixed = 0
    for _ in range(TRIALS):
        v, lo, hi = _draw(rng, 6, 0.02, 0.06)
        p = pool_replicates(v, lo, hi)
        rejected += not p.agree
        covered += p.lo95 <= 1e-3 <= p.hi95
        x, se = np.log(v), log_se(lo, hi)
        w = 1 / se**2
        m, s = np.sum(w * x) / np.sum(w), np.sqrt(1 / np.sum(w))
        covered_fixed += abs(m - np.log(1e-3)) <= Z95 * s
    assert rejected / TRIALS > 0.9
    assert covered / TRIALS > 0.85  # DerSimonian-Laird with six studies covers about 0.89
    assert covered_fixed / TRIALS < 0.5


def test_pooling_ignores_unresolved_and_reports_single():
    p = pool_replicates(np.array([1.0, 2.0]), np.array([0.5, 0.0]), np.array([2.0, 4.0]))
    assert p.k == 1 and p.agree is None and p.value == pytest.approx(1.0)
    assert pool_replicates(np.array([1.0]), np.array([0.0]), np.array([2.0])) is None


def test_robust_outliers_flag_the_noisy_unit_only():
    values = np.array([1.0, 1.05, 0.95, 1.1, 0.92, 1.02, 3.0, np.nan, 0.0])
    m, flag = robust_outliers(values)
    assert flag.tolist() == [False] * 6 + [True, False, False]
    assert m[6] > 3.5 and np.all(np.abs(m[:6]) < 3.5) and np.isnan(m[7])


def test_robust_outliers_need_a_population():
    m, flag = robust_outliers(np.array([1.0, 1.1, 5.0, 1.0]))
    assert not flag.any() and np.isnan(m).all()


def test_grew_and_limit_verdicts():
    assert grew((1.0, 1.2), (1.3, 1.5))
    assert not grew((1.0, 1.2), (1.1, 1.5))
    assert not grew((1.0, 1.2), (0.5, 0.8))
    assert limit_verdict(1.0, 0.9, 1.1, maximum=2.0) == "pass"
    assert limit_verdict(1.0, 0.9, 1.1, maximum=1.05) == "marginal"
    assert limit_verdict(1.0, 0.95, 1.1, maximum=0.9) == "fail"
    assert limit_verdict(1.0, 0.9, 1.1, minimum=1.2) == "fail"
    assert limit_verdict(float("nan"), float("nan"), 2.0, maximum=1.0) == "unresolved"
