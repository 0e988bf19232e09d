"""Averaging irregular or differently sampled series onto one slow time grid, and a
regression on that grid whose test respects autocorrelated errors.

Slow effects (temperature sensitivity, drift) are tested on bin averages of a few seconds
or more. The residual rate on such a grid is strongly autocorrelated (bias instability,
rate random walk), so an ordinary least-squares p-value would be far too small. The
regression here tests the slope by batch means: slopes fitted in separate blocks of the
record are nearly independent whatever the errors' correlation, and their scatter gives an
honest standard error.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imunoise.analysis import distributions as dist


def bin_means(t_s: np.ndarray, x: np.ndarray, edges_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``x`` in each time bin ``[edges[i], edges[i+1])`` and the sample count per bin.

    Empty bins give NaN.
    """
    t_s = np.asarray(t_s, dtype=np.float64)
    idx = np.searchsorted(edges_s, t_s, side="right") - 1
    ok = (idx >= 0) & (idx < len(edges_s) - 1) & np.isfinite(x)
    nbin = len(edges_s) - 1
    cnt = np.bincount(idx[ok], minlength=nbin).astype(float)
    tot = np.bincount(idx[ok], weights=np.asarray(x, dtype=np.float64)[ok], minlength=nbin)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan), cnt


def slow_grid(t_lo: float, t_hi: float, bin_s: float) -> np.ndarray:
    """Bin edges in seconds covering ``[t_lo, t_hi]`` with bins of ``bin_s`` seconds."""
    n = max(int(np.floor((t_hi - t_lo) / bin_s)), 1)
    return t_lo + bin_s * np.arange(n + 1)


@dataclass
class SlowRegression:
    """Result of ``y = a_j + b x + e`` fitted per block ``j`` and combined across blocks.

    Attributes:
        slope: ``b`` in units of y per unit of x (weighted mean of the block slopes).
        slope_se: its standard error from the scatter of the block slopes.
        t: ``slope / slope_se``.
        dof: degrees of freedom of the t test (usable blocks minus one).
        p_value: two-sided p-value of ``b = 0`` from Student's t.
        block_slopes: the per-block slopes.
        n: number of points used.
    """

    slope: float
    slope_se: float
    t: float
    dof: int
    p_value: float
    block_slopes: list[float]
    n: int


def slow_regression(x: np.ndarray, y: np.ndarray, n_blocks: int = 8) -> SlowRegression:
    """Regress ``y`` on ``x`` with a test that holds for any slowly correlated errors.

    The series is cut into ``n_blocks`` consecutive blocks; in each, ``y`` is regressed on
    ``x`` by least squares with its own intercept (so a wandering bias level is absorbed).
    The block slopes are combined with weights ``sum (x - mean_j x)^2`` (their inverse
    variances when the noise is the same throughout), and the t statistic takes its standard
    error from the scatter of the block slopes themselves (batch means, ``n_blocks - 1``
    dof). Errors whose correlation time is shorter than a block (white noise, bias
    instability, Markov terms) and random walks (independent increments) leave the block
    slopes independent, so the test needs no model of the errors: the price is some power.
    NaNs are dropped.
    """
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = np.asarray(x, float)[ok], np.asarray(y, float)[ok]
    n = x.size
    nb = min(n_blocks, n // 4)
    if nb < 3:
        return SlowRegression(0.0, np.inf, 0.0, 0, 1.0, [], n)
    edges = np.linspace(0, n, nb + 1).astype(int)
    slopes, weights = [], []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        xc = x[a:b] - x[a:b].mean()
        sxx = float(xc @ xc)
        if sxx <= 1e-12 * max(float(np.var(x)) * (b - a), 1e-300):
            continue
        slopes.append(float(xc @ (y[a:b] - y[a:b].mean())) / sxx)
        weights.append(sxx)
    j = len(slopes)
    if j < 3:
        return SlowRegression(0.0, np.inf, 0.0, 0, 1.0, slopes, n)
    bs, w = np.array(slopes), np.array(weights)
    mean = float(np.sum(w * bs) / np.sum(w))
    # Unbiased variance of the weighted mean when var(b_j) = s^2 / w_j.
    s2 = float(np.sum(w * (bs - mean) ** 2)) / (j - 1)
    se = float(np.sqrt(s2 / np.sum(w)))
    tval = mean / se if se > 0 else 0.0
    p = float(2.0 * dist.t.sf(abs(tval), j - 1))
    return SlowRegression(mean, se, tval, j - 1, p, slopes, n)
