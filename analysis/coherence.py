"""Cross-spectral density and magnitude-squared coherence between the channels of one record.

Estimator: Welch averaging of Hann-windowed segments with 50 % overlap, each segment's mean
removed, exactly as :func:`imunoise.analysis.psd.welch_psd` does for one channel. For channels
``i`` and ``j`` the one-sided cross-spectral density is ``S_ij = 2 <X_i conj(X_j)> / (fs sum w^2)``
(units_i * units_j / Hz); the magnitude-squared coherence (MSC) is
``C_ij = |S_ij|^2 / (S_ii S_jj)``: the share of channel i's power at ``f`` that a linear filter
of channel j explains. Bins 0 and 1 and the Nyquist bin are left out, and log-frequency points
merge neighbouring bins with the rule of :mod:`imunoise.analysis.psd`
(``floor(log10(f) * points_per_decade)``); a merged point sums the cross-spectra of its bins
before the ratio is taken. There is one Welch level (no decimation cascade): the lowest
frequency is ``2 fs / nperseg``; choose ``nperseg`` for the lowest frequency wanted.

Number of averages: the distribution of the MSC estimate depends on the number ``n`` of
independent averages. Overlapping segments and merged neighbouring bins are not independent;
``n`` is taken as half the equivalent degrees of freedom of the PSD of the same point
(:mod:`imunoise.analysis.psd`: ``nu = 2 K^2 / (K + 2 sum_m (K - m) rho_m^2)`` for ``K``
segments, reduced for adjacent Hann bins), the approximation Carter, Knapp and Nuttall (1973)
found to hold for overlapped Hann processing; a test checks the false-alarm rate it gives.

Distribution (Goodman 1963; Carter, Knapp and Nuttall, "Estimation of the magnitude-squared
coherence function via overlapped fast Fourier transform processing", IEEE Trans. Audio
Electroacoust. AU-21 (1973) 337-344): for Gaussian data with true coherence ``g`` the estimate
from ``n`` averages has the density
``p(C) = (n-1) (1-g)^n (1-C)^(n-2) 2F1(n, n; 1; g C)``. Expanding the hypergeometric series
term by term shows it is a mixture: ``C ~ Beta(1 + k, n - 1)`` with ``k`` negative-binomial,
``P(k) = Gamma(n+k) / (Gamma(n) k!) (1-g)^n g^k``, which this module sums (vectorised, for
non-integer ``n`` too). Under the null ``g = 0`` it reduces to ``P(C > x) = (1 - x)^(n-1)``,
so the threshold of a test at level ``a`` is ``1 - a^(1/(n-1))``. The estimate is biased up
(about ``(1-g)^2 / n`` for large ``n``); the interval is the exact one found by inverting the
distribution in ``g`` (equal tails), so it carries the bias with it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any

import numpy as np
from scipy import special

from imunoise.analysis.psd import _bin_corr2, _merge_factor, _overlap_rho2, _window

DEFAULT_ALPHA = 0.05
"""Significance level of the zero-coherence test."""

_SEGMENTS_PER_CHUNK = 64  # segments transformed at once: bounds temporary memory
_MIXTURE_NODES = 96  # negative-binomial terms summed per evaluation (strided when wide)
_MIXTURE_SPAN = 8.0  # standard deviations of k covered either side of its mean
_ROOT_STEPS = 6


# ---------------------------------------------------------------- distribution of the estimate


def msc_null_sf(x: np.ndarray | float, n: np.ndarray | float) -> np.ndarray:
    """``P(C > x)`` for zero true coherence and ``n`` independent averages: ``(1-x)^(n-1)``."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.exp((np.asarray(n, dtype=np.float64) - 1.0) * np.log1p(-np.minimum(x, 1 - 1e-300)))


