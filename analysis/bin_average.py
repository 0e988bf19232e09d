"""Averages of the Allan filter's oscillating factor over frequency bins.

Integrals over frequency of ``S(f) |H_m(f)|^2`` (the Allan variance, its covariance, the
effect of an output filter) run on a grid in ``u = f/fs``. The factor ``sin^4(pi u m)`` of the
Allan filter oscillates faster than any affordable grid at large ``m``; over a bin where it
does, it is replaced by its exact average, from ``sin^4 x = 3/8 - cos(2x)/2 + cos(4x)/8``.
"""

from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

SIN4 = (3.0 / 8.0, -0.5, 1.0 / 8.0)
"""Fourier coefficients of sin^4 x on 1, cos 2x, cos 4x."""


def bin_avg_cos(nu: float, ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Average of ``cos(pi nu u)`` over each bin ``[ua, ub]`` (``nu`` may be 0)."""
    if nu == 0:
        return np.ones_like(ua)
    x = np.pi * nu
    return (np.sin(x * ub) - np.sin(x * ua)) / (x * (ub - ua))


def sin4_table(m: np.ndarray, um: np.ndarray, ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """``sin^4(pi u m)`` for a column of averaging factors ``m`` (shape ``(k, 1)``): a
    ``(k, bins)`` table, its exact bin average where ``m`` times the bin width exceeds 0.05,
    its mid-point value elsewhere."""
    out = np.sin(np.pi * um * m) ** 4
    fast = (ub - ua) * m > 0.05
    if np.any(fast):
        mf = np.broadcast_to(m, out.shape)[fast]
        a = np.broadcast_to(ua, out.shape)[fast]
        b = np.broadcast_to(ub, out.shape)[fast]
        x2, x4 = 2.0 * np.pi * mf, 4.0 * np.pi * mf
        w = b - a
        out[fast] = (SIN4[0] + SIN4[1] * (np.sin(x2 * b) - np.sin(x2 * a)) / (x2 * w)
                     + SIN4[2] * (np.sin(x4 * b) - np.sin(x4 * a)) / (x4 * w))
    return out


_TABLES: OrderedDict[tuple, np.ndarray] = OrderedDict()
_TABLES_SIZE = 16
_TABLES_LOCK = threading.Lock()


def sin4_table_shared(m: np.ndarray, um: np.ndarray, ua: np.ndarray, ub: np.ndarray,
                      bins_key: tuple | None = None) -> np.ndarray:
    """:func:`sin4_table`, remembered by the values of ``m``, ``ua`` and ``ub`` (``um`` is
    their mid-point): a fit that moves a filter's parameters rebuilds the same frequency grid
    again and again. ``bins_key`` names the bins where the caller has a name for them (their
    bytes are then not hashed on every call). The table returned is read-only."""
    m_key = np.ascontiguousarray(m, dtype=np.float64).tobytes()
    key = (m_key, "bins", bins_key) if bins_key is not None else \
        (m_key, np.ascontiguousarray(ua).tobytes(), np.ascontiguousarray(ub).tobytes())
    with _TABLES_LOCK:
        hit = _TABLES.get(key)
        if hit is not None:
            _TABLES.move_to_end(key)
            return hit
    table = sin4_table(m, um, ua, ub)
    table.setflags(write=False)
    with _TABLES_LOCK:
        _TABLES[key] = table
        while len(_TABLES) > _TABLES_SIZE:
            _TABLES.popitem(last=False)
    return table
