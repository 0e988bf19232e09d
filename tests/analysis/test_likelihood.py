"""Exact second moments of block means behind imunoise.analysis.likelihood, against brute force: the
covariance of the samples built term by term, block-averaged and differenced by matrices."""

import math

import numpy as np
import pytest

from imunoise.analysis.likelihood import diff_block_acov, neg_loglik, reduce_blocks, within_block_ss
from imunoise.analysis.noise_stream import NoiseStream

FS, M, NB = 10.0, 5, 6


def _operators():
    n = M * NB
    avg = np.zeros((NB, n))
    for j in range(NB):
        avg[j, j * M:(j + 1) * M] = 1.0 / M
    return np.diff(np.eye(NB), axis=0) @ avg, np.eye(M) - 1.0 / M


def _sample_cov(name, p):
    n = M * NB
    k = np.arange(n)
    if name == "white":
        return np.eye(n) * p["N"] ** 2 * FS
    if name == "gauss_markov":
        a = math.exp(-1.0 / (FS * p["T"]))
        return p["sigma"] ** 2 * a ** np.abs(k[:, None] - k[None, :])
    # interval averages of a Wiener process, on a fine sub-grid
    sub = 200
    t = (np.arange(n * sub) + 0.5) / (FS * sub)
    avg = np.kron(np.eye(n), np.ones((1, sub)) / sub)
    return avg @ (p["K"] ** 2 * np.minimum(t[:, None], t[None, :])) @ avg.T


@pytest.mark.parametrize(("name", "params", "tol"), [
    ("white", {"N": 0.2}, 1e-12), ("gauss_markov", {"sigma": 1.3, "T": 0.3}, 1e-12),
    ("gauss_markov", {"sigma": 1.3, "T": 50.0}, 1e-9), ("random_walk", {"K": 0.7}, 1e-4)])
def test_block_moments_match_brute_force(name, params, tol):
    diff_op, centre = _operators()
    cov = _sample_cov(name, params)
    want = (diff_op @ cov @ diff_op.T)[0]
    got = diff_block_acov([(name, params)], FS, M, NB - 2)
    assert np.allclose(got, want, rtol=0, atol=tol * want[0])
    ss = float(np.trace(centre @ cov[M:2 * M, M:2 * M]))
    assert within_block_ss([(name, params)], FS, M) == pytest.approx(ss, rel=tol)


def test_likelihood_peaks_near_the_true_white_level():
    model = [("white", {"N": 1e-3}), ("random_walk", {"K": 2e-5})]
    x = NoiseStream(model, 100.0, 3).take(50_000)
    data = reduce_blocks(x, 100.0, 64)
    grid = np.linspace(0.97, 1.03, 13)
    nll = [neg_loglik([("white", {"N": 1e-3 * g}), model[1]], data) for g in grid]
    assert abs(grid[int(np.argmin(nll))] - 1.0) <= 0.01
