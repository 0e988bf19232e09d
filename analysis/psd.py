"""One-sided power spectral density with degrees of freedom and confidence intervals.

Two estimators, one output type (:class:`PsdEstimate`, channel units^2/Hz):

- :func:`welch_psd`: plain Welch (as ``scipy.signal.welch``: Hann window, 50 % overlap, segment
  mean removed) on a linear frequency axis. Good for the upper band and for looking at lines.
- :func:`log_psd` / :class:`StreamingPsd`: a decimation cascade that reaches down to about ten
  times the reciprocal of the record length on a log-spaced axis. Level 0 is Welch at the full
  rate; level ``j`` is the signal low-pass filtered and decimated by 2 ``j`` times, analysed with
  the same Hann segments. The batch function is the streaming estimator fed the whole record,
  so the two agree by construction (and a test checks block-size invariance).

Bands (``L = nperseg``, ``K0 = L/16``, ``fs_j = fs/2^j``)::

    level 0 ("welch"):        bins K0 .. L/2-1  ->  fs/16 .. fs/2 (Nyquist bin excluded)
    level j >= 1:             bins K0 .. 2*K0-1 ->  fs_j/16 .. fs_j/8, one octave each
    deepest populated level:  extends down to bin 2, but not below min_cycles / T

where ``T`` is the longest gap-free stretch of the record. Each level's band starts exactly where
the one above it stops, so no frequency is estimated twice; the bandwidths ``df_hz`` tile the axis
from the lowest point to a half bin below Nyquist, so ``sum(psd * df_hz)`` is the variance there.
A spectral line within two bins of a level boundary is seen by both levels' windows; its
integrated power can then be a few per cent low. Bins 0 and 1 are never used: the segment-mean
removal leaves bin 1 of a Hann-windowed segment biased low by 1/6 for white noise,
while bins >= 2 are unaffected (the Hann window's transform vanishes there).

Anti-alias filter: a 47-tap Kaiser-windowed FIR low-pass (cut-off 0.3 of Nyquist, about 100 dB
stop-band attenuation above half the Nyquist frequency) before each decimation by 2. The
passband droop of the cascade of filters is divided out exactly at each output frequency. Filter
outputs are only used once the filter is full, so nothing is bridged across a gap and no start-up
transient enters the spectrum.

Degrees of freedom: for ``K`` Welch segments in one gap-free run the equivalent degrees of
freedom follow from the window's overlap correlation ``rho_m`` (Welch 1967; Percival & Walden
1993): ``nu = 2 K^2 / (K + 2 sum_m (K - m) rho_m^2)``, about 1.89 K for Hann at 50 %; runs
separated by gaps add as independent. Neighbouring bins merged into one log-frequency point sum
their degrees of freedom, reduced for the correlation of adjacent Hann bins (|c_1|^2 = 4/9,
|c_2|^2 = 1/36). The interval is the chi-square interval
``[nu S / chi2_{1-a/2}, nu S / chi2_{a/2}]``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imunoise.analysis.distributions import chi2
from imunoise.analysis.dsp import (
    fir_response,
    hann,
    lowpass_fir,
    periodogram_sum,
    welch_density,
)
from imunoise.core.series import SAMPLE_LIMIT

_FIR_TAPS = lowpass_fir(47, 0.3, beta=10.0)
_DECIMATION = 2
_CHUNK = 1 << 18  # samples processed at once, bounds temporary memory
_MIN_BATCH = 1 << 16  # small blocks are gathered up to this many samples before processing


@dataclass(frozen=True)
class PsdEstimate:
    """A one-sided PSD estimate.

    Attributes:
        f_hz: frequency of each point in Hz, strictly increasing.
        psd: one-sided PSD in channel units^2/Hz (e.g. (rad/s)^2/Hz).
        dof: equivalent degrees of freedom of each point.
        ci_low, ci_high: chi-square confidence interval of each point (same units as ``psd``).
        ci: confidence level of the interval, e.g. 0.95.
        method: per point, ``"welch"`` (full rate) or ``"decimate<D>"`` (cascade level with
            decimation factor D).
        df_hz: bandwidth each point stands for in Hz; ``sum(psd * df_hz)`` is the variance in the
            covered band.
    """

    f_hz: np.ndarray
    psd: np.ndarray
    dof: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    ci: float
    method: np.ndarray
    df_hz: np.ndarray

    def __len__(self) -> int:
        return int(len(self.f_hz))

    def band_power(self, f_lo_hz: float = 0.0, f_hi_hz: float = math.inf) -> float:
        """Integral of the PSD over the points with ``f_lo_hz <= f <= f_hi_hz`` (units^2)."""
        sel = (self.f_hz >= f_lo_hz) & (self.f_hz <= f_hi_hz)
        return float(np.sum(self.psd[sel] * self.df_hz[sel]))


def chi2_interval(psd: np.ndarray, dof: np.ndarray, ci: float) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided chi-square confidence interval of PSD values with ``dof`` degrees of freedom."""
    if not 0.0 < ci < 1.0:
        raise ValueError(f"confidence level must be in (0, 1), got {ci}")
    a = (1.0 - ci) / 2.0
    psd = np.asarray(psd, dtype=np.float64)
    dof = np.asarray(dof, dtype=np.float64)
    return psd * dof / chi2.ppf(1.0 - a, dof), psd * dof / chi2.ppf(a, dof)


