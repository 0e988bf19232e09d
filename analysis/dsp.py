"""The few signal-processing primitives the fit, the PSD and the evidence use, in numpy.

Each gives the numbers of its ``scipy.signal`` namesake (the tests compare them): the periodic
Hann window of ``get_window("hann", n)``, the Kaiser-windowed low-pass of ``firwin``, a filter's
frequency response (``freqz``), a least-squares line removed along an axis (``detrend``), and the
one-sided Welch density (``welch`` with a mean removed per segment).

Written here rather than imported because importing ``scipy.signal`` imports ``scipy.stats``
and parses the docstrings of both: about half a second at the start of every ``imunoise``
command, which a batch of fits and diagnoses pays hundreds of times.
"""

from __future__ import annotations

import numpy as np
import scipy.special as sc

WELCH_CHUNK = 1 << 18
"""Samples of segments transformed at once by :func:`welch_density` (bounds its memory)."""


def hann(n: int) -> np.ndarray:
    """The periodic ``n``-point Hann window (for spectra: its DFT has a two-bin main lobe)."""
    if n <= 1:
        return np.ones(max(n, 0))
    fac = np.linspace(-np.pi, np.pi, n + 1)[:-1]
    return 0.5 + 0.5 * np.cos(fac)


def kaiser(n: int, beta: float) -> np.ndarray:
    """The symmetric ``n``-point Kaiser window of shape ``beta`` (for filter design)."""
    if n == 1:
        return np.ones(1)
    k = np.arange(0, n)
    alpha = (n - 1) / 2.0
    return sc.i0(beta * np.sqrt(1.0 - ((k - alpha) / alpha) ** 2.0)) / sc.i0(beta)


def lowpass_fir(numtaps: int, cutoff: float, beta: float) -> np.ndarray:
    """Taps of a linear-phase low-pass FIR: the ideal response cut at ``cutoff`` (a fraction
    of the Nyquist frequency) under a Kaiser window of shape ``beta``, scaled to unit gain at
    zero frequency."""
    m = np.arange(0, numtaps) - 0.5 * (numtaps - 1)
    h = cutoff * np.sinc(cutoff * m)
    h *= kaiser(numtaps, beta)
    return h / np.sum(h)


def fir_response(taps: np.ndarray, w_rad: np.ndarray) -> np.ndarray:
    """Complex response of the FIR ``taps`` at normalised angular frequencies ``w_rad``
    (rad/sample)."""
    from numpy.polynomial.polynomial import polyval

    z1 = np.exp(-1j * np.asarray(w_rad, dtype=np.float64))
    return polyval(z1, np.asarray(taps), tensor=False)


def detrend_linear(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """``x`` with its least-squares straight line removed along ``axis``."""
    x = np.asarray(x, dtype=np.float64)
    y = np.moveaxis(x, axis, -1)
    n = y.shape[-1]
    t = np.arange(n, dtype=np.float64) - (n - 1) / 2.0
    centred = y - y.mean(axis=-1, keepdims=True)
    tt = float(t @ t)
    slope = (centred @ t) / tt if tt > 0 else np.zeros(y.shape[:-1])
    return np.moveaxis(centred - slope[..., None] * t, -1, axis)


def periodogram_sum(x: np.ndarray, window: np.ndarray, step: int, nseg: int) -> np.ndarray:
    """Sum of ``|rfft(window * (s - mean(s)))|^2`` over the first ``nseg`` segments ``s`` of
    ``x`` of the window's length, ``step`` samples apart (units^2 per bin, unnormalised): the
    Welch step both :func:`welch_density` and the PSD cascade
    (:mod:`imunoise.analysis.psd`) accumulate."""
    segs = np.lib.stride_tricks.sliding_window_view(x, len(window))[::step][:nseg]
    segs = segs - segs.mean(axis=1, keepdims=True)
    spec = np.fft.rfft(segs * window, axis=1)
    return np.sum(spec.real**2 + spec.imag**2, axis=0)


def welch_density(x: np.ndarray, fs_hz: float, window: np.ndarray | int,
                  step: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD of ``x`` (units^2/Hz) at its frequencies (Hz): segments of the
    window's length every ``step`` samples (default half of it), each with its mean removed,
    their periodograms averaged. ``window`` is the window itself or a length for
    :func:`hann`. Raises ValueError when ``x`` is shorter than one segment."""
    w = hann(int(window)) if np.ndim(window) == 0 else np.asarray(window, dtype=np.float64)
    L = len(w)
    step = L // 2 if step is None else int(step)
    x = np.asarray(x, dtype=np.float64)
    if L < 1 or step < 1 or x.size < L:
        raise ValueError(f"{x.size} samples are fewer than one segment of {L}")
    nseg = 1 + (x.size - L) // step
    total = np.zeros(L // 2 + 1)
    per = max(1, WELCH_CHUNK // L)
    for first in range(0, nseg, per):
        k = min(per, nseg - first)
        total += periodogram_sum(x[first * step:first * step + (k - 1) * step + L], w, step,
                                 k)
    p = total / nseg / (fs_hz * float(np.sum(w * w)))
    p[1:-1 if L % 2 == 0 else None] *= 2.0
    return np.fft.rfftfreq(L, 1.0 / fs_hz), p

