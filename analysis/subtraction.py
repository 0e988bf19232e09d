"""A channel's own noise: what remains once the other channels' coherent part is removed.

Multi-input Wiener subtraction in the frequency domain (Bendat and Piersol, *Random Data*,
4th ed. 2010, ch. 7, conditioned spectra). With the target ``y`` and references ``x`` (other
axes of the same sensor, or a reference sensor), the optimal transfer at each frequency is
``H = S_xx^-1 S_xy`` and the part of ``y`` the references explain has the PSD
``S_yy g_m``, ``g_m = S_yx S_xx^-1 S_xy / S_yy`` the multiple coherence. ``H`` is estimated on
the Welch bins of :mod:`imunoise.analysis.coherence` and applied to the references in the time
domain (an FIR of ``nperseg`` taps, centred, Hann-tapered), so the residual
``r = y - sum_j h_j * x_j`` is a series the Allan/PSD/fit/diagnosis tools take as they are.

Only coherent bins are subtracted: where the multiple coherence does not pass the zero-coherence
test (``P(g_m > x) = I_{1-x}(n-q, q)`` for ``q`` references and ``n`` averages, Goodman 1963;
Sidak over the bins at level ``alpha``), ``H`` is set to zero. Removing an estimated transfer
everywhere would take a random ``q/n`` share of the target's own noise with it and add the
references' noise back.

The error of the subtraction, stated with every result (:attr:`Subtraction.error`):

- ``bias_factor``: where it is applied, the residual's PSD is biased low by ``(n - q) / n``
  (the filter is fitted to the same data; the conditioned spectrum has ``2 (n - q)`` degrees of
  freedom);
- ``leak_var``: the references' own noise the filter passes into the residual, at most
  ``sum_j |H_j|^2 min(S_jj (1 - g_jy), continuum_j)`` integrated over the subtracted bins (each
  reference's part not coherent with the target, and no more than its local continuum, the
  running median of its PSD over 49 bins), in target units^2;
- ``left_var``: the common part left where the test did not pass, at most
  ``S_yy g_m`` integrated over the bins not subtracted (most of it is the estimate's own bias,
  about ``q/n`` of the power);
- ``removed_var``: the variance removed. All three as variances and relative to the target's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.ndimage
from scipy import special

from imunoise.analysis.coherence import DEFAULT_ALPHA, CrossSpectra, cross_spectra

_FLOOR_BINS = 49  # bins of the running median taken as a reference's local continuum


def multiple_coherence_threshold(n: float, q: int, alpha: float = DEFAULT_ALPHA,
                                 n_tests: int = 1) -> float:
    """Multiple coherence above which zero coherence with ``q`` references is rejected at
    ``alpha`` (Sidak over ``n_tests``): under the null ``g_m ~ Beta(q, n - q)``."""
    a1 = -math.expm1(math.log1p(-alpha) / max(int(n_tests), 1))
    return float(special.betaincinv(q, max(n - q, 1e-9), 1.0 - a1))


@dataclass
class Subtraction:
    """The residual of one channel after removing what the references explain.

    Attributes:
        target: the channel cleaned.
        references: the channels whose coherent part was removed.
        residual: the residual series (target units, same length and segments as the input).
        f_hz: Welch bin frequencies (Hz).
        multiple_coherence: ``g_m`` on each bin.
        subtracted: bins where ``H`` was applied (the test passed).
        threshold: the multiple-coherence threshold used.
        psd_target, psd_removed, psd_leak: target PSD, the PSD removed (``S_yy g_m`` on the
            subtracted bins) and the bound on the references' noise passed in (units^2/Hz).
        n_avg: equivalent independent averages per bin.
        error: the stated error (module notes): ``bias_factor``, ``removed_var``, ``leak_var``,
            ``left_var``, ``target_var`` and the ``*_share`` of each in the target's variance.
        segment_starts, t0_s: the residual's segments and first sample time when they are not
            those of the caller's series (the channels were first brought onto another
            channel's time base); None otherwise.
    """

    target: str
    references: list[str]
    residual: np.ndarray
    f_hz: np.ndarray
    multiple_coherence: np.ndarray
    subtracted: np.ndarray
    threshold: float
    psd_target: np.ndarray
    psd_removed: np.ndarray
    psd_leak: np.ndarray
    n_avg: float
    error: dict[str, float] = field(default_factory=dict)
    segment_starts: np.ndarray | None = None
    t0_s: float | None = None

    def avar_of(self, psd: np.ndarray, tau_s: np.ndarray | float) -> np.ndarray:
        """Allan variance (units^2) at ``tau_s`` of a component with the one-sided PSD ``psd``
        on :attr:`f_hz`: ``sum S(f) 2 sin^4(pi f tau) / (pi f tau)^2 df``."""
        tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))[:, None]
        x = np.pi * self.f_hz[None, :] * tau
        df = float(self.f_hz[1] - self.f_hz[0]) if self.f_hz.size > 1 else 0.0
        return np.sum(psd[None, :] * 2.0 * np.sin(x) ** 4 / x**2, axis=1) * df

    def white_level(self, fs_hz: float, tau_s: float = 1.0, ci: float = 0.95,
                    segment_starts: np.ndarray | None = None
                    ) -> tuple[float, tuple[float, float]]:
        """The residual's white level read at ``tau_s`` (``N = sigma(tau) sqrt(tau)``,
        units/sqrt(Hz); right where the own noise is white there), with an interval that
        holds both the Allan estimate's chi-square interval and the subtraction's error: its
        lower end also takes off the references' noise the filter may have passed in
        (:attr:`psd_leak` at that tau)."""
        from imunoise.analysis.allan import oadev

        m = max(int(round(tau_s * fs_hz)), 1)
        curve = oadev(self.residual, fs_hz, m=[m], segment_starts=segment_starts, ci=ci)
        tau = float(curve.tau_s[0])
        leak = float(self.avar_of(self.psd_leak, tau)[0])
        lo = math.sqrt(max(float(curve.ci_low[0]) ** 2 - leak, 0.0) * tau)
        return float(curve.dev[0]) * math.sqrt(tau), (lo, float(curve.ci_high[0]) * math.sqrt(tau))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready summary (no series)."""
        sub = self.subtracted
        bands = []
        if np.any(sub):
            edges = np.flatnonzero(np.diff(np.r_[0, sub.astype(int), 0]))
            bands = [[float(self.f_hz[a]), float(self.f_hz[b - 1])]
                     for a, b in zip(edges[::2], edges[1::2], strict=True)]
        return {"target": self.target, "references": list(self.references),
                "threshold": self.threshold, "n_avg": self.n_avg,
                "bands_subtracted_hz": bands,
                "error": {k: float(v) for k, v in self.error.items()}}


