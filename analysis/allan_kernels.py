"""Compiled one-pass kernels for the overlapping Allan-family sums (numba), with a switch.

Each kernel reads the phase once per averaging factor m and accumulates the squared
differences without temporaries. Precision: eight independent float64 partial sums over
blocks of ``_BLOCK`` terms (eight-way blocked summation, the order BLAS dot products use),
each block total added to a Neumaier-compensated running sum. The error is then that of
summing about ``_BLOCK / 8`` terms, whatever the record length, and the result agrees with
the numpy path to about 1e-14 relative. ``fastmath`` stays off: no reassociation or
contraction beyond what is written here.

``enabled()`` says whether the compiled kernels are in use: numba must import, the kernels
must compile (``cache=True`` keeps the machine code on disk, so only the first run after
an install pays the compile time), and the switch must be on. ``set_enabled(False)`` or the
environment variable ``IMUNOISE_ALLAN_KERNEL=numpy`` selects the numpy path instead.
"""

from __future__ import annotations

import os
import time

import numpy as np

#: Terms per block of the blocked summation (a multiple of 8).
_BLOCK = 1024
#: Start indices per chunk of a multi-m sweep (a multiple of ``_BLOCK``): the phase windows
#: of one chunk for a group of nearby m stay within the L2 cache.
_CHUNK = 16 * _BLOCK
#: Most averaging factors summed in one sweep.
GROUP_MAX = 16

_state: dict[str, object] = {
    "switch": os.environ.get("IMUNOISE_ALLAN_KERNEL", "").strip().lower() != "numpy",
    "compiled": None,  # None: not tried yet; True/False after the first attempt
    "error": "",
    "compile_s": 0.0,
}

try:  # numba is a declared dependency; the numpy path covers an environment without it
    from numba import njit
except Exception as exc:  # pragma: no cover - exercised only without numba
    njit = None
    _state["compiled"] = False
    _state["error"] = f"numba unavailable: {exc}"


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
def _sq2_block(x0, x1, x2, a: int, e: int, acc) -> float:
    """Sum over q in [a, e) of ((x2[q] + x0[q]) - 2 x1[q])^2 in eight lanes (``acc``: scratch)."""
    nq = (e - a) // 8
    for lane in range(8):
        acc[lane] = 0.0
    for q in range(nq):
        base = a + 8 * q
        for lane in range(8):
            d = (x2[base + lane] + x0[base + lane]) - 2.0 * x1[base + lane]
            acc[lane] += d * d
    for q in range(a + 8 * nq, e):
        d = (x2[q] + x0[q]) - 2.0 * x1[q]
        acc[0] += d * d
    return ((acc[0] + acc[4]) + (acc[2] + acc[6])) + ((acc[1] + acc[5]) + (acc[3] + acc[7]))


@_jit
def _sq3_block(x0, x1, x2, x3, a: int, e: int, acc) -> float:
    """Sum over q in [a, e) of ((x3[q] - x0[q]) + 3 (x1[q] - x2[q]))^2 in eight lanes."""
    nq = (e - a) // 8
    for lane in range(8):
        acc[lane] = 0.0
    for q in range(nq):
        base = a + 8 * q
        for lane in range(8):
            i = base + lane
            d = (x3[i] - x0[i]) + 3.0 * (x1[i] - x2[i])
            acc[lane] += d * d
    for i in range(a + 8 * nq, e):
        d = (x3[i] - x0[i]) + 3.0 * (x1[i] - x2[i])
        acc[0] += d * d
    return ((acc[0] + acc[4]) + (acc[2] + acc[6])) + ((acc[1] + acc[5]) + (acc[3] + acc[7]))


@_jit
def _sums_grouped(u: np.ndarray, ms: np.ndarray, stops: np.ndarray, start: int, order: int):
    """Sums of squared differences of order 2 (oadev) or 3 (ohdev) for several m in one sweep.

    The start indices are visited in chunks of ``_CHUNK``; within a chunk every m of the group
    is summed before moving on, so the phase read for the first m is still in the cache for
    the next ones (the group's m should lie within about ``_CHUNK`` of each other). Block
    boundaries are those of a single-m sweep from ``start``, so the result does not depend on
    the grouping.
    """
    g = ms.size
    total = np.zeros(g)
    comp = np.zeros(g)
    acc = np.empty(8)
    kmax = start
    for t in range(g):
        kmax = max(kmax, stops[t])
    for c0 in range(start, kmax, _CHUNK):
        for t in range(g):
            c1 = min(c0 + _CHUNK, stops[t])
            if c1 <= c0:
                continue
            m = ms[t]
            n = c1 - c0
            x0 = u[c0:c1]
            x1 = u[c0 + m : c1 + m]
            x2 = u[c0 + 2 * m : c1 + 2 * m]
            if order == 2:
                for a in range(0, n, _BLOCK):
                    s = _sq2_block(x0, x1, x2, a, min(n, a + _BLOCK), acc)
                    total[t], comp[t] = _add_compensated(total[t], comp[t], s)
            else:
                x3 = u[c0 + 3 * m : c1 + 3 * m]
                for a in range(0, n, _BLOCK):
                    s = _sq3_block(x0, x1, x2, x3, a, min(n, a + _BLOCK), acc)
                    total[t], comp[t] = _add_compensated(total[t], comp[t], s)
    return total + comp