def _window(nperseg: int) -> np.ndarray:
    return hann(nperseg)


def _overlap_rho2(window: np.ndarray, step: int) -> np.ndarray:
    """Squared correlation of periodograms of segments ``m`` steps apart, m = 1, 2, ..."""
    w2 = float(np.sum(window**2))
    out = []
    m = 1
    while m * step < len(window):
        s = m * step
        out.append((float(np.dot(window[:-s], window[s:])) / w2) ** 2)
        m += 1
    return np.asarray(out)


def _bin_corr2(window: np.ndarray, n_max: int = 8) -> np.ndarray:
    """Squared correlation of periodogram bins ``m`` apart for white noise, m = 1 .. n_max."""
    w2 = window**2
    spec = np.abs(np.fft.rfft(w2))
    return (spec[1:n_max + 1] / spec[0]) ** 2


def _merge_factor(n: np.ndarray, c2: np.ndarray) -> np.ndarray:
    """Variance inflation of the mean of ``n`` adjacent correlated bins (1 for n = 1)."""
    n = np.asarray(n, dtype=np.float64)
    total = np.ones_like(n)
    for m, c in enumerate(c2, start=1):
        total += 2.0 * np.clip(n - m, 0.0, None) / n * c
    return total


def _overlap_denominator(k: np.ndarray, rho2: np.ndarray) -> np.ndarray:
    """``K + 2 sum_m (K - m) rho_m^2`` for runs of ``K`` overlapping segments."""
    k = np.asarray(k, dtype=np.float64)
    total = k.copy()
    for m, r in enumerate(rho2, start=1):
        total += 2.0 * np.clip(k - m, 0.0, None) * r
    return total


