"""Seed setup of Hemerly (2017): 100,000 samples at 100 Hz of white noise (N = 5.75e-2
deg/sqrt(s)), a first-order Markov bias (sigma = 1.55e-2 deg/s, T = 100 s) and rate random walk
(K = 9e-4 deg/s^1.5), fitted with ``white,gauss_markov,random_walk`` over 40 fixed seeds.

The paper's Allan-asymptote reading missed N, B, K by 2.6 %, 22.5 % and 18.2 %. The record is
only ten correlation times long: the Markov hump (near 190 s) and the random walk share the
last two octaves of the curve, whose estimates have 4-10 degrees of freedom, so sigma and K
trade against each other (Hemerly finds the same with ARMA and Kalman methods). N is beaten
by an order of magnitude. The sigma and K targets are out of reach of any unbiased estimator:
the Cramer-Rao bound of the exact Gaussian model at this record length puts the spread of
ln(sigma) near 0.9 and of ln(K) near 1.4 (0.43 and 1.03 with T known), i.e. median errors of
60-90 %, which the test below asserts. The K interval coverage shortfall is kept as a strict
expected failure. Figures: docs/fit.md.
"""

import math

import numpy as np
import pytest

from imunoise.analysis.fit import fit_allan
from imunoise.analysis.likelihood import fisher_information
from imunoise.analysis.noise_stream import NoiseStream
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


def test_sigma_and_k_targets_lie_beyond_the_cramer_rao_bound():
    """The paper's sigma and K errors are below what any unbiased estimator can reach in
    1000 s: the Fisher information of the exact Gaussian model (block-mean likelihood, which
    loses almost nothing at this block length) bounds the spread of ln(sigma) and ln(K)."""
    keys = [(0, "N"), (1, "sigma"), (1, "T"), (2, "K")]
    info = fisher_information(MODEL, 100.0, 100_000, keys, block=256)
    sd = np.sqrt(np.diag(np.linalg.inv(info)))
    # median |relative error| of an efficient unbiased log-normal estimate: ~0.674 sd
    median_bound = 0.6745 * sd
    assert median_bound[0] < 0.026  # N: the target is well inside the bound
    assert median_bound[1] > 2.0 * 0.225, sd  # sigma
    assert median_bound[3] > 2.0 * 0.182, sd  # K
    # with T known the bound is tighter but still beyond the paper's errors
    kept = [0, 1, 3]
    sd_t = np.sqrt(np.diag(np.linalg.inv(info[np.ix_(kept, kept)])))
    assert 0.6745 * sd_t[1] > 0.225 and 0.6745 * sd_t[2] > 0.182, sd_t
