"""Light-weight streaming Allan variance for live monitoring.

:class:`OctaveAllan` is the non-overlapping Allan variance at octave cluster sizes
m = 1, 2, 4, ..., computed with a pyramid of pairwise cluster averages: O(1) memory per octave
whatever the record length, O(n) work, block-size invariant, and no cluster ever spans a gap
(``new_segment()``). Curves come with 95 % chi-square bands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats


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
        """Allan variance at every octave with at least ``min_terms`` differences (octaves
        where the signal did not change at all are left out: no log-scale value exists)."""
        counts = np.array([o.count for o in self._octaves], dtype=np.float64)
        sums = np.array([o.sumsq for o in self._octaves], dtype=np.float64)
        keep = (counts >= min_terms) & (sums > 0)  # a constant signal has nothing to show
        m = (2 ** np.arange(len(self._octaves), dtype=np.float64))[keep]
        avar = 0.5 * sums[keep] / counts[keep]
        edf = counts[keep]
        lo, hi = chi2_band(avar, edf)
        return AllanCurveData(tau_s=m / self.fs_hz, m=m, avar=avar, edf=edf,
                              n_terms=counts[keep], ci_low=np.sqrt(lo), ci_high=np.sqrt(hi))