def msc_threshold(n: np.ndarray | float, alpha: float = DEFAULT_ALPHA,
                  n_tests: int = 1) -> np.ndarray:
    """MSC above which zero coherence is rejected at level ``alpha`` (Sidak-corrected for
    ``n_tests`` independent points): ``1 - a1^(1/(n-1))``, ``a1 = 1 - (1-alpha)^(1/n_tests)``."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    a1 = -math.expm1(math.log1p(-alpha) / max(int(n_tests), 1))
    n = np.asarray(n, dtype=np.float64)
    return -np.expm1(math.log(a1) / np.maximum(n - 1.0, 1e-12))


def msc_cdf(c: np.ndarray | float, g: np.ndarray | float, n: np.ndarray | float) -> np.ndarray:
    """``P(C_hat <= c)`` for true coherence ``g`` and ``n`` averages (arrays broadcast).

    The negative-binomial mixture of the module notes; ``k`` is summed over its mean +- 8
    standard deviations, strided when that span exceeds the number of nodes (the terms then
    vary slowly, over many strides) and renormalised.
    """
    c, g, n = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (c, g, n)))
    shape = c.shape
    c, g, n = c.ravel(), np.clip(g.ravel(), 0.0, 1.0 - 1e-12), n.ravel()
    mean = n * g / (1.0 - g)
    sd = np.sqrt(n * g) / (1.0 - g)
    lo = np.floor(np.maximum(mean - _MIXTURE_SPAN * sd, 0.0))
    hi = np.ceil(mean + _MIXTURE_SPAN * sd) + 2.0
    stride = np.maximum(np.ceil((hi - lo) / _MIXTURE_NODES), 1.0)
    k = lo[:, None] + stride[:, None] * np.arange(_MIXTURE_NODES)[None, :]
    logw = (special.gammaln(n[:, None] + k) - special.gammaln(n[:, None])
            - special.gammaln(k + 1.0) + n[:, None] * np.log1p(-g[:, None])
            + k * np.log(np.maximum(g[:, None], 1e-300)))
    logw = np.where(k <= hi[:, None], logw, -np.inf)
    w = np.exp(logw - np.max(logw, axis=1, keepdims=True))
    w /= np.sum(w, axis=1, keepdims=True)
    cdf = np.sum(w * special.betainc(k + 1.0, np.maximum(n[:, None] - 1.0, 1e-9),
                                     c[:, None]), axis=1)
    return cdf.reshape(shape)


def msc_expected(g: np.ndarray | float, n: np.ndarray | float) -> np.ndarray:
    """Expected value of the estimate, ``E[(1+k)/(n+k)]`` over the mixture (its bias is this
    minus ``g``; ``1/n`` at ``g = 0``)."""
    g, n = np.broadcast_arrays(np.asarray(g, dtype=np.float64), np.asarray(n, dtype=np.float64))
    shape = g.shape
    g, n = np.clip(g.ravel(), 0.0, 1.0 - 1e-12), n.ravel()
    mean = n * g / (1.0 - g)
    sd = np.sqrt(n * g) / (1.0 - g)
    lo = np.floor(np.maximum(mean - _MIXTURE_SPAN * sd, 0.0))
    hi = np.ceil(mean + _MIXTURE_SPAN * sd) + 2.0
    stride = np.maximum(np.ceil((hi - lo) / _MIXTURE_NODES), 1.0)
    k = lo[:, None] + stride[:, None] * np.arange(_MIXTURE_NODES)[None, :]
    logw = (special.gammaln(n[:, None] + k) - special.gammaln(k + 1.0)
            + k * np.log(np.maximum(g[:, None], 1e-300)))
    logw = np.where(k <= hi[:, None], logw, -np.inf)
    w = np.exp(logw - np.max(logw, axis=1, keepdims=True))
    w /= np.sum(w, axis=1, keepdims=True)
    return np.sum(w * (1.0 + k) / (n[:, None] + k), axis=1).reshape(shape)


def msc_interval(c: np.ndarray | float, n: np.ndarray | float,
                 ci: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Equal-tailed confidence interval of the true coherence from the estimate ``c``.

    The lower bound is the ``g`` at which ``c`` is the upper ``(1-ci)/2`` quantile (0 when even
    ``g = 0`` makes ``c`` that likely), the upper bound the ``g`` at which it is the lower one.
    """
    if not 0.0 < ci < 1.0:
        raise ValueError(f"confidence level must be in (0, 1), got {ci}")
    c, n = np.broadcast_arrays(np.asarray(c, dtype=np.float64), np.asarray(n, dtype=np.float64))
    shape = c.shape
    c, n = np.clip(c.ravel(), 0.0, 1.0), n.ravel()
    a = (1.0 - ci) / 2.0
    # both bounds in one root search: cdf(c; g) = 1-a (lower bound) and = a (upper bound),
    # in z = atanh(sqrt(g)), where the cdf is close to a normal one (Fisher's transform)
    cc, nn = np.concatenate((c, c)), np.concatenate((n, n))
    target = np.concatenate((np.full(c.size, 1.0 - a), np.full(c.size, a)))
    z_max = math.atanh(math.sqrt(1.0 - 1e-9))

    probit_target = special.ndtri(target)

    def excess(z: np.ndarray) -> np.ndarray:
        # on the probit scale the cdf is nearly linear in z: false position converges fast
        p = np.clip(msc_cdf(cc, np.tanh(z) ** 2, nn), 1e-300, 1.0 - 1e-16)
        return special.ndtri(p) - probit_target  # falls as z rises

    at_zero = excess(np.zeros(cc.size))
    # bracket from Fisher's approximation, widened to the whole range where it fails
    se = 1.0 / np.sqrt(2.0 * np.maximum(nn - 1.0, 1.0))
    z0 = np.arctanh(np.sqrt(np.minimum(cc, 1.0 - 1e-12)))
    lo = np.clip(z0 - 7.0 * se, 0.0, z_max)
    hi = np.clip(z0 + 7.0 * se, 0.0, z_max)
    f_lo, f_hi = excess(lo), excess(hi)
    bad = (f_lo < 0) | (f_hi > 0)
    lo, hi = np.where(bad, 0.0, lo), np.where(bad, z_max, hi)
    f_lo, f_hi = np.where(bad, at_zero, f_lo), np.where(bad, excess(np.full(cc.size, z_max)),
                                                        f_hi)
    # Illinois false position: superlinear, keeps the bracket
    side = np.zeros(cc.size, dtype=np.int8)
    for _ in range(_ROOT_STEPS):
        z = np.where(f_lo - f_hi > 0, (lo * -f_hi + hi * f_lo) / np.where(
            f_lo - f_hi > 0, f_lo - f_hi, 1.0), 0.5 * (lo + hi))
        fz = excess(z)
        up = fz > 0
        lo, f_lo = np.where(up, z, lo), np.where(up, fz, f_lo)
        hi, f_hi = np.where(up, hi, z), np.where(up, f_hi, fz)
        f_hi = np.where(up & (side == 1), 0.5 * f_hi, f_hi)
        f_lo = np.where(~up & (side == -1), 0.5 * f_lo, f_lo)
        side = np.where(up, 1, -1).astype(np.int8)
    zr = np.where(f_lo - f_hi > 0, (lo * -f_hi + hi * f_lo) / np.where(
        f_lo - f_hi > 0, f_lo - f_hi, 1.0), 0.5 * (lo + hi))
    g = np.where(at_zero <= 0, 0.0, np.tanh(zr) ** 2)
    return g[:c.size].reshape(shape), g[c.size:].reshape(shape)


