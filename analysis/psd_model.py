"""The model's PSD as the log-frequency estimator sees it: the expected value of
:func:`imunoise.analysis.psd.log_psd` under a noise model, point by point.

A model's PSD evaluated at a point's frequency is not what the estimator returns on average.
Three effects separate them, and each is computed here exactly or to a known bound:

- Sampling. The terms' spectra are those of the sampled sequence (aliasing included): white,
  quantization, random walk, Markov and resonance terms are defined in discrete time and their
  ``psd`` is periodic in ``fs``; output filters multiply the noise terms' PSD by ``|G(f)|^2``.
  Bias instability is taken as sampled: the exact spectrum of its Markov-sum realisation
  (:func:`imunoise.analysis.terms.bias_instability.flicker_psd`), ``B^2/(pi f)`` over the band
  and aliased near Nyquist.
- The cascade. Level ``j`` of the estimator is the record through ``j`` anti-alias FIR filters,
  each followed by a decimation by 2; by the noble identity this is one filter at the full rate
  followed by decimation by ``2^j``. Its PSD is the input's times the cascade's power gain,
  folded at ``fs_j = fs/2^j`` (the folds at ``+-fs_j`` are included: they carry the filters'
  transition band; further folds lie 100 dB down twice). The estimator divides the gain at
  the bin frequency back out; so does this expectation.
- The window. A Welch bin's expected periodogram is the level's PSD convolved with the Hann
  window's spectral kernel ``|W(u)|^2`` (normalised to unit area). The segment mean removal
  changes nothing at the bins used (``k >= 2``, where the periodic Hann window's transform
  vanishes). The convolution is done on a grid of ``PAD`` points per bin over the whole period
  (so far leakage, e.g. of a steep random-walk spectrum into the lowest bins, is included),
  by FFT. Spectral lines (sinusoids), resonances narrower than four grid steps and the rate
  ramp are added in closed form: a line of amplitude ``A`` at ``f0`` contributes
  ``A^2/4 (K(u_k - u0) + K(u_k + u0))`` (random phase), a ramp the periodogram of its windowed
  segment (deterministic; the offset is removed by the window at bins >= 2).

Merged log-frequency points average their bins, so their expectation is the mean of the bins'
expectations. The bin layout is that of :class:`imunoise.analysis.psd.StreamingPsd` and is
recovered from the estimate itself (its ``method`` and ``f_hz``), so the expectation always
belongs to the estimate it is compared with.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np

from imunoise.analysis.dsp import hann
from imunoise.analysis.psd import PsdEstimate, _cascade_gain
from imunoise.analysis.terms import get_term, model_psd
from imunoise.analysis.terms.bias_instability import flicker_psd

PAD = 32
"""Grid points per bin of the window convolution."""

Model = Sequence[tuple[str, dict[str, float]]]


def _level_of(method: str) -> int:
    if method == "welch":
        return 0
    return int(round(math.log2(int(method.removeprefix("decimate")))))


def _hann_kernel(u: np.ndarray, L: int) -> np.ndarray:
    """``|W(u)|^2 / sum(w^2)`` of the periodic L-point Hann window at ``u`` cycles/sample;
    its integral over one period is 1.

    The window is ``1/2 - cos(2 pi n/L)/2``, so its transform is three Dirichlet kernels,
    ``W(u) = D(u)/2 - D(u - 1/L)/4 - D(u + 1/L)/4`` with ``D(v) = sum_n exp(-2 pi i v n)``
    in closed form: O(1) per point where the direct sum costs O(L) (at L = 4096, 0.6 s of
    a 12.7 s diagnosis of a channel with a line). Points within 1e-6 of a whole number of
    cycles, where the closed form divides by nearly zero, are summed directly."""
    u = np.atleast_1d(np.asarray(u, dtype=np.float64))
    w = hann(L)
    if L < 2:
        return np.abs(np.exp(-2j * np.pi * np.outer(u, np.arange(L))) @ w) ** 2 \
            / float(np.sum(w**2))

    def dirichlet(v: np.ndarray) -> np.ndarray:
        den = 1.0 - np.exp(-2j * np.pi * v)
        near = np.abs(np.sin(np.pi * v)) < 1e-6
        out = (1.0 - np.exp(-2j * np.pi * v * L)) / np.where(near, 1.0, den)
        if np.any(near):
            out[near] = np.exp(-2j * np.pi * np.outer(v[near], np.arange(L))).sum(axis=1)
        return out

    transform = 0.5 * dirichlet(u) - 0.25 * (dirichlet(u - 1.0 / L) + dirichlet(u + 1.0 / L))
    return np.abs(transform) ** 2 / float(np.sum(w**2))


def _noise_and_rest(model: Model) -> tuple[list, list, list]:
    """Split a model into its Gaussian part (with any filter), its lines ``(A, f0)`` and its
    ramp slopes; a regressor (removed before any estimate) has no part."""
    gaussian, lines, ramps = [], [], []
    for name, p in model:
        t = get_term(name)
        if t.role == "line":
            lines.append(t.line(p))
        elif t.role == "ramp":
            ramps.append(t.ramp_slope(p))
        elif t.role == "regressor":
            continue
        else:
            gaussian.append((name, dict(p)))
    return gaussian, lines, ramps


def _periodic(f: np.ndarray, fs: float) -> np.ndarray:
    """Frequencies folded into ``[0, fs/2]`` (the sampled spectrum is even and periodic)."""
    g = np.mod(np.abs(f), fs)
    return np.minimum(g, fs - g)


_PEAK_TERMS = ("resonance", "wandering_resonance", "antiresonance")
"""Terms with a spectral peak at ``f0`` of width ``f0/Q``."""


def _split_narrow(gaussian: list, df_grid: float) -> tuple[list, list]:
    """Resonances narrower than four grid steps (a wandering one with its wander) apart from
    the other Gaussian terms (the filter, if any, stays with both)."""
    filt = [(n, p) for n, p in gaussian if get_term(n).kind == "filter"]
    narrow = [(n, p) for n, p in gaussian
              if n in _PEAK_TERMS
              and p["f0"] / p["Q"] + 2.0 * p.get("spread", 0.0) < 4.0 * df_grid]
    rest = [(n, p) for n, p in gaussian if not any(p is q for _, q in narrow)]
    return rest, [[(n, p)] + filt for n, p in narrow]


def _core(res: list, fs: float, core_hz: float) -> tuple[float, float]:
    """``(f0, power)`` of a narrow resonance (with its filter) within ``core_hz`` of f0,
    integrated on a grid that resolves its width (units^2)."""
    p = res[0][1]
    f0 = float(p["f0"])
    f = np.linspace(max(f0 - core_hz, 0.0), f0 + core_hz, 4001)
    return f0, float(np.trapezoid(model_psd(res, f, fs), f))


def _gaussian_psd(gaussian: list, f: np.ndarray, fs: float) -> np.ndarray:
    if not any(get_term(n).kind != "filter" for n, _ in gaussian):
        return np.zeros_like(f)
    fp = _periodic(f, fs)
    # bias instability as sampled: the exact spectrum of its Markov-sum realisation (the
    # simulator's), 1/f over the band and aliased near Nyquist
    plain = [(n, p) for n, p in gaussian if n != "bias_instability"]
    b2 = sum(float(p["B"]) ** 2 for n, p in gaussian if n == "bias_instability")
    with np.errstate(divide="ignore", invalid="ignore"):
        s = model_psd(plain, fp, fs) if any(get_term(n).kind != "filter" for n, _ in plain) \
            else np.zeros_like(f)
        if b2 > 0:
            flick = flicker_psd(fp, fs, math.sqrt(b2))
            for n, p in plain:
                if get_term(n).kind == "filter":
                    flick = flick * get_term(n).response(fp, fs, p)
            s = s + flick
    return np.where(np.isfinite(s), s, 0.0)


def _level_bins(est: PsdEstimate, fs: float, L: int, ppd: float | None
                ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per level, the bin indices the estimator used and the index of each bin's point."""
    method = np.asarray(est.method).astype(str)
    levels = sorted({_level_of(m) for m in method})
    deepest = max(levels)
    k0 = L // 16
    out = {}
    for j in levels:
        sel = np.flatnonzero(method == ("welch" if j == 0 else f"decimate{2 ** j}"))
        fs_j = fs / 2**j
        k_hi = L // 2 if j == 0 else 2 * k0
        starts = range(2, k_hi) if j == deepest else [k0]
        target = est.f_hz[sel]
        found = None
        for k_lo in starts:
            k = np.arange(k_lo, k_hi)
            f = k * fs_j / L
            if ppd is None:
                fg, groups = f, np.arange(len(k))
            else:
                idx = np.floor(np.log10(f) * ppd + 1e-9).astype(np.int64)
                _, groups = np.unique(idx, return_inverse=True)
                fg = np.bincount(groups, f) / np.bincount(groups)
            if len(fg) == len(target) and np.allclose(fg, target, rtol=1e-9, atol=0.0):
                found = (k, sel[groups])
                break
        if found is None:
            raise ValueError("the PSD estimate's points do not match the log-frequency "
                             "estimator's bin layout (nperseg or points per decade differ)")
        out[j] = found
    return out