def _segments_of(x: np.ndarray, segment_starts: np.ndarray | None) -> list[np.ndarray]:
    x = np.asarray(x, dtype=np.float64).ravel()
    if segment_starts is None:
        return [x]
    starts = np.asarray(segment_starts, dtype=np.int64)
    bounds = np.append(starts, len(x))
    return [x[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


def _check_finite(x: np.ndarray) -> None:
    if not np.all(np.isfinite(x)):
        raise ValueError("PSD input contains NaN or infinite values; split the record around them")
    if x.size and float(np.max(np.abs(x))) > SAMPLE_LIMIT:  # its squares' sums would overflow
        raise ValueError(f"PSD input has values beyond {SAMPLE_LIMIT:g}")


def _log_group(
    f: np.ndarray, psd: np.ndarray, dof: float, df: np.ndarray, c2: np.ndarray,
    points_per_decade: float | None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Average adjacent bins of one level that fall in the same log-frequency bin.

    ``df`` is the bandwidth of each bin in Hz; merged points carry the sum.
    """
    if points_per_decade is None or len(f) == 0:
        return f, psd, np.full(len(f), dof), df
    idx = np.floor(np.log10(f) * points_per_decade + 1e-9).astype(np.int64)
    _, first, counts = np.unique(idx, return_index=True, return_counts=True)
    n = counts.astype(np.float64)
    f_g = np.add.reduceat(f, first) / n
    p_g = np.add.reduceat(psd, first) / n
    dof_g = dof * n / _merge_factor(n, c2)
    return f_g, p_g, dof_g, np.add.reduceat(df, first)


def welch_psd(
    x: np.ndarray,
    fs_hz: float,
    nperseg: int = 256,
    ci: float = 0.95,
    segment_starts: np.ndarray | None = None,
    points_per_decade: float | None = None,
) -> PsdEstimate:
    """Welch PSD (Hann, 50 % overlap, mean removed) of one channel, one-sided, units^2/Hz.

    Args:
        x: samples in channel units.
        fs_hz: sampling rate in Hz.
        nperseg: segment length in samples.
        ci: confidence level of the interval.
        segment_starts: indices where gap-free segments begin; segments are analysed apart
            and averaged with their segment counts as weights (gaps are never bridged).
        points_per_decade: if given, average neighbouring bins into log-frequency bins.

    Bins 0, 1 and the Nyquist bin are left out (see the module notes).
    """
    if nperseg < 8:
        raise ValueError("nperseg must be at least 8")
    step = nperseg // 2
    win = _window(nperseg)
    rho2 = _overlap_rho2(win, step)
    total = None
    n_seg = 0
    denom = 0.0
    f = None
    for seg in _segments_of(x, segment_starts):
        if len(seg) < nperseg:
            continue
        _check_finite(seg)
        f, p = welch_density(seg, fs_hz, win, step)
        k = 1 + (len(seg) - nperseg) // step
        total = p * k if total is None else total + p * k
        n_seg += k
        denom += float(_overlap_denominator(np.array([k]), rho2)[0])
    if total is None or f is None:
        raise ValueError(f"no gap-free stretch of at least nperseg={nperseg} samples")
    psd = total / n_seg
    dof = 2.0 * n_seg**2 / denom
    sel = slice(2, nperseg // 2)
    f_g, p_g, dof_g, df_g = _log_group(f[sel], psd[sel], dof,
                                       np.full(len(f[sel]), fs_hz / nperseg),
                                       _bin_corr2(win), points_per_decade)
    lo, hi = chi2_interval(p_g, dof_g, ci)
    return PsdEstimate(f_hz=f_g, psd=p_g, dof=dof_g, ci_low=lo, ci_high=hi, ci=ci,
                       method=np.full(len(f_g), "welch"), df_hz=df_g)


class _Level:
    """One level of the cascade: Welch accumulation at rate ``fs_hz`` and the decimator below."""

    def __init__(self, fs_hz: float, nperseg: int, window: np.ndarray, rho2: np.ndarray) -> None:
        self.fs_hz = fs_hz
        self.nperseg = nperseg
        self.step = nperseg // 2
        self.window = window
        self.rho2_cum = np.concatenate(([0.0], np.cumsum(rho2)))
        self.pgram_sum = np.zeros(nperseg // 2 + 1)
        self.n_seg = 0
        self.dof_denominator = 0.0
        self.reset_segment()

    def reset_segment(self) -> None:
        self.pending = np.empty(0)
        self.run_segments = 0
        self.fir_history = np.empty(0)
        self.valid_outputs = 0

    def add(self, x: np.ndarray) -> None:
        buf = np.concatenate((self.pending, x)) if self.pending.size else x
        L, step = self.nperseg, self.step
        if len(buf) < L:
            self.pending = buf.copy()
            return
        nseg = 1 + (len(buf) - L) // step
        self.pgram_sum += periodogram_sum(buf, self.window, step, nseg)
        r = self.run_segments + np.arange(nseg)
        lags = np.minimum(r, len(self.rho2_cum) - 1)
        self.dof_denominator += float(np.sum(1.0 + 2.0 * self.rho2_cum[lags]))
        self.n_seg += nseg
        self.run_segments += nseg
        self.pending = buf[nseg * step:].copy()

    def decimate(self, x: np.ndarray) -> np.ndarray:
        buf = np.concatenate((self.fir_history, x)) if self.fir_history.size else x
        ntaps = len(_FIR_TAPS)
        if len(buf) < ntaps:
            self.fir_history = buf.copy()
            return np.empty(0)
        y = np.convolve(buf, _FIR_TAPS, mode="valid")
        start = (-self.valid_outputs) % _DECIMATION
        self.valid_outputs += len(y)
        self.fir_history = buf[len(buf) - (ntaps - 1):].copy()
        return y[start::_DECIMATION]


def _cascade_gain(f_hz: np.ndarray, fs_hz: float, level: int) -> np.ndarray:
    """Power gain of the ``level`` anti-alias filters in front of cascade level ``level``."""
    gain = np.ones(len(f_hz))
    for i in range(level):
        fs_i = fs_hz / _DECIMATION**i
        h = fir_response(_FIR_TAPS, 2.0 * np.pi * f_hz / fs_i)
        gain *= np.abs(h) ** 2
    return gain


class StreamingPsd:
    """Log-frequency PSD fed block by block with bounded memory.

    Each cascade level keeps the running sum of its segment periodograms, the partial segment
    and the filter history, all a few ``nperseg`` long; the number of levels grows with the log
    of the record length. Call :meth:`new_segment` at every gap so nothing is bridged.

    Args:
        fs_hz: sampling rate in Hz.
        nperseg: Welch segment length at every level (multiple of 16, at least 64).
        points_per_decade: log-frequency bins per decade for merging neighbouring bins, or
            None to keep every bin.
        min_cycles: the lowest frequency reported is ``min_cycles / T`` with ``T`` the longest
            gap-free stretch seen.
        max_levels: maximum number of cascade levels (decimation by up to 2^(max_levels-1)).
    """

    def __init__(self, fs_hz: float, nperseg: int = 256, points_per_decade: float | None = 40.0,
                 min_cycles: float = 10.0, max_levels: int = 48) -> None:
        if fs_hz <= 0 or not math.isfinite(fs_hz):
            raise ValueError(f"sampling rate must be positive, got {fs_hz}")
        if nperseg < 64 or nperseg % 16:
            raise ValueError(f"nperseg must be a multiple of 16 and at least 64, got {nperseg}")
        self.fs_hz = float(fs_hz)
        self.nperseg = int(nperseg)
        self.points_per_decade = points_per_decade
        self.min_cycles = float(min_cycles)
        self.max_levels = int(max_levels)
        self._window = _window(nperseg)
        self._rho2 = _overlap_rho2(self._window, nperseg // 2)
        self._c2 = _bin_corr2(self._window)
        self._levels: list[_Level] = []
        self._inbox: list[np.ndarray] = []
        self._inbox_samples = 0
        self._run = 0
        self._longest_run = 0
        self.n_samples = 0

    def new_segment(self) -> None:
        """Declare a gap: the next block does not continue the previous one."""
        self._flush()
        for lev in self._levels:
            lev.reset_segment()
        self._run = 0

    def update(self, block: np.ndarray) -> None:
        """Add contiguous samples (channel units) that continue the current segment."""
        x = np.asarray(block, dtype=np.float64).ravel()
        _check_finite(x)
        self.n_samples += len(x)
        self._run += len(x)
        self._longest_run = max(self._longest_run, self._run)
        if len(x) >= _MIN_BATCH and not self._inbox:
            self._process(x)
            return
        # Small blocks wait until there are enough to make the per-level work worthwhile;
        # the result does not depend on how the samples were split.
        self._inbox.append(x.copy())
        self._inbox_samples += len(x)
        if self._inbox_samples >= _MIN_BATCH:
            self._flush()

    def _flush(self) -> None:
        if self._inbox:
            x = np.concatenate(self._inbox)
            self._inbox.clear()
            self._inbox_samples = 0
            self._process(x)

    def _process(self, x: np.ndarray) -> None:
        for a in range(0, len(x), _CHUNK):
            self._feed(0, x[a:a + _CHUNK])

    def _feed(self, j: int, x: np.ndarray) -> None:
        while j < self.max_levels and x.size:
            if j == len(self._levels):
                self._levels.append(_Level(self.fs_hz / _DECIMATION**j, self.nperseg,
                                           self._window, self._rho2))
            lev = self._levels[j]
            lev.add(x)
            x = lev.decimate(x) if j + 1 < self.max_levels else np.empty(0)
            j += 1

    def state_size(self) -> int:
        """Number of float64 values held (periodogram sums, partial segments, filter histories)."""
        return self._inbox_samples + sum(
            lev.pgram_sum.size + lev.pending.size + lev.fir_history.size for lev in self._levels)

    @property
    def longest_segment_s(self) -> float:
        """Duration of the longest gap-free stretch seen, in seconds."""
        return self._longest_run / self.fs_hz

    def estimate(self, ci: float = 0.95) -> PsdEstimate:
        """The current estimate on a log-spaced axis; raises ValueError before the first segment."""
        self._flush()
        populated = [j for j, lev in enumerate(self._levels) if lev.n_seg > 0]
        if not populated:
            raise ValueError(f"not enough data for a PSD: need {self.nperseg} contiguous samples")
        deepest = max(populated)
        L = self.nperseg
        k0 = L // 16
        f_floor = self.min_cycles / self.longest_segment_s
        parts = []
        for j in range(deepest, -1, -1):
            lev = self._levels[j]
            k_hi = L // 2 if j == 0 else 2 * k0
            k_lo = 2 if j == deepest else k0
            k = np.arange(k_lo, k_hi)
            f = k * lev.fs_hz / L
            keep = f >= f_floor if j == deepest else np.ones(len(k), dtype=bool)
            k, f = k[keep], f[keep]
            if not len(k):
                continue
            scale = 2.0 / (lev.fs_hz * float(np.sum(self._window**2)) * lev.n_seg)
            psd = lev.pgram_sum[k] * scale / _cascade_gain(f, self.fs_hz, j)
            dof = 2.0 * lev.n_seg**2 / lev.dof_denominator
            # Bin k stands for (k -/+ 1/2) fs_j / L, except that the lowest bin of a level
            # with a deeper level below starts where the deeper level's top bin ends.
            df = np.full(len(k), lev.fs_hz / L)
            if j != deepest:
                df[k == k0] *= 0.75
            fg, pg, dg, wg = _log_group(f, psd, dof, df, self._c2, self.points_per_decade)
            name = "welch" if j == 0 else f"decimate{_DECIMATION**j}"
            parts.append((fg, pg, dg, wg, np.full(len(fg), name)))
        if not parts:
            raise ValueError("not enough data for a PSD above min_cycles / T")
        f_all, p_all, d_all, w_all, m_all = (np.concatenate(c) for c in zip(*parts, strict=True))
        lo, hi = chi2_interval(p_all, d_all, ci)
        return PsdEstimate(f_hz=f_all, psd=p_all, dof=d_all, ci_low=lo, ci_high=hi, ci=ci,
                           method=m_all, df_hz=w_all)


def log_psd(
    x: np.ndarray,
    fs_hz: float,
    segment_starts: np.ndarray | None = None,
    points_per_decade: float | None = 40.0,
    ci: float = 0.95,
    nperseg: int = 256,
    min_cycles: float = 10.0,
) -> PsdEstimate:
    """Log-frequency PSD of one channel (one-sided, units^2/Hz) from the Welch band down to
    about ``min_cycles`` over the longest gap-free stretch.

    Args:
        x: samples in channel units, gap-free segments concatenated.
        fs_hz: sampling rate in Hz.
        segment_starts: indices where gap-free segments begin (None: one segment).
        points_per_decade: log bins per decade for merging neighbouring bins (None: all bins).
        ci: confidence level of the interval.
        nperseg: segment length at every cascade level (see :class:`StreamingPsd`).
        min_cycles: lowest frequency reported is ``min_cycles / T``.
    """
    est = StreamingPsd(fs_hz, nperseg=nperseg, points_per_decade=points_per_decade,
                       min_cycles=min_cycles)
    for seg in _segments_of(x, segment_starts):
        est.new_segment()
        est.update(seg)
    return est.estimate(ci=ci)


def default_nperseg(n_longest: int, preferred: int = 256) -> int:
    """The largest power of two ``<= preferred`` that fits a gap-free stretch of ``n_longest``
    samples at least twice (at least 64)."""
    n = preferred
    while n > 64 and 2 * n > n_longest:
        n //= 2
    return n


def white_level(psd: np.ndarray, dof: np.ndarray, ci: float = 0.95
                ) -> tuple[float, float, float] | None:
    """White-noise density N (units/sqrt(Hz)) from one-sided PSD points of a white band.

    A white rate noise with Allan variance N^2/tau has the flat one-sided PSD 2 N^2, so
    N = sqrt(mean(S) / 2) over the band. The mean of points with ``dof`` degrees of freedom each
    is a scaled chi-square; neighbouring Welch bins of a Hann window are correlated, so half of
    the summed degrees of freedom is used (conservative: the true effective number is about
    two thirds). Returns ``(N, low, high)`` at confidence ``ci``, or None without usable points.
    """
    s = np.asarray(psd, dtype=np.float64)
    d = np.asarray(dof, dtype=np.float64)
    ok = np.isfinite(s) & (s > 0) & np.isfinite(d) & (d > 0)
    if not ok.any():
        return None
    mean = float(np.mean(s[ok]))
    nu = 0.5 * float(np.sum(d[ok]))
    lo_q, hi_q = chi2.ppf([(1 + ci) / 2, (1 - ci) / 2], nu)
    return (math.sqrt(mean / 2.0), math.sqrt(mean * nu / lo_q / 2.0),
            math.sqrt(mean * nu / hi_q / 2.0))
