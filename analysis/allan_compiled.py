"""The compiled one-pass kernels of :mod:`imunoise.analysis.allan_kernels` (numba).

Imported only when a record is long enough for them to pay (``allan_kernels.enabled``): the
import of numba and the load of the cached machine code cost about 0.6 s per process, more
than the kernels save on the curves of a short record. Without numba the functions below stay
plain Python (``_jit`` is then the identity) and ``NUMBA_ERROR`` says why; they are not used
then.
"""

from __future__ import annotations

import numpy as np

#: Terms per block of the blocked summation (a multiple of 8).
_BLOCK = 1024
#: Start indices per chunk of a multi-m sweep (a multiple of ``_BLOCK``): the phase windows
#: of one chunk for a group of nearby m stay within the L2 cache.
_CHUNK = 16 * _BLOCK
#: Most averaging factors summed in one sweep.
GROUP_MAX = 16

try:  # numba is a declared dependency; the numpy path covers an environment without it
    from numba import njit

    NUMBA_ERROR = ""
except Exception as exc:  # noqa: BLE001 - numba fails to import in many ways; numpy then
    njit = None
    NUMBA_ERROR = f"numba unavailable: {exc}"


def _identity(fn):
    return fn


_jit = _identity if njit is None else njit(cache=True, fastmath=False, nogil=True)


@_jit
def _add_compensated(total: float, comp: float, x: float) -> tuple[float, float]:
    """Neumaier step: ``total + comp`` tracks the exact running sum."""
    t = total + x
    if abs(total) >= abs(x):
        comp += (total - t) + x
    else:
        comp += (x - t) + total
    return t, comp


@_jit
def _tree_sum(buf: np.ndarray, n: int) -> float:
    """Pairwise sum of ``buf[:n]`` (``buf`` of ``_BLOCK`` elements, destroyed): the tail is
    zeroed, then halves are added elementwise down to eight partial sums. Each level is a
    plain vector loop, which the compiler turns into SIMD code without any reassociation."""
    for q in range(n, buf.size):
        buf[q] = 0.0
    w = buf.size // 2
    while w >= 8:
        low = buf[:w]
        high = buf[w : 2 * w]
        for q in range(w):
            low[q] += high[q]
        w //= 2
    return ((buf[0] + buf[4]) + (buf[2] + buf[6])) + ((buf[1] + buf[5]) + (buf[3] + buf[7]))


@_jit
def _sq2_block(y0, y1, y2, buf) -> float:
    """Sum of ((y2 - 2 y1) + y0)^2 over a block (arrays of at most ``_BLOCK`` elements)."""
    n = y0.size
    for q in range(n):
        d = (y2[q] + y0[q]) - 2.0 * y1[q]
        buf[q] = d * d
    return _tree_sum(buf, n)


@_jit
def _sq3_block(y0, y1, y2, y3, buf) -> float:
    """Sum of ((y3 - y0) + 3 (y1 - y2))^2 over a block."""
    n = y0.size
    for q in range(n):
        d = (y3[q] - y0[q]) + 3.0 * (y1[q] - y2[q])
        buf[q] = d * d
    return _tree_sum(buf, n)


@_jit
def _sweep2(u: np.ndarray, ms: np.ndarray, stops: np.ndarray, start: int) -> np.ndarray:
    """Second-difference sums for several m in one sweep over ``u``.

    The start indices are visited in chunks of ``_CHUNK``; within a chunk every m of the group
    is summed before moving on, so the phase read for the first m is still in the cache for
    the next ones (the group's m should lie within about ``_CHUNK`` of each other). Block
    boundaries are those of a single-m sweep from ``start``, so the result does not depend on
    the grouping.
    """
    total = np.zeros(ms.size)
    comp = np.zeros(ms.size)
    buf = np.empty(_BLOCK)
    for c0 in range(start, max(start, stops.max()), _CHUNK):
        for t in range(ms.size):
            m = ms[t]
            c1 = min(c0 + _CHUNK, stops[t])
            for a in range(c0, c1, _BLOCK):
                e = min(c1, a + _BLOCK)
                s = _sq2_block(u[a:e], u[a + m : e + m], u[a + 2 * m : e + 2 * m], buf)
                total[t], comp[t] = _add_compensated(total[t], comp[t], s)
    return total + comp


@_jit
def _sweep3(u: np.ndarray, ms: np.ndarray, stops: np.ndarray, start: int) -> np.ndarray:
    """Third-difference sums for several m in one sweep over ``u`` (as ``_sweep2``)."""
    total = np.zeros(ms.size)
    comp = np.zeros(ms.size)
    buf = np.empty(_BLOCK)
    for c0 in range(start, max(start, stops.max()), _CHUNK):
        for t in range(ms.size):
            m = ms[t]
            c1 = min(c0 + _CHUNK, stops[t])
            for a in range(c0, c1, _BLOCK):
                e = min(c1, a + _BLOCK)
                y0 = u[a:e]
                y1 = u[a + m : e + m]
                y2 = u[a + 2 * m : e + 2 * m]
                s = _sq3_block(y0, y1, y2, u[a + 3 * m : e + 3 * m], buf)
                total[t], comp[t] = _add_compensated(total[t], comp[t], s)
    return total + comp


