"""Exact Gaussian likelihood of a noise model from block means of the raw record.

The Allan curve summarises a record by a handful of variances; at the longest taus each has
only a few degrees of freedom and their correlations are modelled, not removed. For models
made of white noise, first-order Markov (``gauss_markov``) terms and rate random walk, the
record itself has an exact Gaussian likelihood, and this module maximises it.

The record (rate samples at ``fs``) is cut into blocks of ``m`` samples per gap-free segment.
The likelihood factorises into two nearly independent parts:

* **Differenced block means** ``z_j = ybar_(j+1) - ybar_j``: a stationary Gaussian series
  (differencing removes the constant bias and makes the random walk stationary) whose exact
  autocovariance is the sum of the terms' (``diff_block_acov``). Its likelihood is evaluated
  exactly with a Cholesky factor of the Toeplitz covariance: this part carries the slow terms.
* **Deviations within blocks** ``sum (y_i - ybar)^2``: for white noise a scaled chi-square
  with ``n_blocks (m - 1)`` degrees of freedom; its exact expectation under every term is
  used (``within_block_ss``). This part pins the white-noise level.

The block length is the longest power of two (``choose_block``) at which the non-white terms
of a preliminary model hold under a small fraction of the Allan variance, so almost nothing
about them is left inside the blocks, while the number of blocks stays small enough for a
dense factorisation. Intervals are profile-likelihood intervals (log-likelihood drop 1.92).

Units: rates in SI units of the channel, ``fs`` in Hz, ``T`` in s, ``N`` per sqrt(Hz), ``K``
per sqrt(s), as in :mod:`imunoise.analysis.terms`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import linalg, optimize

from imunoise.analysis.profile import profile_bounds
from imunoise.analysis.terms import TERMS, ar1_avar_shape

ESTIMATOR = "block_likelihood"
"""The name terms list in ``Term.estimators`` when this likelihood supports them."""

_CHI2_95_HALF = 1.920729410347062  # chi2(1) 95 % quantile / 2
_MAX_BLOCKS = 4096
_MIN_BLOCKS = 64

Model = Sequence[tuple[str, dict[str, float]]]


def supports(names: Sequence[str]) -> bool:
    """True when the model can be fitted by :func:`fit_likelihood` (white noise present, every
    term one whose ``Term.estimators`` lists :data:`ESTIMATOR`)."""
    return "white" in names and all(n in TERMS and ESTIMATOR in TERMS[n].estimators
                                    for n in names)


def supported_terms() -> tuple[str, ...]:
    """Names of the terms this likelihood supports."""
    return tuple(n for n, t in TERMS.items() if ESTIMATOR in t.estimators)


# --- exact second moments of block means -----------------------------------------------------

def _ar1_block_cov(sigma: float, T: float, fs: float, m: int, nlags: int) -> np.ndarray:
    """Autocovariance of m-sample means of a point-sampled AR(1) process at lags 0..nlags."""
    b = 1.0 / (fs * T)
    one_a = -math.expm1(-b)
    one_am = -math.expm1(-m * b)
    lags = np.arange(1, max(nlags, 1) + 1, dtype=np.float64)
    c = np.empty(lags.size + 1)
    # cov(mean_0, mean_j) = sigma^2 a^((j-1)m+1) ((1-a^m)/(1-a))^2 / m^2, j >= 1
    c[1:] = sigma * sigma * np.exp(-b * ((lags - 1.0) * m + 1.0)) * (one_am / one_a) ** 2 / m**2
    # c0 - c1 is the Allan variance of m-sample means (evaluated without cancellation)
    c[0] = c[1] + sigma * sigma * float(ar1_avar_shape(np.array([m]), b)[0])
    return c[:nlags + 1]


def diff_block_acov(model: Model, fs: float, m: int, nlags: int) -> np.ndarray:
    """Autocovariance (units^2) of differenced m-sample block means at lags 0..nlags.

    White noise (density N): block mean variance ``v = N^2 fs/m``; differenced: ``2v, -v``.
    Random walk (K): differences of interval averages of a Wiener process over ``tau = m/fs``:
    ``2 K^2 tau/3, K^2 tau/6``. Gauss-Markov: from the exact block-mean autocovariance ``c``,
    ``2(c0 - c1)`` at lag 0, ``c1(1 - A) - (c0 - c1)`` at lag 1 and ``-c_k (1-A)^2/A`` beyond
    (``A = exp(-m/(fs T))``), all without cancellation.
    """
    g = np.zeros(nlags + 1)
    tau = m / fs
    for name, p in model:
        if name == "white":
            v = p["N"] ** 2 * fs / m
            g[0] += 2.0 * v
            if nlags >= 1:
                g[1] -= v
        elif name == "random_walk":
            k2 = p["K"] ** 2
            g[0] += 2.0 * k2 * tau / 3.0
            if nlags >= 1:
                g[1] += k2 * tau / 6.0
        elif name == "gauss_markov":
            sigma, T = p["sigma"], p["T"]
            c = _ar1_block_cov(sigma, T, fs, m, nlags + 1)
            s = c[0] - c[1]  # Allan variance of the block means
            g[0] += 2.0 * s
            if nlags >= 1:
                one_A = -math.expm1(-m / (fs * T))
                g[1] += c[1] * one_A - s
            if nlags >= 2:
                one_A = -math.expm1(-m / (fs * T))
                A = 1.0 - one_A
                g[2:] -= c[2:nlags + 1] * one_A**2 / A
        else:
            raise ValueError(f"no exact block likelihood for term {name!r}")
    return g


def within_block_ss(model: Model, fs: float, m: int) -> float:
    """Expected sum of squared deviations from the block mean within one m-sample block."""
    total = 0.0
    for name, p in model:
        if name == "white":
            total += (m - 1) * p["N"] ** 2 * fs
        elif name == "random_walk":
            # variogram of sample-interval averages of a Wiener process: K^2 Ts (k - 1/3)
            total += p["K"] ** 2 / fs * m * (m - 1) / 6.0
        elif name == "gauss_markov":
            # half the mean squared difference over all pairs: variogram 2 sigma^2 (1 - a^k)
            k = np.arange(1, m, dtype=np.float64)
            b = 1.0 / (fs * p["T"])
            total += 2.0 * p["sigma"] ** 2 / m * float(np.sum((m - k) * -np.expm1(-k * b)))
        else:
            raise ValueError(f"no exact block likelihood for term {name!r}")
    return total


# --- data reduction ---------------------------------------------------------------------------

@dataclass
class BlockData:
    """Sufficient reduction of a record for the block likelihood.

    Attributes:
        fs_hz: sampling rate, Hz.
        m: block length, samples.
        diffs: differenced block means of each gap-free segment (units).
        ss_within: sum over all blocks of squared deviations from the block mean (units^2).
        n_blocks: number of complete blocks.
    """

    fs_hz: float
    m: int
    diffs: list[np.ndarray]
    ss_within: float
    n_blocks: int


def reduce_blocks(values: np.ndarray, fs_hz: float, m: int,
                  segment_starts: np.ndarray | None = None) -> BlockData:
    """Block means (``m`` samples, per segment; a trailing partial block is dropped), their
    differences and the within-block sum of squares."""
    x = np.asarray(values, dtype=np.float64)
    starts = np.asarray(segment_starts if segment_starts is not None else [0], dtype=np.int64)
    bounds = np.append(starts, x.size)
    diffs: list[np.ndarray] = []
    ss = 0.0
    nb = 0
    for s, e in zip(bounds[:-1], bounds[1:], strict=True):
        k = (e - s) // m
        if k < 1:
            continue
        blocks = x[s:s + k * m].reshape(k, m)
        means = blocks.mean(axis=1)
        ss += float(np.sum((blocks - means[:, None]) ** 2))
        nb += k
        if k >= 2:
            diffs.append(np.diff(means))
    return BlockData(float(fs_hz), int(m), diffs, ss, nb)


def choose_block(model: Model, fs_hz: float, n_samples: int, fraction: float = 0.02) -> int:
    """Block length (samples, a power of two) for the likelihood: the longest one at which the
    non-white terms of ``model`` hold at most ``fraction`` of the Allan variance, kept between
    ``n/4096`` and ``n/64`` blocks' worth."""
    from imunoise.analysis.terms import get_term

    lo = max(1, int(2 ** math.ceil(math.log2(max(n_samples / _MAX_BLOCKS, 1.0)))))
    hi = max(lo, int(2 ** math.floor(math.log2(max(n_samples / _MIN_BLOCKS, 1.0)))))
    best = lo
    m = lo
    while m <= hi:
        tau = np.array([m / fs_hz])
        white = sum(float(get_term(n).avar(tau, fs_hz, **p)[0]) for n, p in model
                    if n == "white")
        rest = sum(float(get_term(n).avar(tau, fs_hz, **p)[0]) for n, p in model
                   if n != "white")
        if rest > fraction * (white + rest):
            break
        best = m
        m *= 2
    return best