_GRID_GAINS: OrderedDict[tuple[float, int, int, int], np.ndarray] = OrderedDict()
_GRID_GAINS_KEPT = 128
_GRID_GAINS_LOCK = threading.Lock()


def _grid_gain(fs: float, n_grid: int, j: int, alias: int) -> np.ndarray:
    """The cascade's power gain at level ``j`` on the convolution grid of ``n_grid`` points
    shifted by ``alias`` periods (read-only). The same for every model compared with one
    estimate, and most of the time of an expectation: computed once per process (the last
    :data:`_GRID_GAINS_KEPT` kept), or handed over by :func:`adopt_grid_gains`."""
    key = (float(fs), int(n_grid), int(j), int(alias))
    gain = _GRID_GAINS.get(key)
    if gain is None:
        u = np.arange(n_grid) / n_grid
        u = np.where(u > 0.5, u - 1.0, u)
        gain = _cascade_gain(np.abs((u + alias) * (fs / 2**j)), fs, j)
        gain.setflags(write=False)
        _remember_gain(key, gain)
    return gain


def _remember_gain(key: tuple[float, int, int, int], gain: np.ndarray) -> None:
    with _GRID_GAINS_LOCK:  # the live service computes expectations in threads
        _GRID_GAINS[key] = gain
        while len(_GRID_GAINS) > _GRID_GAINS_KEPT:
            _GRID_GAINS.popitem(last=False)


