"""Seed setup of Hemerly (2017): 100,000 samples at 100 Hz of white noise (N = 5.75e-2
deg/sqrt(s)), a first-order Markov bias (sigma = 1.55e-2 deg/s, T = 100 s) and rate random walk
(K = 9e-4 deg/s^1.5), fitted with ``white,gauss_markov,random_walk`` over 40 fixed seeds.

The paper's Allan-asymptote reading missed N, B, K by 2.6 %, 22.5 % and 18.2 %. The record is
only ten correlation times long: the Markov hump (near 190 s) and the random walk share the
last two octaves of the curve, whose estimates have 4-10 degrees of freedom, so sigma and K
trade against each other (Hemerly finds the same with ARMA and Kalman methods). N is beaten
by an order of magnitude; the sigma and K targets are not reached and are kept as expected
failures (strict: they turn into errors the day the estimator does better). Figures:
docs/fit.md.
"""

import math

import numpy as np
import pytest

from analysis.fit import fit_allan
from analysis.noise_stream import NoiseStream
from tests._avar_batch import Curve

DEG = math.pi / 180.0
TRUTH = {"N": 5.75e-2 * DEG, "sigma": 1.55e-2 * DEG, "T": 100.0, "K": 9e-4 * DEG}
MODEL = [("white", {"N": TRUTH["N"]}),
         ("gauss_markov", {"sigma": TRUTH["sigma"], "T": TRUTH["T"]}),
         ("random_walk", {"K": TRUTH["K"]})]
SEEDS = 40


@pytest.fixture(scope="module")
def monte_carlo():
    err = {k: [] for k in TRUTH}
    covered = {k: 0 for k in TRUTH}
    for seed in range(SEEDS):
        x = NoiseStream(MODEL, 100.0, seed).take(100_000)
        res = fit_allan(Curve(x, 100.0), "white,gauss_markov,random_walk")
        est = {k: v for t in res.terms for k, v in t.params.items()}
        ci = {k: v for t in res.terms for k, v in t.ci95.items()}
        for k, truth in TRUTH.items():
            err[k].append(abs(est[k] / truth - 1))
            covered[k] += ci[k][0] <= truth <= ci[k][1]
    return ({k: float(np.median(v)) for k, v in err.items()},
            {k: v / SEEDS for k, v in covered.items()})


def test_white_noise_beats_the_paper(monte_carlo):
    median, _ = monte_carlo
    assert median["N"] < 0.026


@pytest.mark.parametrize("param", ["N", "sigma", "T"])
def test_intervals_cover_the_truth_at_their_level(monte_carlo, param):
    _, coverage = monte_carlo
    assert 0.90 <= coverage[param] <= 0.98, coverage


@pytest.mark.xfail(strict=True, reason="K is weakly identified in 1000 s: its profile "
                   "interval covers it in about 78 % of seeds")
def test_random_walk_interval_coverage(monte_carlo):
    _, coverage = monte_carlo
    assert 0.90 <= coverage["K"] <= 0.98, coverage


@pytest.mark.xfail(strict=True, reason="sigma and K are not separable in a 1000 s record "
                   "(median errors about 30 % and 90 %)")
@pytest.mark.parametrize(("param", "paper"), [("sigma", 0.225), ("K", 0.182)])
def test_bias_and_random_walk_beat_the_paper(monte_carlo, param, paper):
    median, _ = monte_carlo
    assert median[param] < paper, median