# --- the likelihood ----------------------------------------------------------------------------

def neg_loglik(model: Model, data: BlockData) -> float:
    """Negative log-likelihood (up to a constant) of ``model`` given the reduced record."""
    fs, m = data.fs_hz, data.m
    nll = 0.0
    longest = max((d.size for d in data.diffs), default=0)
    if longest:
        g = diff_block_acov(model, fs, m, longest - 1)
        cache: dict[int, tuple[np.ndarray, bool]] = {}
        for d in data.diffs:
            n = d.size
            if n not in cache:
                try:
                    cache[n] = linalg.cho_factor(linalg.toeplitz(g[:n]), lower=True,
                                                 check_finite=False)
                except linalg.LinAlgError:
                    return math.inf
            cf = cache[n]
            logdet = 2.0 * float(np.sum(np.log(np.diag(cf[0]))))
            nll += 0.5 * (logdet + float(d @ linalg.cho_solve(cf, d, check_finite=False)))
    dof = data.n_blocks * (m - 1)
    if dof > 0:
        v = within_block_ss(model, fs, m) / (m - 1)
        if not v > 0:
            return math.inf
        nll += 0.5 * dof * (math.log(v) + data.ss_within / (dof * v))
    return nll


# --- the fit ------------------------------------------------------------------------------------