def grid_gains() -> dict[tuple[float, int, int, int], np.ndarray]:
    """The cascade gains this process has computed, for :func:`adopt_grid_gains` in another.

    A job map's worker that computes the first expectation of a diagnosis (0.1-0.2 s of
    gains for a 1e6-sample record) hands them to the parent, so that every worker forked
    from the parent later starts with them instead of computing them again."""
    with _GRID_GAINS_LOCK:
        return dict(_GRID_GAINS)


def adopt_grid_gains(found: dict[tuple[float, int, int, int], np.ndarray]) -> None:
    """Keep the gains another process computed (:func:`grid_gains`): the same arrays
    :func:`_grid_gain` would compute here."""
    for key, gain in found.items():
        if key not in _GRID_GAINS:
            gain = np.asarray(gain)
            gain.setflags(write=False)
            _remember_gain(key, gain)


def expected_log_psd(model: Model, est: PsdEstimate, fs_hz: float,
                     nperseg: int | None = 256, points_per_decade: float | None = 40.0,
                     levels: Sequence[int] | None = None) -> np.ndarray:
    """Expected value (units^2/Hz, one-sided) of each point of ``est`` (a
    :func:`imunoise.analysis.psd.log_psd` estimate made with ``nperseg`` and
    ``points_per_decade``) when the record follows ``model`` ``[(term, params)]``.
    ``levels`` restricts the work to those cascade levels (0: the full-rate Welch band); the
    other points are NaN. ``nperseg=None`` finds the segment length (a power of two from 64
    to 4096) whose bin layout the estimate has."""
    if nperseg is None:
        for n in (256, 128, 64, 512, 1024, 2048, 4096):
            try:
                return expected_log_psd(model, est, fs_hz, n, points_per_decade, levels)
            except ValueError:
                continue
        raise ValueError("the PSD estimate's points match no segment length's bin layout")
    fs = float(fs_hz)
    L = int(nperseg)
    N = L * PAD
    gaussian, lines, ramps = _noise_and_rest(model)
    out = np.zeros(len(est.f_hz))
    counts = np.zeros(len(est.f_hz))
    w = hann(L)
    kern = np.abs(np.fft.fft(w, N)) ** 2
    kern /= kern.sum()
    kern_f = np.fft.fft(kern)
    for j, (k, point) in _level_bins(est, fs, L, points_per_decade).items():
        if levels is not None and j not in levels:
            np.add.at(out, point, np.nan)
            continue
        fs_j = fs / 2**j
        step = fs_j / N
        g_noise, narrow = _split_narrow(gaussian, step)
        core = 2.0 * step
        lines_j = list(lines)
        u = np.arange(N) / N
        u = np.where(u > 0.5, u - 1.0, u)  # one period, two-sided, cycles/sample at level j
        s = np.zeros(N)
        for a in ((0,) if j == 0 else (-1, 0, 1)):
            f = (u + a) * fs_j
            gain = np.ones(N) if j == 0 else _grid_gain(fs, N, j, a)
            s += 0.5 * _gaussian_psd(g_noise, f, fs) * gain
            for res in narrow:
                # the resonance's tails on the grid; its core (within two steps) as a line
                fp = _periodic(f, fs)
                outside = np.abs(fp - res[0][1]["f0"]) >= core
                s += 0.5 * np.where(outside, model_psd(res, fp, fs), 0.0) * gain
        # E[P(u_k)] = sum_m S(u_k - m/N) K(m/N): circular convolution on the grid
        conv = np.real(np.fft.ifft(np.fft.fft(s) * kern_f))
        e = 2.0 * conv[(k * PAD) % N]
        uk = k / L
        for res in narrow:
            f0, power = _core(res, fs, core)
            lines_j.append((math.sqrt(2.0 * power), f0))
        for amp, f0 in lines_j:
            g0 = 1.0 if j == 0 else float(_cascade_gain(np.array([f0]), fs, j)[0])
            if g0 < 1e-14:
                continue
            u0 = f0 / fs_j
            both = _hann_kernel(uk - u0, L) + _hann_kernel(uk + u0, L)
            e += 0.5 * amp * amp * g0 * both / fs_j
        for slope in ramps:
            # the ramp within a segment at level j: slope/fs_j per sample (offsets vanish)
            n = np.arange(L)
            ph = np.exp(-2j * np.pi * np.outer(uk, n))
            amp = ph @ (w * n * slope / fs_j)
            e += 2.0 * np.abs(amp) ** 2 / (fs_j * float(np.sum(w**2)))
        gain_k = np.ones(len(k)) if j == 0 else _cascade_gain(k * fs_j / L, fs, j)
        e = e / gain_k
        np.add.at(out, point, e)
        np.add.at(counts, point, 1.0)
    return out / np.maximum(counts, 1.0)


