"""Bias steps and warm-up transients, tested against the fitted noise model.

A knock that shifts the bias, or a bias that settles exponentially after power-on, bends the
Allan curve much as rate random walk or flicker do, and those also wander: a test that ignores
them calls every random walk a step. Here the record is cut into about ``BLOCKS`` blocks and
the block means ``ybar_i`` are examined through zero-sum contrasts ``w . ybar``: for each
split point, the mean after minus the mean before, over the whole record and over two blocks
on each side (a step), and for each time constant, the
least-squares amplitude of ``exp(-t/T)`` beside a constant (a warm-up). Under the fitted noise
model (no step, no warm-up) the contrasts are jointly Gaussian with covariance
``-sum_ij w_i w'_j V(|i-j|)``, where ``V(k) = E[(ybar_{i+k} - ybar_i)^2] / 2`` is the model's
block-mean variogram, ``V(k) = 2 int_0^{fs/2} S(f) |M_b(f)|^2 sin^2(pi f k b / fs) df`` with
``|M_b|^2`` the power response of a b-sample mean. The statistic is the largest standardised
contrast; its p-value is the probability of a larger one under the model, estimated from
``DRAWS`` draws of the contrasts (exact in distribution, not a bound), with a Bonferroni
normal tail where the draws run out. So the false-alarm rate holds for records with random
walk and flicker when the model holds them.

Once found, the step's time and size and the warm-up's time constant and amplitude are
estimated by generalised least squares on the first differences of the block means (the bias
drops out, and under the model the differences are Gaussian with covariance
``V(k+1) + V(k-1) - 2 V(k)`` at lag ``k``), the nonlinear parameter profiled on a fine grid.
A step inside a block moves that block's mean by the fraction of the block after it, so its
time is resolved below one block. The 95 % intervals are profile-likelihood intervals at the
chi-square(1) level 3.84. A change point is not a regular parameter, and for a step small
against the noise of many blocks the level would be 7.35 (the limit of the likelihood ratio
is then twice the larger of two independent unit exponentials); but over the steps this test
detects, the profile within the step's block is sharp enough that 3.84 keeps the coverage of
the time near 95 % (simulated: 91 % at the detection limit, 98-99 % at 1.6-4 times it), where
7.35 covers 99-100 %. The step's time is then refined to the sample (:func:`_sample_step`),
where every step is small against the noise of single samples and 7.35 is the level.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from scipy.linalg import solve_triangular

from imunoise.analysis import distributions as dist
from imunoise.analysis.blas import one_blas_thread
from imunoise.analysis.evidence.finding import Finding
from imunoise.analysis.terms import get_term, model_psd
from imunoise.analysis.terms.output_filter import OutputFilter

BLOCKS = 120
"""Number of blocks the longest segment is cut into."""
MIN_BLOCK_SAMPLES = 16
DRAWS = 4000
_SEED = 20261125


def _exact_variogram(r: np.ndarray, b: int, lags: np.ndarray) -> np.ndarray:
    """``V(k)`` of b-sample block means of a stationary sequence whose autocovariance ``r``
    ends before ``b`` lags: ``var(ybar) - cov(ybar_0, ybar_k)``."""
    r = np.asarray(r, dtype=np.float64)
    lag = np.arange(len(r), dtype=np.float64)
    var = (b * r[0] + 2.0 * float(np.sum((b - lag[1:]) * r[1:]))) / (b * b)
    cov1 = float(np.sum(lag[1:] * r[1:])) / (b * b)  # pairs straddling one boundary
    return np.where(lags == 0, 0.0, var - np.where(lags == 1, cov1, 0.0))


_FILTER_NEGLIGIBLE = 1e-5
"""Bound on a filter's effect on the spectral terms' variogram, relative to the variogram,
below which the spectral integral leaves the filter out (see :func:`_variogram`)."""


def _variogram(model: Sequence[tuple[str, dict[str, float]]], fs_hz: float, b: int,
               lags: np.ndarray) -> np.ndarray:
    """``V(k)`` of b-sample block means of the model's Gaussian noise (units^2): white noise
    and quantization exactly in the time domain (through the filters: their autocovariance
    convolved with the filters' autocorrelation), the other terms by the spectral integral of
    the module's docstring.

    A filter changes the other terms' spectra only towards Nyquist, where a block mean's gain
    is about ``1 / (b sin(pi u))^2``: their variogram moves by at most
    ``2 fs int S(u) (1 - |G|^2) w(u) du``, ``w = 2 min(1, (b sin pi u)^-2) min(1, (pi u k b)^2)``
    bounding the integrand's weight at lag ``k``. Where that bound is below
    :data:`_FILTER_NEGLIGIBLE` of the variogram at every lag (flicker and random walk beside a
    sensor's short filter; the Allan variance's own filter correction is left out below the
    same level), the integral leaves the filters out and needs no grid fine enough for
    their ripple (120 lags by 65536 bins took 0.47 s of every fit with a filter)."""
    filters = [(t, p) for n, p in model if isinstance(t := get_term(n), OutputFilter)]
    out = np.zeros(len(lags))
    spectral = []
    for n, p in model:
        term = get_term(n)
        if term.kind == "filter" or term.role != "noise":
            continue
        r = term.autocovariance(fs_hz, p)
        for filt, fp in filters if r is not None else []:
            r = filt.filtered_autocovariance(r, fs_hz, fp)
        if r is not None and len(r) < b:
            out += _exact_variogram(r, b, lags)
        else:
            spectral.append((n, p))
    if not spectral:
        return out
    k_max = float(max(lags.max(), 1))
    u_lo = 1e-3 / (k_max * b)
    ua, ub, um = _edges(u_lo, 2048)
    s = model_psd(spectral, um * fs_hz, fs_hz)
    total = out + _spectral_variogram(s, ua, ub, um, fs_hz, b, lags)
    if not filters:
        return total
    gain = np.prod([f.response(um * fs_hz, fs_hz, p) for f, p in filters], axis=0)
    # the integrand's weight 2 mean_gain sin^2(pi u k b) is at most
    # 2 min(1, (b sin pi u)^-2) min(1, (pi u k b)^2), lag by lag
    with np.errstate(divide="ignore"):
        per_bin = 4.0 * fs_hz * s * np.clip(1.0 - gain, 0.0, None) \
            * np.minimum(1.0, (b * np.sin(np.pi * um)) ** -2.0) * (ub - ua)
    k = np.asarray(lags, dtype=np.float64)[:, None]
    bound = np.minimum(1.0, (np.pi * um[None, :] * k * b) ** 2) @ per_bin
    if np.all(bound[lags > 0] <= _FILTER_NEGLIGIBLE * total[lags > 0]):
        return total
    ua, ub, um = _edges(u_lo, int(min(max(16 * b, 512), 65536)))
    s = model_psd(spectral + [(f.name, p) for f, p in filters], um * fs_hz, fs_hz)
    return out + _spectral_variogram(s, ua, ub, um, fs_hz, b, lags)


def _edges(u_lo: float, n_lin: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bins ``(ua, ub, um)`` in ``u = f/fs`` from ``u_lo`` to 1/2: log-spaced, and ``n_lin``
    linear ones."""
    edges = np.unique(np.concatenate((
        np.geomspace(u_lo, 0.5, int(np.log10(0.5 / u_lo) * 200) + 2),
        np.linspace(0.0, 0.5, n_lin + 1)[1:])))
    ua, ub = edges[:-1], edges[1:]
    return ua, ub, 0.5 * (ua + ub)


def _spectral_variogram(s: np.ndarray, ua: np.ndarray, ub: np.ndarray, um: np.ndarray,
                        fs_hz: float, b: int, lags: np.ndarray) -> np.ndarray:
    """The spectral integral of the module's docstring over the bins ``ua..ub`` (mid-points
    ``um``) of a PSD ``s`` (units^2/Hz at ``um * fs``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        mean_gain = (np.sin(np.pi * um * b) / (b * np.sin(np.pi * um))) ** 2
    base = 2.0 * s * mean_gain * (ub - ua) * fs_hz
    x = 2.0 * np.pi * np.asarray(lags, dtype=np.float64)[:, None] * b
    width = (ub - ua)[None, :]
    # sin^2(pi u k b) averaged over each bin: (1 - <cos(2 pi u k b)>) / 2
    with np.errstate(divide="ignore", invalid="ignore"):
        avg_cos = np.where(x * width > 0.05,
                           (np.sin(x * ub) - np.sin(x * ua)) / (x * width),
                           np.cos(x * um))
    return (0.5 * (1.0 - avg_cos)) @ base


def _contrast_cov(w: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Covariance of zero-sum contrasts ``w`` (rows) of block means with variogram ``v``."""
    n = w.shape[1]
    idx = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    gamma = v[idx]
    return -(w @ gamma @ w.T)


_LR95_REGULAR = float(dist.chi2.isf(0.05, 1))
_STEP_GRID_PER_BLOCK = 50
_WARMUP_GRID = 400


def _difference_whitener(v: np.ndarray, n: int) -> np.ndarray:
    """Cholesky factor of the covariance of the ``n - 1`` first differences of ``n`` block
    means whose variogram is ``v`` (``v[k]`` for ``k = 0 .. n - 1``)."""
    k = np.abs(np.subtract.outer(np.arange(n - 1), np.arange(n - 1)))
    vv = np.concatenate((v, [v[-1]]))
    cov = vv[k + 1] + vv[np.abs(k - 1)] - 2.0 * vv[k]
    scale = float(np.mean(np.diag(cov)))
    if not np.isfinite(scale) or scale <= 0.0:
        raise np.linalg.LinAlgError("no noise in the model")
    return np.linalg.cholesky(cov + np.eye(n - 1) * scale * 1e-12)


def _profile(chol: np.ndarray, ybar: np.ndarray, shapes: np.ndarray) -> tuple[
        np.ndarray, np.ndarray, np.ndarray, float]:
    """GLS fit of ``ybar = mu + a * shape`` for each row of ``shapes`` (block units), on the
    differences: the amplitude ``a`` per row, its variance, ``-2 log L`` above the best row,
    and the best row's fall of ``-2 log L`` from no shape at all."""
    d = solve_triangular(chol, np.diff(ybar), lower=True)
    xs = solve_triangular(chol, np.diff(shapes, axis=1).T, lower=True)
    info = np.sum(xs * xs, axis=0)
    score = xs.T @ d
    with np.errstate(divide="ignore", invalid="ignore"):
        amp = np.where(info > 0, score / info, 0.0)
        gain = np.where(info > 0, score * score / info, 0.0)
        var = np.where(info > 0, 1.0 / info, np.inf)
    best = float(np.max(gain))
    return amp, var, best - gain, best


def _amplitude_sets(amp: np.ndarray, var: np.ndarray, lr: np.ndarray
                    ) -> tuple[tuple[float, float], tuple[float, float] | None]:
    """The amplitude's 95 % profile interval over the nonlinear parameter's grid, and, where
    the profile set has pieces of both signs with zero in none, the hull of the pieces of the
    sign opposite to the best amplitude's (else None). A knock (the bias leaves and comes
    back) fits as a step up at its start and as a step down at its end: the hull of both
    would reach across zero although no size near zero fits."""
    ok = (lr <= _LR95_REGULAR) & np.isfinite(var)
    half = np.sqrt((_LR95_REGULAR - lr[ok]) * var[ok])
    lo, hi = amp[ok] - half, amp[ok] + half
    if not np.any((lo <= 0.0) & (hi >= 0.0)):
        best = float(amp[int(np.argmin(lr))])
        same = (lo > 0.0) if best > 0.0 else (hi < 0.0)
        if not np.all(same):
            return ((float(np.min(lo[same])), float(np.max(hi[same]))),
                    (float(np.min(lo[~same])), float(np.max(hi[~same]))))
    return (float(np.min(lo)), float(np.max(hi))), None


def _step_estimate(chol: np.ndarray, ybar: np.ndarray) -> dict[str, Any]:
    """Step time (blocks from the segment start) and size, with 95 % intervals."""
    n = ybar.size
    t = np.arange(_STEP_GRID_PER_BLOCK, (n - 1) * _STEP_GRID_PER_BLOCK + 1) / _STEP_GRID_PER_BLOCK
    shapes = np.clip(np.arange(n)[None, :] + 1.0 - t[:, None], 0.0, 1.0)
    amp, var, lr, gain = _profile(chol, ybar, shapes)
    best = int(np.argmin(lr))
    inside = t[lr <= _LR95_REGULAR]
    # the true time lies between grid points: one grid step more on each side
    step = 1.0 / _STEP_GRID_PER_BLOCK
    size_ci, other = _amplitude_sets(amp, var, lr)
    return {"t": float(t[best]), "size": float(amp[best]), "gain": gain,
            "t_ci": (max(float(inside.min()) - step, 0.0), min(float(inside.max()) + step, n)),
            "size_ci": size_ci, "size_ci_other": other}


_LR95_CHANGE_POINT = 7.35
"""95 % point of the likelihood ratio of a change point whose step is small against the noise
of the samples around it (twice the larger of two independent unit exponentials): the
regime of every step this test finds, seen sample by sample."""


_LONG_RUN_SPAN = 32
"""Span (in step-response lengths) of the sums whose variance scales the change point's
likelihood ratio (:func:`_sample_step`)."""


def _step_response(model: Sequence[tuple[str, dict[str, float]]], fs_hz: float) -> np.ndarray:
    """The sensor's response to a unit bias step, sample by sample until it settles: the
    cumulated impulse response of the model's output filter (unit gain), or ``[1.0]``."""
    for name, params in model:
        term = get_term(name)
        if term.kind == "filter" and isinstance(term, OutputFilter):
            g = np.asarray(term.impulse_response(fs_hz, params), dtype=np.float64)
            if g.size and abs(float(g.sum())) > 0.0:
                return np.cumsum(g) / float(g.sum())
    return np.ones(1)


def _sample_step(x: np.ndarray, b: int, est: dict[str, Any], response: np.ndarray
                 ) -> tuple[int, int, int] | None:
    """The step's first sample, refined from the block estimate ``est`` (block units) to the
    sample, with its 95 % interval: ``(sample, low, high)`` in samples of ``x``, or None
    where the record around it is too short.

    Within the block estimate's interval widened by a block each side, every sample ``s`` is
    tried as the step's first one: ``x = mu + d u_s`` by least squares over the searched
    samples and a block beyond them on each side, ``u_s`` the sensor's step response
    starting at ``s`` (:func:`_step_response`). The rise of the residual sum of squares over
    the best's, in units of the residuals' long-run variance per sample (that of their sums
    over :data:`_LONG_RUN_SPAN` step-response lengths), is the likelihood ratio of ``s``
    against the best; the interval holds the samples within :data:`_LR95_CHANGE_POINT` of it. The
    slow wander of the bias over those few blocks (random walk, flicker) stays in the
    residuals, which widens the interval rather than moving the step.
    """
    n = x.size
    lo = max(int(np.floor((est["t_ci"][0] - 1.0) * b)), 1)
    hi = min(int(np.ceil((est["t_ci"][1] + 1.0) * b)), n - 1)
    a, z = max(lo - b, 0), min(hi + b, n)
    y = np.asarray(x[a:z], dtype=np.float64)
    m, L = y.size, response.size
    cand = np.arange(lo - a, hi - a + 1)
    cand = cand[cand + L <= m]
    if cand.size == 0 or m < 4:
        return None
    y = y - float(np.mean(y))  # the level is fitted anyway; this keeps the sums small
    tail = np.concatenate((np.cumsum(y[::-1])[::-1], [0.0]))  # tail[k] = sum(y[k:])
    ramp = np.correlate(y, response, mode="valid")  # sum_j response[j] y[s + j]
    s_uy = ramp[cand] + tail[cand + L]
    after = (m - cand - L).astype(np.float64)
    s_u = float(np.sum(response)) + after
    s_uu = float(np.sum(response * response)) + after
    # y has zero mean: the level's projection leaves S_uy and reduces S_uu by S_u^2 / m
    info = s_uu - s_u * s_u / m
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = np.where(info > 0, s_uy * s_uy / info, 0.0)
    best = int(np.argmax(gain))
    s0 = int(cand[best])
    u = np.concatenate((np.zeros(s0), response, np.ones(m - s0 - L)))
    resid = y - float(s_uy[best] / info[best]) * (u - float(np.mean(u)))
    # The ratio compares sums of the noise over the samples between two candidate times,
    # so its scale is the noise's variance per sample over such spans (its long-run
    # variance), not per single sample: a filter correlates neighbouring samples and would
    # otherwise narrow the interval by its length (four times for a 4-tap average).
    q = _LONG_RUN_SPAN * L
    chunks = resid[: (m // q) * q].reshape(-1, q).sum(axis=1) if m >= 4 * q else resid
    var = float(np.mean(chunks * chunks)) / (q if m >= 4 * q else 1)
    if not np.isfinite(var) or var <= 0.0:
        return None
    lr = (float(gain[best]) - gain) / var
    inside = cand[lr <= _LR95_CHANGE_POINT]
    return int(cand[best] + a), int(inside.min() + a), int(inside.max() + a)


def _warmup_estimate(chol: np.ndarray, ybar: np.ndarray) -> dict[str, float | tuple]:
    """Warm-up time constant (blocks) and amplitude at the segment start, with 95 %
    intervals; a bound that reaches the searched range's end is that end."""
    n = ybar.size
    tc = np.geomspace(0.05, 3.0 * n, _WARMUP_GRID)
    i = np.arange(n)[None, :]
    # block mean of exp(-t / T), t in blocks from the segment start
    shapes = tc[:, None] * (np.exp(-i / tc[:, None]) - np.exp(-(i + 1) / tc[:, None]))
    amp, var, lr, gain = _profile(chol, ybar, shapes)
    best = int(np.argmin(lr))
    inside = tc[lr <= _LR95_REGULAR]
    return {"tau": float(tc[best]), "amplitude": float(amp[best]), "gain": gain,
            "tau_ci": (float(inside.min()), float(inside.max())),
            "amplitude_ci": _amplitude_sets(amp, var, lr)[0]}


def _family(n: int, t_blocks: np.ndarray) -> tuple[np.ndarray, list[tuple[str, float]]]:
    """Zero-sum contrast rows: a step at each split (mean after minus mean before), and the
    least-squares amplitude of exp(-t/T) beside a constant for T from 1 block to a third of
    the record."""
    rows, labels = [], []
    for c in range(2, n - 1):
        w = np.zeros(n)
        w[:c] = -1.0 / c
        w[c:] = 1.0 / (n - c)
        rows.append(w)
        labels.append(("step", float(c)))
    # the same split seen locally, two blocks on each side: rate random walk spreads its
    # wander over the record, a knock puts it in one place (and an Allan fit that absorbed
    # the knock as random walk leaves this contrast its power)
    for c in range(2, n - 1):
        w = np.zeros(n)
        w[c - 2:c] = -0.5
        w[c:c + 2] = 0.5
        rows.append(w)
        labels.append(("step", float(c)))
    for tb in np.geomspace(1.0, n / 3.0, 16):
        e = np.exp(-t_blocks / tb)
        e = e - e.mean()
        rows.append(e / float(e @ e))
        labels.append(("warmup", float(tb)))
    return np.array(rows), labels


@one_blas_thread
def transients(segments: Sequence[np.ndarray], fs_hz: float,
               model: Sequence[tuple[str, dict[str, float]]], alpha: float = 0.05,
               units: str = "rad/s", t0_s: float = 0.0) -> tuple[Finding, Finding]:
    """Test the longest segment for one bias step and for a warm-up transient.

    Args:
        segments: gap-free rate segments (SI units); the longest is tested.
        fs_hz: sampling rate (Hz).
        model: the fitted noise model ``[(term, params)]`` (its Gaussian terms make the null).
        t0_s: time of the longest segment's first sample relative to the record start (s).

    Returns:
        ``(step, warmup)`` findings (kinds ``"bias_step"`` and ``"warmup"``), each with its
        time and size (``params``: ``t_s`` (s from the record start) and ``size`` (units) for
        a step, ``tau_s`` (s) and ``amplitude`` (units, at the segment start) for a warm-up),
        their 95 % intervals in ``details`` (``t_s_ci95``, ``size_ci95``; ``tau_s_ci95``,
        ``amplitude_ci95``; ``unresolved`` names the size or amplitude whose interval holds
        zero: no measurement, and the sentence says so; ``size_ci95_other``, where a step of
        the opposite sign fits as well, a knock's return, its interval, else None) and a
        Monte Carlo p-value, both tests sharing one search (the p-value covers every split
        and time constant). The shape whose profiled fit lowers ``-2 log L`` more
        (``details["gain"]``) names the transient and may take the p-value of the largest
        contrast of both families; the other finding then carries
        ``details["better_explained_by"]`` (the better finding's kind).
    """
    x = max(segments, key=len) if segments else np.zeros(0)
    b = max(len(x) // BLOCKS, MIN_BLOCK_SAMPLES)
    n = len(x) // b
    if n < 12:
        empty = Finding("bias_step", None, 0.0, "max |z|", 1.0, alpha,
                        why="Too short for a step test.")
        return empty, Finding("warmup", None, 0.0, "max |z|", 1.0, alpha,
                              why="Too short for a warm-up test.")
    ybar = x[: n * b].reshape(n, b).mean(axis=1)
    t_blocks = np.arange(n) + 0.5
    w, labels = _family(n, t_blocks)
    v = _variogram(model, fs_hz, b, np.arange(n))
    cov = _contrast_cov(w, v)
    sd = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    z = (w @ ybar) / sd
    # the null distribution of the largest standardised contrast, by drawing the contrasts
    corr = cov / np.outer(sd, sd)
    vals, vecs = np.linalg.eigh(corr)
    root = vecs * np.sqrt(np.clip(vals, 0.0, None))
    draws = np.random.default_rng(_SEED).standard_normal((DRAWS, len(vals))) @ root.T
    try:
        chol = _difference_whitener(v, n)
    except np.linalg.LinAlgError:
        chol = None
    blk = b / fs_hz
    ests = ({"step": _step_estimate(chol, ybar), "warmup": _warmup_estimate(chol, ybar)}
            if chol is not None else {})
    # A warm-up also trips the step contrasts (a step down early on) and a step late in the
    # record the long exponentials: the shape whose fit explains the block means better
    # names the transient, and it may take the p-value of the whole search.
    better = max(ests, key=lambda kd: ests[kd]["gain"]) if ests else None
    p_any = _max_z_p(z, draws, np.ones(len(labels), dtype=bool))
    out = []
    for kind in ("step", "warmup"):
        sel = np.array([lab[0] == kind for lab in labels])
        k = int(np.flatnonzero(sel)[np.argmax(np.abs(z[sel]))])
        zmax = float(abs(z[k]))
        p = _max_z_p(z, draws, sel)
        if kind == better and p_any < p:
            # the evidence is the whole search's largest contrast, named by the better shape
            p, zmax = p_any, float(np.max(np.abs(z)))
        if kind == "step":
            if chol is not None:
                est = ests["step"]
            else:
                c = labels[k][1]
                est = {"t": c, "size": float(w[k] @ ybar), "t_ci": (c - 1.0, c + 1.0),
                       "size_ci": (float("nan"), float("nan"))}
            t_s = t0_s + est["t"] * blk
            size = est["size"]
            t_ci = [t0_s + est["t_ci"][0] * blk, t0_s + est["t_ci"][1] * blk]
            block_t = {"t_s_block": t_s, "t_s_block_ci95": list(t_ci)}
            refined = _sample_step(x, b, est, _step_response(model, fs_hz)) \
                if chol is not None else None
            if refined is not None:
                # the step's first sample, so that a cut there leaves no stepped sample
                t_s = t0_s + refined[0] / fs_hz
                t_ci = [t0_s + refined[1] / fs_hz, t0_s + refined[2] / fs_hz]
            size_ci = list(est["size_ci"])
            params = {"t_s": t_s, "size": size}
            if holds_zero(size_ci):
                # the contrasts found a departure there, but a lasting step of any size
                # near zero explains the block means as well: no size to report
                why = (f"The bias departs from the fitted noise model's random wander at "
                       f"t = {t_s:.6g} s (95 % interval {t_ci[0]:.6g} .. {t_ci[1]:.6g} s, "
                       f"|z| = {zmax:.1f}), but the size of a lasting step there is not "
                       f"resolved (its 95 % interval {size_ci[0]:.3g} .. {size_ci[1]:.3g} "
                       f"{units} holds zero): a knock or a short disturbance rather than a "
                       f"change of state. Analyse the two sides as separate segments.")
            elif est.get("size_ci_other") is not None:
                o_lo, o_hi = est["size_ci_other"]
                b_lo, b_hi = block_t["t_s_block_ci95"]
                why = (f"The bias steps by {size:.3g} {units} at t = {t_s:.6g} s "
                       f"(95 % intervals {t_ci[0]:.6g} .. {t_ci[1]:.6g} s, size "
                       f"{size_ci[0]:.3g} .. {size_ci[1]:.3g}), more than the fitted noise "
                       f"model's random wander allows (|z| = {zmax:.1f}); a step of the "
                       f"opposite sign ({o_lo:.3g} .. {o_hi:.3g}) fits the block means as "
                       f"well between {b_lo:.6g} and {b_hi:.6g} s: the bias leaves and comes "
                       f"back, a knock rather than a change of state. Analyse the two sides "
                       f"as separate segments.")
            else:
                why = (f"The bias steps by {size:.3g} {units} at t = {t_s:.6g} s "
                       f"(95 % intervals {t_ci[0]:.6g} .. {t_ci[1]:.6g} s, size "
                       f"{size_ci[0]:.3g} .. {size_ci[1]:.3g}), more than the fitted noise "
                       f"model's random wander allows (|z| = {zmax:.1f}): a knock or a change "
                       f"of state. Analyse the two sides as separate segments.")
            out.append(Finding("bias_step", None, zmax, "max |z|", p, alpha, params,
                               {"t_s": t_ci}, why if p < alpha else
                               f"No bias step beyond the model's wander (largest |z| = "
                               f"{zmax:.1f}).", {"size_ci95": size_ci, "t_s_ci95": t_ci,
                                                  "unresolved": ["size"] if holds_zero(
                                                      size_ci) else [],
                                                  "size_ci95_other": (
                                                      None if est.get("size_ci_other") is None
                                                      else list(est["size_ci_other"])),
                                                  "block_s": blk, **block_t}))
        else:
            if chol is not None:
                est = ests["warmup"]
            else:
                tb = labels[k][1]
                est = {"tau": tb, "amplitude": float(w[k] @ ybar), "tau_ci": (tb, tb),
                       "amplitude_ci": (float("nan"), float("nan"))}
            tau_s = est["tau"] * blk
            amplitude = est["amplitude"]
            tau_ci = [est["tau_ci"][0] * blk, est["tau_ci"][1] * blk]
            amp_ci = list(est["amplitude_ci"])
            params = {"tau_s": tau_s, "amplitude": amplitude}
            # five time constants, in whole samples (the remedy's --skip counts samples)
            skip = round(min(5.0 * tau_s, 0.5 * n * blk) * fs_hz) / fs_hz
            size_text = (f"an exponential whose amplitude is not resolved (95 % interval "
                         f"{amp_ci[0]:.3g} .. {amp_ci[1]:.3g} {units} holds zero)"
                         if holds_zero(amp_ci) else
                         f"an exponential of {amplitude:.3g} {units} (95 % interval "
                         f"{amp_ci[0]:.3g} .. {amp_ci[1]:.3g})")
            why = (f"The bias settles after the start: {size_text} with a time constant of "
                   f"{tau_s:.3g} s ({tau_ci[0]:.3g} .. {tau_ci[1]:.3g} s), beyond the fitted "
                   f"noise model's wander (|z| = {zmax:.1f}): a warm-up. Skip the first "
                   f"{skip:.0f} s.")
            out.append(Finding("warmup", None, zmax, "max |z|", p, alpha, params,
                               {"t_s": [t0_s, t0_s + skip]}, why if p < alpha else
                               f"No warm-up transient beyond the model's wander (largest |z| "
                               f"= {zmax:.1f}).", {"skip_s": skip, "block_s": blk,
                                                   "tau_s_ci95": tau_ci,
                                                   "amplitude_ci95": amp_ci,
                                                   "unresolved": ["amplitude"] if holds_zero(
                                                       amp_ci) else []}))
    step_f, warm_f = out
    if better is not None:
        step_f.details["gain"] = ests["step"]["gain"]
        warm_f.details["gain"] = ests["warmup"]["gain"]
        winner, loser = (step_f, warm_f) if better == "step" else (warm_f, step_f)
        loser.details["better_explained_by"] = winner.kind
        if loser.significant:
            shape = "a bias step" if winner.kind == "bias_step" else "a warm-up"
            loser.why += (f" But {shape} explains the block means better (-2 log L lower by "
                          f"{winner.details['gain'] - loser.details['gain']:.1f}).")
    return step_f, warm_f


def holds_zero(ci: Sequence[float] | None) -> bool:
    """Whether a signed size's 95 % interval reaches or crosses zero (no measurement then);
    False for no interval or one with an undefined end."""
    if ci is None:
        return False
    lo, hi = float(ci[0]), float(ci[1])
    return bool(np.isfinite(lo) and np.isfinite(hi) and lo <= 0.0 <= hi)


def _max_z_p(z: np.ndarray, draws: np.ndarray, sel: np.ndarray) -> float:
    """p-value of the largest ``|z|`` among the contrasts ``sel`` under the model: the share of
    null draws reaching it, with a Bonferroni normal tail where the draws run out."""
    zmax = float(np.max(np.abs(z[sel])))
    p_mc = (1.0 + float(np.sum(np.max(np.abs(draws[:, sel]), axis=1) >= zmax))) / (DRAWS + 1)
    p_tail = min(1.0, float(sel.sum()) * 2.0 * float(dist.norm.sf(zmax)))
    return min(p_mc, p_tail) if p_mc <= 2.0 / (DRAWS + 1) else p_mc