def _fir(h_bins: np.ndarray, nperseg: int) -> np.ndarray:
    """A centred, Hann-tapered FIR of ``nperseg`` taps with the rfft-grid response ``h_bins``."""
    from scipy.signal import get_window  # slow to import: see analysis.dsp

    h = np.fft.irfft(h_bins, n=nperseg)
    return np.roll(h, nperseg // 2) * get_window("hann", nperseg, fftbins=False)


def subtract_common(x: np.ndarray, fs_hz: float, channels: list[str] | tuple[str, ...],
                    target: str, references: list[str] | None = None, *,
                    nperseg: int | None = None, segment_starts: np.ndarray | None = None,
                    alpha: float = DEFAULT_ALPHA, cross: CrossSpectra | None = None
                    ) -> Subtraction:
    """Remove from ``target`` what ``references`` (default: every other channel) explain.

    Args:
        x: samples ``(n, channels)`` on one time base (channel units; SI inside).
        fs_hz: sampling rate, Hz.
        channels: column names.
        target: the channel to clean.
        references: the channels to remove the coherent part of.
        nperseg: Welch/FIR length (default that of :func:`cross_spectra`).
        segment_starts: gap-free segment starts; filtering never crosses a gap.
        alpha: family-wise level of the per-bin test deciding where to subtract.
        cross: cross-spectra of ``x`` already computed (same ``nperseg``), to reuse.
    """
    from scipy.signal import oaconvolve  # slow to import: see analysis.dsp

    x = np.asarray(x, dtype=np.float64)
    names = list(channels)
    if target not in names:
        raise ValueError(f"no channel {target!r} (channels: {', '.join(names)})")
    refs = [c for c in (references if references is not None else names) if c != target]
    missing = [c for c in refs if c not in names]
    if missing or not refs:
        raise ValueError(f"references must be other channels of the record; got "
                         f"{', '.join(missing) or 'none'}")
    cs = cross if cross is not None else cross_spectra(x, fs_hz, names, nperseg=nperseg,
                                                       segment_starts=segment_starts)
    L = cs.nperseg
    it, ir = cs.index(target), [cs.index(c) for c in refs]
    q = len(refs)
    sxx = cs.s[:, ir][:, :, ir]                     # (F, q, q)
    sxy = cs.s[:, ir, it]                           # (F, q): E[X_j conj Y]
    syy = cs.s[:, it, it].real
    # H_j: y ~ sum_j H_j x_j; normal equations S_xx^T H = S_yx^T, i.e. conj(S_xx) H = conj(S_xy)
    ridge = 1e-12 * np.trace(sxx, axis1=1, axis2=2).real[:, None, None] * np.eye(q)
    h = np.linalg.solve(np.conj(sxx) + ridge, np.conj(sxy)[..., None])[..., 0]  # (F, q)
    explained = np.einsum("fj,fj->f", np.conj(h), np.conj(sxy)).real
    gm = np.clip(np.where(syy > 0, explained / np.where(syy > 0, syy, 1.0), 0.0), 0.0, 1.0)
    thr = multiple_coherence_threshold(cs.n_avg, q, alpha, n_tests=cs.f_hz.size)
    sub = gm > thr
    h_full = np.zeros((L // 2 + 1, q), dtype=np.complex128)
    h_full[2:L // 2][sub] = h[sub]
    firs = [_fir(h_full[:, j], L) for j in range(q)]
    starts = np.zeros(1, dtype=np.int64) if segment_starts is None \
        else np.asarray(segment_starts, dtype=np.int64)
    bounds = np.append(starts, len(x))
    residual = x[:, it].copy()
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        if b <= a:
            continue
        for j, fir in zip(ir, firs, strict=True):
            seg = x[a:b, j] - np.mean(x[a:b, j])
            residual[a:b] -= oaconvolve(seg, fir, mode="full")[L // 2:L // 2 + b - a]
    df = cs.df_hz
    sjj = np.stack([cs.s[:, j, j].real for j in ir], axis=1)
    gjy = np.abs(sxy) ** 2 / np.maximum(sjj * syy[:, None], 1e-300)
    # a reference's own noise at a bin: at most its part not coherent with the target, and
    # at most its local continuum (a line's bin owes its 1 - g to the estimate's scatter)
    floor = scipy.ndimage.median_filter(sjj, size=(_FLOOR_BINS, 1), mode="nearest")
    own_ref = np.minimum(sjj * (1.0 - gjy), floor)
    leak = np.where(sub, np.sum(np.abs(h) ** 2 * own_ref, axis=1), 0.0)
    removed = np.where(sub, syy * gm, 0.0)
    target_var = float(np.sum(syy) * df)
    err = {"bias_factor": (cs.n_avg - q) / cs.n_avg,
           "removed_var": float(np.sum(removed) * df), "leak_var": float(np.sum(leak) * df),
           "left_var": float(np.sum(np.where(sub, 0.0, syy * gm)) * df),
           "target_var": target_var}
    for k in ("removed_var", "leak_var", "left_var"):
        err[k.replace("_var", "_share")] = err[k] / target_var if target_var > 0 else 0.0
    return Subtraction(target, refs, residual, cs.f_hz, gm, sub, thr, syy, removed, leak,
                       cs.n_avg, err)