def whittle_part(psd: np.ndarray, dof: np.ndarray, model: np.ndarray, ci: float = 0.95
                 ) -> dict[str, float | int] | None:
    """The PSD part of a model's error: Whittle deviance per bin ``mean(nu (r - 1 - ln r))``
    with ``r = psd/model`` (about 1 when the model is right: each term is a scaled chi-square
    with ``nu`` degrees of freedom), the number of bins and the share outside their ``ci``
    chi-square interval. None with fewer than 5 usable bins."""
    from imunoise.analysis.distributions import chi2

    p, nu, s = (np.asarray(x, dtype=np.float64) for x in (psd, dof, model))
    ok = np.isfinite(p) & np.isfinite(nu) & np.isfinite(s) & (p > 0) & (nu > 0) & (s > 0)
    if ok.sum() < 5:
        return None
    r, nu = p[ok] / s[ok], nu[ok]
    a = (1.0 - ci) / 2.0
    outside = (r < chi2.ppf(a, nu) / nu) | (r > chi2.ppf(1.0 - a, nu) / nu)
    return {"deviance_per_bin": float(np.mean(nu * (r - 1.0 - np.log(r)))),
            "bins": int(ok.sum()), "outside_95": float(np.mean(outside))}


MISS_FAMILY_RATE = 0.05
"""Probability that a right model's PSD flags any bin as missed (Sidak over the bins)."""