# ------------------------------------------------------------------- cross-spectral matrix


@dataclass(frozen=True)
class CrossSpectra:
    """Welch cross-spectral matrix of several channels on the linear bin grid.

    Attributes:
        channels: channel names, in matrix order.
        fs_hz: sampling rate in Hz.
        nperseg: segment length in samples.
        f_hz: bin frequencies in Hz (bins 2 .. nperseg/2 - 1).
        s: one-sided cross-spectral density, shape ``(len(f_hz), C, C)``, complex, entry
            ``[f, i, j]`` in units_i * units_j / Hz (``S_ij = 2 <X_i conj X_j> / (fs sum w^2)``;
            the diagonal is each channel's PSD).
        n_avg: equivalent number of independent averages of one bin (PSD dof / 2).
        n_segments: Welch segments averaged.
    """

    channels: tuple[str, ...]
    fs_hz: float
    nperseg: int
    f_hz: np.ndarray
    s: np.ndarray
    n_avg: float
    n_segments: int

    @property
    def df_hz(self) -> float:
        return self.fs_hz / self.nperseg

    def index(self, name: str) -> int:
        return self.channels.index(name)

    def psd(self, name: str) -> np.ndarray:
        i = self.index(name)
        return self.s[:, i, i].real

    def msc(self, a: str, b: str) -> np.ndarray:
        """MSC of channels ``a`` and ``b`` on every bin."""
        i, j = self.index(a), self.index(b)
        return _msc(self.s[:, i, j], self.s[:, i, i].real, self.s[:, j, j].real)

    def band(self, f_lo_hz: float, f_hi_hz: float) -> tuple[np.ndarray, float]:
        """The cross-spectral matrix summed over the bins in ``[f_lo, f_hi]`` (at least the
        nearest bin) and the number of averages it stands for (neighbours' correlation
        allowed for): ``(matrix (C, C), n)``."""
        sel = np.flatnonzero((self.f_hz >= f_lo_hz) & (self.f_hz <= f_hi_hz))
        if sel.size == 0:
            sel = np.array([int(np.argmin(np.abs(self.f_hz - 0.5 * (f_lo_hz + f_hi_hz))))])
        m = float(sel.size)
        inflation = _merge_factor(np.array([m]), _bin_corr2(_window(self.nperseg)))[0]
        n = self.n_avg * m / float(inflation)
        return self.s[sel].sum(axis=0), n