@dataclass
class LikelihoodFit:
    """Maximum-likelihood parameters and 95 % profile-likelihood intervals.

    Attributes:
        params: per term, in model order.
        ci95: per term, ``{param: (low, high)}``; an amplitude whose interval reaches zero is
            reported as ``(0, high)``.
        nll: negative log-likelihood at the maximum.
        block: block length, samples.
        cov_log: inverse observed information of the free log-parameters (order ``keys``).
        keys: ``(term index, parameter)`` of each free parameter.
    """

    params: list[dict[str, float]]
    ci95: list[dict[str, tuple[float, float]]]
    nll: float
    block: int
    cov_log: np.ndarray
    keys: list[tuple[int, str]]


def _bounds(name: str, pname: str, fs: float, duration: float, m: int
            ) -> tuple[float, float]:
    if pname == "T":
        # a correlation time shorter than a block looks like white noise inside the blocks,
        # which the within-block part does not resolve
        return math.log(m / fs), math.log(max(50.0 * duration, 2.0 * m / fs))
    return math.log(1e-30), math.log(1e6)


def fit_likelihood(values: np.ndarray, fs_hz: float, names: Sequence[str],
                   start: Sequence[dict[str, float]], *,
                   segment_starts: np.ndarray | None = None,
                   fixed: dict[tuple[int, str], float] | None = None,
                   block: int | None = None, intervals: bool = True) -> LikelihoodFit:
    """Maximise the exact block-mean likelihood of the model ``names`` from ``start``.

    Args:
        values: rate samples (SI units), segments concatenated.
        fs_hz: sampling rate, Hz.
        names: model terms (see :func:`supports`).
        start: starting parameters per term (e.g. an Allan-curve fit); also sets the block
            length unless ``block`` is given.
        segment_starts: gap-free segment starts.
        fixed: ``{(term index, parameter): value}`` held fixed.
        block: block length in samples (default :func:`choose_block`).
        intervals: compute 95 % profile-likelihood intervals.
    """
    names = list(names)
    if not supports(names):
        raise ValueError(f"no exact likelihood for model {','.join(names)}: it needs white "
                         f"noise and only {', '.join(supported_terms())}")
    fixed = dict(fixed or {})
    x = np.asarray(values, dtype=np.float64)
    fs = float(fs_hz)
    duration = x.size / fs
    start_model = [(n, dict(p)) for n, p in zip(names, start, strict=True)]
    m = int(block) if block else choose_block(start_model, fs, x.size)
    data = reduce_blocks(x, fs, m, segment_starts)

    keys = [(i, pname) for i, n in enumerate(names) for pname in TERMS[n].param_names
            if (i, pname) not in fixed]
    bounds = np.array([_bounds(names[i], k, fs, duration, m) for i, k in keys]).reshape(-1, 2)
    lo_a, hi_a = bounds[:, 0], bounds[:, 1]

    def unpack(theta: np.ndarray) -> list[dict[str, float]]:
        params = [dict(p) for p in start]
        for (i, k), v in fixed.items():
            params[i][k] = v
        for (i, k), v in zip(keys, theta, strict=True):
            params[i][k] = math.exp(float(v))
        return params

    def nll(theta: np.ndarray) -> float:
        val = neg_loglik(list(zip(names, unpack(theta), strict=True)), data)
        return val if math.isfinite(val) else 1e300

    theta0 = np.clip([math.log(max(start[i][k], 1e-300)) for i, k in keys],
                     lo_a + 1e-6, hi_a - 1e-6)
    theta, best = _minimise(nll, theta0, lo_a, hi_a)
    # amplitudes the Allan fit set near zero get a second start, as the likelihood surface
    # of weakly identified terms has a valley along the trade-off between them
    for j, (_, k) in enumerate(keys):
        if k in ("sigma", "K"):
            alt = theta.copy()
            alt[j] = min(theta[j] + 2.0, hi_a[j] - 1e-6)
            th2, v2 = _minimise(nll, alt, lo_a, hi_a)
            if v2 < best - 1e-9:
                theta, best = th2, v2

    hess = _hessian(nll, theta)
    try:
        cov = np.linalg.inv(hess)
    except np.linalg.LinAlgError:
        cov = np.linalg.pinv(hess)
    params = unpack(theta)
    ci: list[dict[str, tuple[float, float]]] = [dict() for _ in names]
    for (i, k), v in fixed.items():
        ci[i][k] = (v, v)
    for j, (i, k) in enumerate(keys):
        if intervals:
            sd = math.sqrt(cov[j, j]) if cov[j, j] > 0 else 1.0
            a, b = _profile(nll, theta, best, j, lo_a, hi_a, sd)
        else:
            sd = math.sqrt(max(cov[j, j], 0.0))
            a, b = theta[j] - 1.959964 * sd, theta[j] + 1.959964 * sd
        low = 0.0 if (a <= lo_a[j] + 1e-3 and k != "T") else math.exp(a)
        ci[i][k] = (low, math.exp(min(b, 700.0)))
    return LikelihoodFit(params, ci, best, m, cov, keys)


