"""Light-weight streaming Allan variance and PSD for live monitoring.

Both estimators take blocks of samples, keep memory bounded whatever the record length, never
bridge a gap (``new_segment()``), and return their curves with 95 % chi-square bands.

- :class:`OctaveAllan`: non-overlapping Allan variance at octave cluster sizes m = 1, 2, 4, ...,
  computed with a pyramid of pairwise cluster averages (O(1) memory per octave, O(n) work).
- :class:`StreamingWelch`: Welch periodogram with a fixed segment length (Hann window,
  non-overlapping segments, mean removed), averaged over every complete segment seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal, stats


@dataclass
class AllanCurveData:
    """Allan variance at a set of averaging times.

    Attributes:
        tau_s: averaging times in s.
        m: cluster sizes in samples.
        avar: Allan variance in (channel units)^2.
        edf: equivalent degrees of freedom of each estimate.
        n_terms: number of squared differences averaged.
        ci_low, ci_high: 95 % interval of the Allan *deviation* (channel units).
    """

    tau_s: np.ndarray
    m: np.ndarray
    avar: np.ndarray
    edf: np.ndarray
    n_terms: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray

    @property
    def dev(self) -> np.ndarray:
        return np.sqrt(self.avar)


@dataclass
class PsdData:
    """One-sided power spectral density.

    Attributes:
        f_hz: frequencies in Hz (DC excluded).
        psd: PSD in (channel units)^2/Hz.
        dof: degrees of freedom of each point.
        ci_low, ci_high: 95 % interval of the PSD.
    """

    f_hz: np.ndarray
    psd: np.ndarray
    dof: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray


def chi2_band(value: np.ndarray, dof: np.ndarray,
              level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided chi-square interval of a variance-like estimate with ``dof`` degrees of freedom."""
    dof = np.maximum(np.asarray(dof, dtype=np.float64), 1e-9)
    alpha = (1.0 - level) / 2.0
    low = value * dof / stats.chi2.ppf(1.0 - alpha, dof)
    high = value * dof / stats.chi2.ppf(alpha, dof)
    return low, high


class _Octave:
    """Running state of one octave: a pending half cluster and the last complete cluster mean."""

    __slots__ = ("carry", "last", "sumsq", "count")

    def __init__(self) -> None:
        self.carry: float | None = None  # first of a pair waiting for its partner
        self.last: float | None = None   # previous cluster mean in this segment
        self.sumsq = 0.0
        self.count = 0


class OctaveAllan:
    """Streaming non-overlapping Allan variance at octave cluster sizes.

    Args:
        fs_hz: sampling rate in Hz.
        max_octaves: largest cluster size is ``2**(max_octaves-1)`` samples.
    """

    def __init__(self, fs_hz: float, max_octaves: int = 40) -> None:
        if not fs_hz > 0:
            raise ValueError(f"sampling rate must be positive, got {fs_hz}")
        self.fs_hz = float(fs_hz)
        self._octaves = [_Octave() for _ in range(max_octaves)]
        self.n_samples = 0

    def new_segment(self) -> None:
        """Forget partial clusters: the next sample is not contiguous with the last one."""
        for octave in self._octaves:
            octave.carry = None
            octave.last = None

    def update(self, values: np.ndarray) -> None:
        """Add contiguous samples (channel units)."""
        y = np.asarray(values, dtype=np.float64).ravel()
        y = y[np.isfinite(y)]
        self.n_samples += y.size
        for octave in self._octaves:
            if y.size == 0:
                break
            seq = y if octave.last is None else np.concatenate(([octave.last], y))
            if seq.size >= 2:
                d = np.diff(seq)
                octave.sumsq += float(d @ d)
                octave.count += d.size
            octave.last = float(y[-1])
            if octave.carry is not None:
                y = np.concatenate(([octave.carry], y))
            if y.size % 2:
                octave.carry = float(y[-1])
                y = y[:-1]
            else:
                octave.carry = None
            y = 0.5 * (y[0::2] + y[1::2])

    def curve(self, min_terms: int = 4) -> AllanCurveData:
        """Allan variance at every octave with at least ``min_terms`` differences."""
        counts = np.array([o.count for o in self._octaves], dtype=np.float64)
        sums = np.array([o.sumsq for o in self._octaves], dtype=np.float64)
        keep = counts >= min_terms
        m = (2 ** np.arange(len(self._octaves), dtype=np.float64))[keep]
        avar = 0.5 * sums[keep] / counts[keep]
        edf = counts[keep]
        lo, hi = chi2_band(avar, edf)
        return AllanCurveData(tau_s=m / self.fs_hz, m=m, avar=avar, edf=edf,
                              n_terms=counts[keep], ci_low=np.sqrt(lo), ci_high=np.sqrt(hi))


class StreamingWelch:
    """Welch PSD accumulated over fixed-length segments, bounded memory.

    Args:
        fs_hz: sampling rate in Hz.
        nperseg: segment length in samples (frequency resolution ``fs_hz/nperseg``).
    """

    def __init__(self, fs_hz: float, nperseg: int = 4096) -> None:
        if not fs_hz > 0:
            raise ValueError(f"sampling rate must be positive, got {fs_hz}")
        self.fs_hz = float(fs_hz)
        self.nperseg = int(nperseg)
        self._pending = np.empty(0)
        self._sum: np.ndarray | None = None
        self._segments = 0

    def new_segment(self) -> None:
        """Drop the incomplete segment: the next sample is not contiguous."""
        self._pending = np.empty(0)

    def update(self, values: np.ndarray) -> None:
        """Add contiguous samples (channel units)."""
        y = np.asarray(values, dtype=np.float64).ravel()
        buf = np.concatenate((self._pending, y)) if self._pending.size else y
        n_full = buf.size // self.nperseg
        if n_full:
            segs = buf[: n_full * self.nperseg].reshape(n_full, self.nperseg)
            segs = segs[np.all(np.isfinite(segs), axis=1)]
            if len(segs):
                _, p = signal.periodogram(segs, fs=self.fs_hz, window="hann",
                                          detrend="constant", axis=-1)
                total = p.sum(axis=0)
                self._sum = total if self._sum is None else self._sum + total
                self._segments += len(segs)
        self._pending = buf[n_full * self.nperseg:].copy()

    @property
    def segments(self) -> int:
        return self._segments

    def estimate(self) -> PsdData | None:
        """The averaged PSD without DC, or ``None`` before the first complete segment."""
        if self._sum is None or self._segments == 0:
            return None
        f = np.fft.rfftfreq(self.nperseg, 1.0 / self.fs_hz)[1:]
        psd = self._sum[1:] / self._segments
        dof = np.full(psd.shape, 2.0 * self._segments)
        lo, hi = chi2_band(psd, dof)
        return PsdData(f_hz=f, psd=psd, dof=dof, ci_low=lo, ci_high=hi)