@_jit
def oadev_sums(u: np.ndarray, ms: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """For each m in ``ms`` (int64), the sum over i in [0, stops[j]) of
    (u[i+2m] - 2u[i+m] + u[i])^2, in one sweep over ``u`` (units of u squared)."""
    return _sweep2(u, ms, stops, 0)


@_jit
def ohdev_sums(u: np.ndarray, ms: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """As ``oadev_sums`` for (u[i+3m] - 3u[i+2m] + 3u[i+m] - u[i])^2."""
    return _sweep3(u, ms, stops, 0)


@_jit
def oadev_sum(u: np.ndarray, m: int, start: int, stop: int) -> float:
    """Sum over i in [start, stop) of (u[i+2m] - 2u[i+m] + u[i])^2 (units of u squared)."""
    ms = np.full(1, m, dtype=np.int64)
    stops = np.full(1, stop, dtype=np.int64)
    return _sweep2(u, ms, stops, start)[0]


@_jit
def ohdev_sum(u: np.ndarray, m: int, start: int, stop: int) -> float:
    """Sum over i in [start, stop) of (u[i+3m] - 3u[i+2m] + 3u[i+m] - u[i])^2."""
    ms = np.full(1, m, dtype=np.int64)
    stops = np.full(1, stop, dtype=np.int64)
    return _sweep3(u, ms, stops, start)[0]


@_jit
def _mdev_block(h0, h1, h2, h3, l0, l1, l2, l3, buf) -> float:
    n = h0.size
    for q in range(n):
        d = ((h3[q] - h0[q]) + 3.0 * (h1[q] - h2[q])) + ((l3[q] - l0[q]) + 3.0 * (l1[q] - l2[q]))
        buf[q] = d * d
    return _tree_sum(buf, n)


@_jit
def mdev_sum(hi: np.ndarray, lo: np.ndarray, m: int) -> float:
    """Modified Allan sum from the prefix sum U = hi + lo: sum over its N - 3m + 1 start
    indices of the squared third difference of U at spacing m."""
    n = hi.size - 3 * m
    total = 0.0
    comp = 0.0
    buf = np.empty(_BLOCK)
    for a in range(0, n, _BLOCK):
        e = min(n, a + _BLOCK)
        s = _mdev_block(
            hi[a:e],
            hi[a + m : e + m],
            hi[a + 2 * m : e + 2 * m],
            hi[a + 3 * m : e + 3 * m],
            lo[a:e],
            lo[a + m : e + m],
            lo[a + 2 * m : e + 2 * m],
            lo[a + 3 * m : e + 3 * m],
            buf,
        )
        total, comp = _add_compensated(total, comp, s)
    return total + comp


@_jit
def running_sum_split(u: np.ndarray, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """Prefix sums ``U[0] = 0``, ``U[k] = sum(v[:k])`` of ``v = u - offset`` (each difference
    rounded to float64, as numpy's) as a float64 pair ``hi + lo``, the sum
    carried in double-double arithmetic (error-free addition, then renormalised): ``hi`` is
    the sum rounded to float64 and ``lo`` the rest, accurate to about 2^-100 of the sum, so
    differences of ``U`` over m points keep full float64 precision however large U grows."""
    n = u.size
    hi = np.empty(n + 1)
    lo = np.empty(n + 1)
    hi[0] = 0.0
    lo[0] = 0.0
    s = 0.0
    c = 0.0
    for k in range(n):
        x = u[k] - offset
        t = s + x
        bp = t - s
        e = (s - (t - bp)) + (x - bp)
        c += e
        s = t + c
        c = c - (s - t)
        hi[k + 1] = s
        lo[k + 1] = c
    return hi, lo


@_jit
def diff_products(v: np.ndarray) -> tuple[float, float, float]:
    """For ``z = diff(v)`` (``v`` may be a strided view): ``(z.z, z[:-1].z[1:], sum(v[1:]))``.
    Blocks of ``_BLOCK`` terms are summed in order, the block totals Neumaier-compensated."""
    n = v.size - 1
    zz = 0.0
    zc = 0.0
    pp = 0.0
    pc = 0.0
    ss = 0.0
    sc = 0.0
    prev = 0.0
    for a in range(0, n, _BLOCK):
        e = min(n, a + _BLOCK)
        bz = 0.0
        bp = 0.0
        bs = 0.0
        for q in range(a, e):
            x1 = v[q + 1]
            z = x1 - v[q]
            bz += z * z
            if q > 0:
                bp += prev * z
            bs += x1
            prev = z
        zz, zc = _add_compensated(zz, zc, bz)
        pp, pc = _add_compensated(pp, pc, bp)
        ss, sc = _add_compensated(ss, sc, bs)
    return zz + zc, pp + pc, ss + sc


def groups(ms: np.ndarray, stops: np.ndarray) -> list[np.ndarray]:
    """Indices of ``ms`` (with terms) in sweeps of at most ``GROUP_MAX`` m each, in increasing
    m. Up to ``_CHUNK`` the largest m of a sweep exceeds its smallest by at most ``_CHUNK``: all
    three phase windows of its m then overlap in the cache. Beyond, the windows of different m
    never overlap, but the first is common to every m of a sweep: sharing it instead of
    reading it once per m took the 38 m above ``_CHUNK`` of a 1e7-sample curve from 290 ms to
    175 ms. The sums do not depend on the grouping."""
    order = np.argsort(ms, kind="stable")
    order = order[stops[order] > 0]
    out: list[np.ndarray] = []
    first = 0
    for k in range(1, order.size + 1):
        if (
            k == order.size
            or k - first >= GROUP_MAX
            or (ms[order[first]] <= _CHUNK and ms[order[k]] - ms[order[first]] > _CHUNK)
        ):
            out.append(order[first:k])
            first = k
    return out
