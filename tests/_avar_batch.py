"""Overlapping Allan variance of many equal-length records at once, for Monte Carlo tests.

Vectorised over records (rows) so that hundreds of seeds cost one cumulative sum. It checks the
simulators against their formulas; the product's estimator is imunoise.analysis.allan.
"""

import numpy as np


def oavar_rows(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    """OAVAR of each row of ``x`` at averaging lengths ``m`` (samples); shape (rows, len(m))."""
    x = np.atleast_2d(x)
    c = np.concatenate([np.zeros((x.shape[0], 1)), np.cumsum(x, axis=1)], axis=1)
    out = np.empty((x.shape[0], len(m)))
    for j, mm in enumerate(m):
        d = c[:, 2 * mm:] - 2.0 * c[:, mm:-mm] + c[:, : -2 * mm]
        out[:, j] = np.mean(d * d, axis=1) / (2.0 * mm * mm)
    return out


class Curve:
    """Minimal octave OAVAR curve (the fields the fit reads) of one gap-free record."""

    def __init__(self, x: np.ndarray, fs_hz: float, max_m: int | None = None) -> None:
        n = len(x)
        top = max_m or n // 4
        self.m = (2 ** np.arange(int(np.log2(top)) + 1)).astype(np.int64)
        self.fs_hz = float(fs_hz)
        self.tau_s = self.m / self.fs_hz
        self.dev = np.sqrt(oavar_rows(x, self.m)[0])
        self.n_terms = n - 2 * self.m + 1
