"""Overlapping Allan variance of many equal-length records at once, for Monte Carlo tests.

Vectorised over records (rows) so that hundreds of seeds cost one cumulative sum. It checks the
simulators against their formulas; the product's estimator is analysis.allan.
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