def _minimise(fun, theta0: np.ndarray, lo: np.ndarray, hi: np.ndarray
              ) -> tuple[np.ndarray, float]:
    if theta0.size == 0:
        return theta0, fun(theta0)
    sol = optimize.minimize(fun, theta0, method="L-BFGS-B", bounds=list(zip(lo, hi, strict=True)),
                            options={"maxiter": 200})
    th = sol.x
    # polish with Nelder-Mead: the surface is flat along sigma-K trade-offs
    sol2 = optimize.minimize(fun, th, method="Nelder-Mead",
                             options={"xatol": 1e-4, "fatol": 1e-6, "maxiter": 400})
    th2 = np.clip(sol2.x, lo, hi)
    v1, v2 = fun(th), fun(th2)
    return (th2, v2) if v2 < v1 else (th, v1)


def _hessian(fun, theta: np.ndarray, h: float = 1e-3) -> np.ndarray:
    k = theta.size
    out = np.zeros((k, k))
    f0 = fun(theta)
    for i in range(k):
        for j in range(i, k):
            ei = np.zeros(k)
            ej = np.zeros(k)
            ei[i] = h
            ej[j] = h
            if i == j:
                v = (fun(theta + ei) - 2 * f0 + fun(theta - ei)) / h**2
            else:
                v = (fun(theta + ei + ej) - fun(theta + ei - ej) - fun(theta - ei + ej)
                     + fun(theta - ei - ej)) / (4 * h * h)
            out[i, j] = out[j, i] = v
    return out