MISS_EXTEND_Z = 2.0
"""A miss extends over the neighbouring bins on its side of the model beyond this score."""


def psd_misses(f_hz: np.ndarray, psd: np.ndarray, dof: np.ndarray, model: np.ndarray,
               z: np.ndarray | None = None) -> list[dict[str, Any]]:
    """Where the measured PSD leaves the model's band: each run of consecutive bins on one
    side of the model, every one beyond :data:`MISS_EXTEND_Z` in normal score
    (:func:`psd_z`), and at least one beyond the level at which a right model flags any bin
    with probability :data:`MISS_FAMILY_RATE` (a run is not cut where one bin inside a broad
    miss happens to fall a little short of that level). Each run gives ``f_hz`` (its first
    and last bin, Hz), ``max_abs_z``, ``direction`` and ``deviance_share``, the share of the
    whole Whittle deviance its bins carry: which misses make the PSD part large. Frequency
    order. ``z``: the points' :func:`psd_z` where the caller has it already."""
    from imunoise.analysis.misfit import failure_threshold

    f, p, nu, s = (np.asarray(x, dtype=np.float64) for x in (f_hz, psd, dof, model))
    ok = np.isfinite(p) & np.isfinite(nu) & np.isfinite(s) & (p > 0) & (nu > 0) & (s > 0)
    if ok.sum() < 5:
        return []
    z = psd_z(p[ok], nu[ok], s[ok]) if z is None else np.asarray(z, dtype=np.float64)[ok]
    f, p, nu, s = f[ok], p[ok], nu[ok], s[ok]
    r = p / s
    dev = nu * (r - 1.0 - np.log(r))
    total = float(np.sum(dev))
    level = failure_threshold(int(z.size), MISS_FAMILY_RATE)
    wide = np.abs(z) > MISS_EXTEND_Z
    out: list[dict[str, Any]] = []
    i = 0
    while i < z.size:
        if not wide[i]:
            i += 1
            continue
        j = i
        while j + 1 < z.size and wide[j + 1] and np.sign(z[j + 1]) == np.sign(z[i]):
            j += 1
        if not np.max(np.abs(z[i:j + 1])) > level:
            i = j + 1
            continue
        out.append({"f_hz": [float(f[i]), float(f[j])],
                    "max_abs_z": float(np.max(np.abs(z[i:j + 1]))),
                    "direction": "measured above model" if z[i] > 0 else
                    "measured below model",
                    "deviance_share": float(np.sum(dev[i:j + 1]) / total) if total > 0
                    else 0.0})
        i = j + 1
    return out


def psd_z(psd: np.ndarray, dof: np.ndarray, model: np.ndarray) -> np.ndarray:
    """Per point, the normal score of the measured PSD under the model (its chi-square law
    with ``dof`` degrees of freedom): positive when the measurement lies above the model."""
    from imunoise.analysis.distributions import chi2, norm

    p, nu, s = (np.asarray(x, dtype=np.float64) for x in (psd, dof, model))
    with np.errstate(divide="ignore", invalid="ignore"):
        x = nu * p / s
        lo = chi2.logcdf(x, nu)
        hi = chi2.logsf(x, nu)
        z = np.where(lo < hi, norm.ppf(np.exp(lo)), -norm.ppf(np.exp(hi)))
        # far tails, where the probabilities underflow: Wilson-Hilferty
        c = 2.0 / (9.0 * nu)
        tail = (np.cbrt(x / nu) - (1.0 - c)) / np.sqrt(c)
        z = np.where(np.isfinite(z), z, tail)
    return np.clip(np.where(np.isfinite(z), z, 0.0), -1e4, 1e4)