def _msc(sij: np.ndarray, sii: np.ndarray, sjj: np.ndarray) -> np.ndarray:
    den = sii * sjj
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, (sij.real**2 + sij.imag**2) / np.where(den > 0, den, 1.0), 0.0)


class CrossSpectralAccumulator:
    """Welch cross-spectral matrix fed block by block (live use) with bounded memory.

    Each block is ``(samples, channels)`` on one time base; call :meth:`new_segment` at a gap
    so no segment bridges it. Memory: one partial segment plus the running ``(L/2+1, C, C)``
    sum.
    """

    def __init__(self, channels: list[str] | tuple[str, ...], fs_hz: float,
                 nperseg: int) -> None:
        if fs_hz <= 0 or not math.isfinite(fs_hz):
            raise ValueError(f"sampling rate must be positive, got {fs_hz}")
        if nperseg < 16 or nperseg % 2:
            raise ValueError(f"nperseg must be even and at least 16, got {nperseg}")
        if len(channels) < 2:
            raise ValueError("coherence needs at least two channels")
        self.channels = tuple(channels)
        self.fs_hz = float(fs_hz)
        self.nperseg = int(nperseg)
        self.step = self.nperseg // 2
        self.window = _window(self.nperseg)
        self.rho2_cum = np.concatenate(([0.0], np.cumsum(_overlap_rho2(self.window, self.step))))
        c = len(self.channels)
        self.sum = np.zeros((self.nperseg // 2 + 1, c, c), dtype=np.complex128)
        self.n_segments = 0
        self.dof_denominator = 0.0
        self.new_segment()

    def new_segment(self) -> None:
        """Declare a gap: the next block does not continue the previous one."""
        self.pending = np.empty((0, len(self.channels)))
        self.run_segments = 0

    def add(self, block: np.ndarray) -> None:
        """Append samples, shape ``(n, channels)``, channel units."""
        x = np.asarray(block, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != len(self.channels):
            raise ValueError(f"block must have shape (n, {len(self.channels)}), got {x.shape}")
        if not np.all(np.isfinite(x)):
            raise ValueError("coherence input contains NaN or infinite values; split the "
                             "record around them")
        buf = np.concatenate((self.pending, x)) if self.pending.size else x
        L, step = self.nperseg, self.step
        if len(buf) < L:
            self.pending = buf.copy()
            return
        nseg = 1 + (len(buf) - L) // step
        for a in range(0, nseg, _SEGMENTS_PER_CHUNK):
            b = min(a + _SEGMENTS_PER_CHUNK, nseg)
            # (segments, L, C) view of the overlapping segments, copied chunk by chunk
            segs = np.lib.stride_tricks.sliding_window_view(buf, L, axis=0)[a * step:(b - 1)
                                                                            * step + 1:step]
            segs = segs - segs.mean(axis=2, keepdims=True)  # (k, C, L)
            spec = np.fft.rfft(segs * self.window, axis=2)  # (k, C, F)
            self.sum += np.einsum("kif,kjf->fij", spec, spec.conj(), optimize=True)
        r = self.run_segments + np.arange(nseg)
        lags = np.minimum(r, len(self.rho2_cum) - 1)
        self.dof_denominator += float(np.sum(1.0 + 2.0 * self.rho2_cum[lags]))
        self.n_segments += nseg
        self.run_segments += nseg
        self.pending = buf[nseg * step:].copy()

    def result(self) -> CrossSpectra:
        """The averaged cross-spectral matrix so far."""
        if self.n_segments == 0:
            raise ValueError(f"no gap-free stretch of at least nperseg={self.nperseg} samples "
                             f"for a coherence estimate")
        scale = 2.0 / (self.fs_hz * float(np.sum(self.window**2)) * self.n_segments)
        sel = slice(2, self.nperseg // 2)
        f = np.fft.rfftfreq(self.nperseg, 1.0 / self.fs_hz)[sel]
        dof = 2.0 * self.n_segments**2 / self.dof_denominator
        return CrossSpectra(self.channels, self.fs_hz, self.nperseg, f, self.sum[sel] * scale,
                            0.5 * dof, self.n_segments)


def default_nperseg(n_longest: int, min_segments: int = 64, largest: int = 1 << 16) -> int:
    """The largest power of two that gives at least ``min_segments`` non-overlapping segments
    in a gap-free stretch of ``n_longest`` samples (at least 16, at most ``largest``)."""
    n = max(int(n_longest) // max(min_segments, 1), 16)
    return int(min(1 << int(math.floor(math.log2(n))), largest))


def cross_spectra(x: np.ndarray, fs_hz: float, channels: list[str] | tuple[str, ...],
                  nperseg: int | None = None,
                  segment_starts: np.ndarray | None = None) -> CrossSpectra:
    """Cross-spectral matrix of the columns of ``x`` (``(samples, channels)``, channel units).

    Args:
        x: samples, one column per channel, all on one time base.
        fs_hz: sampling rate in Hz.
        channels: column names.
        nperseg: Welch segment length (default :func:`default_nperseg` of the longest
            gap-free stretch).
        segment_starts: indices where gap-free segments begin (no Welch segment crosses one).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"x must be (samples, channels), got shape {x.shape}")
    starts = np.zeros(1, dtype=np.int64) if segment_starts is None \
        else np.asarray(segment_starts, dtype=np.int64)
    bounds = np.append(starts, len(x))
    if nperseg is None:
        nperseg = default_nperseg(int(np.max(np.diff(bounds))) if len(bounds) > 1 else 0)
    acc = CrossSpectralAccumulator(channels, fs_hz, nperseg)
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        acc.new_segment()
        if b > a:
            acc.add(x[a:b])
    return acc.result()


# ------------------------------------------------------------------ log-frequency coherence


@dataclass
class Coherence:
    """Coherence of every channel pair on log-frequency points.

    Attributes:
        channels: channel names.
        pairs: ``(a, b)`` channel-name pairs, in the order of the rows below.
        f_hz: point frequencies in Hz (mean of the merged bins).
        n_avg: equivalent independent averages of each point.
        msc: estimate, shape ``(pairs, points)``.
        ci_low, ci_high: equal-tailed interval of the true coherence (confidence ``ci``).
        threshold: MSC above which a point is coherent at ``alpha`` (single point).
        threshold_family: the same, Sidak-corrected for the points of one pair (a pair of
            independent channels shows no point above it with probability ``1 - alpha``).
        csd_abs: ``|S_ab|`` (units_a * units_b / Hz), ``csd_phase_rad``: its phase (rad).
        psd: each channel's PSD at the points, shape ``(channels, points)``.
        cross: the linear-bin cross-spectra it came from (not serialised).
    """

    channels: tuple[str, ...]
    pairs: list[tuple[str, str]]
    f_hz: np.ndarray
    n_avg: np.ndarray
    msc: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    threshold: np.ndarray
    threshold_family: np.ndarray
    csd_abs: np.ndarray
    csd_phase_rad: np.ndarray
    psd: np.ndarray
    ci: float
    alpha: float
    nperseg: int
    fs_hz: float
    cross: CrossSpectra | None = field(default=None, repr=False)

    def pair(self, a: str, b: str) -> int:
        """Row of the pair ``a``-``b`` (either order)."""
        for k, p in enumerate(self.pairs):
            if p in ((a, b), (b, a)):
                return k
        raise KeyError(f"no pair {a}-{b}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (lists of floats)."""
        def fl(a: np.ndarray) -> list:
            return np.round(np.asarray(a, dtype=np.float64), 12).tolist()

        return {"channels": list(self.channels), "pairs": [list(p) for p in self.pairs],
                "f_hz": fl(self.f_hz), "n_avg": fl(self.n_avg), "msc": fl(self.msc),
                "ci": {"level": self.ci, "low": fl(self.ci_low), "high": fl(self.ci_high)},
                "threshold": fl(self.threshold), "threshold_family": fl(self.threshold_family),
                "alpha": self.alpha, "csd_abs": fl(self.csd_abs),
                "csd_phase_rad": fl(self.csd_phase_rad), "psd": fl(self.psd),
                "nperseg": self.nperseg, "fs_hz": self.fs_hz,
                "method": "Welch, Hann, 50 % overlap; exact MSC distribution (Carter, Knapp "
                          "and Nuttall 1973)"}


def log_coherence(cs: CrossSpectra, points_per_decade: float = 10.0, ci: float = 0.95,
                  alpha: float = DEFAULT_ALPHA, intervals: bool = True) -> Coherence:
    """Coherence of every channel pair of ``cs`` merged onto log-frequency points.

    A point sums the cross-spectra of the bins ``floor(log10 f * points_per_decade)`` groups
    together (the rule of :mod:`imunoise.analysis.psd`); its number of averages is the bins'
    total reduced for adjacent Hann bins' correlation. ``intervals=False`` skips the exact
    intervals (about a second for 21 pairs of 60 points) and leaves them nan.
    """
    idx = np.floor(np.log10(cs.f_hz) * points_per_decade + 1e-9).astype(np.int64)
    _, first, counts = np.unique(idx, return_index=True, return_counts=True)
    n = counts.astype(np.float64)
    f = np.add.reduceat(cs.f_hz, first) / n
    s = np.add.reduceat(cs.s, first, axis=0)  # sums: the ratios need no division
    n_avg = cs.n_avg * n / _merge_factor(n, _bin_corr2(_window(cs.nperseg)))
    pairs = list(combinations(range(len(cs.channels)), 2))
    diag = np.stack([s[:, i, i].real for i in range(len(cs.channels))])
    msc = np.stack([_msc(s[:, i, j], diag[i], diag[j]) for i, j in pairs]) if pairs \
        else np.empty((0, f.size))
    csd = np.stack([s[:, i, j] for i, j in pairs]) / n if pairs \
        else np.empty((0, f.size), dtype=complex)
    if intervals and pairs:
        lo, hi = msc_interval(msc, np.broadcast_to(n_avg, msc.shape), ci)
    else:
        lo = hi = np.full(msc.shape, np.nan)
    return Coherence(
        channels=cs.channels, pairs=[(cs.channels[i], cs.channels[j]) for i, j in pairs],
        f_hz=f, n_avg=n_avg, msc=msc, ci_low=lo, ci_high=hi,
        threshold=msc_threshold(n_avg, alpha),
        threshold_family=msc_threshold(n_avg, alpha, n_tests=f.size),
        csd_abs=np.abs(csd), csd_phase_rad=np.angle(csd), psd=diag / n, ci=ci, alpha=alpha,
        nperseg=cs.nperseg, fs_hz=cs.fs_hz, cross=cs)


def coherence(x: np.ndarray, fs_hz: float, channels: list[str] | tuple[str, ...], *,
              nperseg: int | None = None, segment_starts: np.ndarray | None = None,
              points_per_decade: float = 10.0, ci: float = 0.95,
              alpha: float = DEFAULT_ALPHA) -> Coherence:
    """Cross-spectral density and coherence of every pair of the columns of ``x`` on
    log-frequency points, with exact intervals and the zero-coherence threshold.

    Arguments as :func:`cross_spectra` and :func:`log_coherence`.
    """
    cs = cross_spectra(x, fs_hz, channels, nperseg=nperseg, segment_starts=segment_starts)
    return log_coherence(cs, points_per_decade=points_per_decade, ci=ci, alpha=alpha)