def _profile(fun, theta: np.ndarray, best: float, j: int, lo: np.ndarray, hi: np.ndarray,
             sd: float) -> tuple[float, float]:
    """95 % profile-likelihood interval of log-parameter ``j``."""
    others = [k for k in range(theta.size) if k != j]

    def excess(v: float, guess: np.ndarray) -> tuple[float, np.ndarray]:
        th = theta.copy()
        th[j] = v
        if not others:
            return fun(th) - best, guess

        def sub(xo: np.ndarray) -> float:
            t2 = th.copy()
            t2[others] = xo
            return fun(t2)

        sol = optimize.minimize(sub, guess, method="L-BFGS-B",
                                bounds=list(zip(lo[others], hi[others], strict=True)),
                                options={"maxiter": 100})
        return float(sol.fun) - best, sol.x

    step = min(max(1.5 * sd, 0.02), 3.0)
    return profile_bounds(excess, float(theta[j]), float(lo[j]), float(hi[j]), step,
                          _CHI2_95_HALF, theta[others], bisections=8)


def fisher_information(model: Model, fs_hz: float, n_samples: int, keys: Sequence[tuple[int, str]],
                       block: int | None = None, step: float = 1e-5) -> np.ndarray:
    """Expected Fisher information of the log-parameters ``keys`` for a gap-free record of
    ``n_samples`` samples under ``model``, from the exact block-mean likelihood:
    ``0.5 tr(S^-1 dS_i S^-1 dS_j)`` for the differenced block means plus the chi-square
    information of the within-block sum of squares. Its inverse is the Cramer-Rao bound of
    any unbiased estimator using the reduced record (blocks short enough that the non-white
    terms are negligible inside them lose almost nothing: see :func:`choose_block`)."""
    base = [(n, dict(p)) for n, p in model]
    m = int(block) if block else choose_block(base, fs_hz, n_samples)
    nb = n_samples // m
    nz = nb - 1

    def moved(j: int, h: float) -> list[tuple[str, dict[str, float]]]:
        out = [(n, dict(p)) for n, p in base]
        i, k = keys[j]
        out[i][1][k] *= math.exp(h)
        return out

    s_inv = np.linalg.inv(linalg.toeplitz(diff_block_acov(base, fs_hz, m, nz - 1)))
    d_s, d_w = [], []
    for j in range(len(keys)):
        up, dn = moved(j, step), moved(j, -step)
        d_s.append((linalg.toeplitz(diff_block_acov(up, fs_hz, m, nz - 1))
                    - linalg.toeplitz(diff_block_acov(dn, fs_hz, m, nz - 1))) / (2 * step))
        d_w.append((math.log(within_block_ss(up, fs_hz, m))
                    - math.log(within_block_ss(dn, fs_hz, m))) / (2 * step))
    a = [s_inv @ d for d in d_s]
    dof = nb * (m - 1)
    k = len(keys)
    info = np.empty((k, k))
    for i in range(k):
        for j in range(i, k):
            info[i, j] = info[j, i] = (0.5 * float(np.sum(a[i] * a[j].T))
                                       + 0.5 * dof * d_w[i] * d_w[j])
    return info