@_jit
def oadev_sums(u: np.ndarray, ms: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """For each m in ``ms`` (int64), the sum over i in [0, stops[j]) of
    (u[i+2m] - 2u[i+m] + u[i])^2, in one sweep over ``u`` (units of u squared)."""
    return _sums_grouped(u, ms, stops, 0, 2)


@_jit
def ohdev_sums(u: np.ndarray, ms: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """As ``oadev_sums`` for (u[i+3m] - 3u[i+2m] + 3u[i+m] - u[i])^2."""
    return _sums_grouped(u, ms, stops, 0, 3)


@_jit
def oadev_sum(u: np.ndarray, m: int, start: int, stop: int) -> float:
    """Sum over i in [start, stop) of (u[i+2m] - 2u[i+m] + u[i])^2 (units of u squared)."""
    total = 0.0
    comp = 0.0
    if stop <= start:
        return 0.0
    acc = np.empty(8)
    n = stop - start
    x0 = u[start:stop]
    x1 = u[start + m : stop + m]
    x2 = u[start + 2 * m : stop + 2 * m]
    for a in range(0, n, _BLOCK):
        s = _sq2_block(x0, x1, x2, a, min(n, a + _BLOCK), acc)
        total, comp = _add_compensated(total, comp, s)
    return total + comp


@_jit
def ohdev_sum(u: np.ndarray, m: int, start: int, stop: int) -> float:
    """Sum over i in [start, stop) of (u[i+3m] - 3u[i+2m] + 3u[i+m] - u[i])^2."""
    total = 0.0
    comp = 0.0
    if stop <= start:
        return 0.0
    acc = np.empty(8)
    n = stop - start
    x0 = u[start:stop]
    x1 = u[start + m : stop + m]
    x2 = u[start + 2 * m : stop + 2 * m]
    x3 = u[start + 3 * m : stop + 3 * m]
    for a in range(0, n, _BLOCK):
        s = _sq3_block(x0, x1, x2, x3, a, min(n, a + _BLOCK), acc)
        total, comp = _add_compensated(total, comp, s)
    return total + comp


@_jit
def mdev_sum(hi: np.ndarray, lo: np.ndarray, m: int) -> float:
    """Modified Allan sum from the prefix sum U = hi + lo: sum over its N - 3m + 1 start
    indices of the squared third difference of U at spacing m."""
    n = hi.size - 3 * m
    total = 0.0
    comp = 0.0
    if n <= 0:
        return 0.0
    h0 = hi[0:n]
    h1 = hi[m : m + n]
    h2 = hi[2 * m : 2 * m + n]
    h3 = hi[3 * m : 3 * m + n]
    l0 = lo[0:n]
    l1 = lo[m : m + n]
    l2 = lo[2 * m : 2 * m + n]
    l3 = lo[3 * m : 3 * m + n]
    acc = np.empty(8)
    for a in range(0, n, _BLOCK):
        e = min(n, a + _BLOCK)
        nq = (e - a) // 8
        for lane in range(8):
            acc[lane] = 0.0
        for q in range(nq):
            base = a + 8 * q
            for lane in range(8):
                i = base + lane
                d = ((h3[i] - h0[i]) + 3.0 * (h1[i] - h2[i])) + (
                    (l3[i] - l0[i]) + 3.0 * (l1[i] - l2[i])
                )
                acc[lane] += d * d
        for i in range(a + 8 * nq, e):
            d = ((h3[i] - h0[i]) + 3.0 * (h1[i] - h2[i])) + (
                (l3[i] - l0[i]) + 3.0 * (l1[i] - l2[i])
            )
            acc[0] += d * d
        s = ((acc[0] + acc[4]) + (acc[2] + acc[6])) + ((acc[1] + acc[5]) + (acc[3] + acc[7]))
        total, comp = _add_compensated(total, comp, s)
    return total + comp


def groups(ms: np.ndarray, stops: np.ndarray) -> list[np.ndarray]:
    """Indices of ``ms`` (with terms) in sweeps of at most ``GROUP_MAX`` nearby m each (the
    largest m of a sweep exceeds its smallest by at most ``_CHUNK``)."""
    order = np.argsort(ms, kind="stable")
    order = order[stops[order] > 0]
    out: list[np.ndarray] = []
    first = 0
    for k in range(1, order.size + 1):
        if (
            k == order.size
            or k - first >= GROUP_MAX
            or ms[order[k]] - ms[order[first]] > _CHUNK
        ):
            out.append(order[first:k])
            first = k
    return out


def _compile() -> None:
    """Compile (or load from the on-disk cache) every kernel once; record the time taken."""
    t0 = time.perf_counter()
    try:
        u = np.linspace(0.0, 1.0, 64)
        oadev_sum(u, 3, 0, u.size - 6)
        ohdev_sum(u, 3, 0, u.size - 9)
        ms = np.array([1, 3], dtype=np.int64)
        oadev_sums(u, ms, u.size - 2 * ms)
        ohdev_sums(u, ms, u.size - 3 * ms)
        mdev_sum(u, u, 3)
    except Exception as exc:  # any numba/LLVM failure: fall back to numpy, say why
        _state["compiled"] = False
        _state["error"] = f"compiled Allan kernels failed: {type(exc).__name__}: {exc}"
    else:
        _state["compiled"] = True
    _state["compile_s"] = time.perf_counter() - t0


def enabled() -> bool:
    """True when the compiled kernels are switched on and work (compiles on first call)."""
    if not _state["switch"]:
        return False
    if _state["compiled"] is None:
        _compile()
    return bool(_state["compiled"])


def set_enabled(flag: bool) -> bool:
    """Switch the compiled kernels on or off for this process; returns the previous setting."""
    previous = bool(_state["switch"])
    _state["switch"] = bool(flag)
    return previous


def status() -> dict[str, object]:
    """``enabled``, ``error`` (why not, if not) and ``compile_s`` (first-use compile or cache
    load time, s) of the compiled kernels."""
    on = enabled()
    return {"enabled": on, "error": _state["error"], "compile_s": float(_state["compile_s"])}
