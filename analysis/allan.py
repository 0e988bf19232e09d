"""Allan-family deviations of evenly sampled rate data, with chi-square confidence intervals.

Conventions: the input is a rate signal ``y`` (gyro rad/s, accelerometer m/s^2) sampled at
``fs_hz``; in time-and-frequency terms it is the "fractional frequency" and its running
integral the "phase". Internally the phase is kept in units of rate x samples,
``u[k] = sum(y[:k] - mean(y))`` (k = 0..n), so every deviation comes out directly in the
units of the rate. Removing the mean rate changes no difference of order >= 1 but keeps the
cumulative sum small, which preserves precision on long records.

Estimators (N = n + 1 phase points per contiguous segment, m = averaging factor):

* ``oadev``  overlapping Allan: sum over all i of (u[i+2m] - 2u[i+m] + u[i])^2 / (2 m^2),
  N - 2m terms.
* ``adev``   non-overlapping Allan: the same at i = 0, m, 2m, ..., floor((N-1)/m) - 1 terms.
* ``mdev``   modified Allan: second difference of m-sample sums of u, / (2 m^4), N - 3m + 1 terms.
* ``ohdev``  overlapping Hadamard: (u[i+3m] - 3u[i+2m] + 3u[i+m] - u[i])^2 / (6 m^2),
  N - 3m terms.

Segments (``segment_starts``) are processed on their own; squared differences are pooled
(sum and count) over segments and no difference ever spans a gap. Confidence intervals use
Greenhall's equivalent degrees of freedom (``imunoise.analysis.edf``), summed over segments, at the
noise type identified per tau by the lag-1 autocorrelation method unless ``alpha`` is given.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from imunoise.analysis import allan_kernels
from imunoise.analysis.blas import single_thread_blas
from imunoise.analysis.edf import (
    LAG1_MIN_POINTS,
    chi2_interval,
    greenhall_edf,
    noise_id_b1_rn,
    noise_id_lag1_phase,
)
from imunoise.core.series import SAMPLE_LIMIT
from imunoise.core.units import ONE_SIGMA_CI

#: Confidence level of a one-sigma interval, as printed by Stable32.


@dataclass(frozen=True)
class KindSpec:
    """How one deviation kind is estimated.

    Attributes:
        d: order of the phase difference (2 Allan, 3 Hadamard).
        overlapping: every start index (stride 1) rather than stride m.
        modified: the phase is averaged over m before differencing.
        span: phase points spanned by one term, in units of m (plus one point).
        norm: the variance is sum / (norm * m^2 * count) (mdev: / (norm * m^4 * count)).
    """

    d: int
    overlapping: bool
    modified: bool
    span: int
    norm: float


KINDS: dict[str, KindSpec] = {
    "oadev": KindSpec(d=2, overlapping=True, modified=False, span=2, norm=2.0),
    "adev": KindSpec(d=2, overlapping=False, modified=False, span=2, norm=2.0),
    "mdev": KindSpec(d=2, overlapping=True, modified=True, span=3, norm=2.0),
    "ohdev": KindSpec(d=3, overlapping=True, modified=False, span=3, norm=6.0),
}

# Start indices handled per step of the overlapping kernels: the working set (a few vectors
# of this length) stays in the L2 cache, which roughly halves the time on long records.
_CHUNK = 1 << 17


@dataclass(frozen=True)
class AllanCurve:
    """An Allan-family deviation curve with its confidence interval.

    Attributes:
        kind: ``"oadev"``, ``"adev"``, ``"mdev"`` or ``"ohdev"``.
        fs_hz: sampling rate of the rate data, Hz.
        tau_s: averaging time, s.
        m: averaging factor (int64), ``tau_s = m / fs_hz``.
        dev: deviation, in the units of the rate (e.g. rad/s).
        n_terms: number of squared differences summed at each tau, pooled over segments.
        edf: equivalent degrees of freedom of the estimate at each tau.
        alpha: power-law noise exponent (rate PSD ~ f^alpha) used for ``edf``.
        ci_low, ci_high: bounds on ``dev`` at two-sided confidence ``ci``.
        ci: confidence level, e.g. 0.683.
        exact_upto_m: largest m computed on every start index (batch: the largest m;
            streaming: its exact limit m0).
    """

    kind: str
    fs_hz: float
    tau_s: np.ndarray
    m: np.ndarray
    dev: np.ndarray
    n_terms: np.ndarray
    edf: np.ndarray
    alpha: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    ci: float
    exact_upto_m: int

    @property
    def avar(self) -> np.ndarray:
        """The variance (``dev`` squared), in rate units squared."""
        return self.dev**2

    def to_dict(self) -> dict:
        """Plain JSON-serialisable form (lists of floats)."""
        return {
            "kind": self.kind,
            "fs_hz": self.fs_hz,
            "tau_s": self.tau_s.tolist(),
            "m": self.m.tolist(),
            "dev": self.dev.tolist(),
            "n_terms": self.n_terms.tolist(),
            "edf": self.edf.tolist(),
            "alpha": self.alpha.tolist(),
            "ci_low": self.ci_low.tolist(),
            "ci_high": self.ci_high.tolist(),
            "ci": self.ci,
            "exact_upto_m": self.exact_upto_m,
        }


# ----------------------------------------------------------------------------- tau grids


def default_max_m(n_phase: int, kind: str = "oadev") -> int:
    """Largest averaging factor used by default, as Stable32 does for its tables.

    ``n_phase`` is the number of phase points (rate samples + 1). Overlapping estimators stop
    at ``(n_phase - 1) // 4``; the non-overlapping ADEV at ``(n_phase - 1) // 5`` so that at
    least four differences remain.
    """
    n = max(0, int(n_phase) - 1)
    return max(1, n // 5 if kind == "adev" else n // 4)


def tau_grid(
    n_samples: int,
    kind: str | int = "octave",
    max_m: int | None = None,
    dev_kind: str = "oadev",
) -> np.ndarray:
    """Averaging factors m (int64, increasing, unique).

    Args:
        n_samples: number of rate samples in the longest segment.
        kind: ``"octave"`` (1, 2, 4, ...), ``"decade"`` (1, 2, 4, 10, 20, 40, ... as
            Stable32), ``"all"`` (every m), or an int N for N log-spaced m from 1 to ``max_m``
            (rounded, duplicates removed, so fewer than N at short tau).
        max_m: largest m; default ``default_max_m(n_samples + 1, dev_kind)``.
        dev_kind: the deviation the grid is for (sets the default ``max_m``).
    """
    if max_m is None:
        max_m = default_max_m(int(n_samples) + 1, dev_kind)
    max_m = int(max_m)
    if max_m < 1:
        return np.zeros(0, dtype=np.int64)
    if isinstance(kind, (int, np.integer)) and not isinstance(kind, bool):
        if kind < 1:
            raise ValueError(f"number of log-spaced taus must be >= 1, got {kind}")
        grid = np.round(np.logspace(0.0, np.log10(max_m), int(kind)))
        return np.unique(grid.astype(np.int64))
    if kind == "octave":
        return (1 << np.arange(int(np.log2(max_m)) + 1)).astype(np.int64)
    if kind == "decade":
        decades = 10 ** np.arange(int(np.log10(max_m)) + 1, dtype=np.int64)
        grid = (decades[:, None] * np.array([1, 2, 4], dtype=np.int64)).ravel()
        return grid[grid <= max_m]
    if kind == "all":
        return np.arange(1, max_m + 1, dtype=np.int64)
    raise ValueError(f"unknown tau grid {kind!r}: use 'octave', 'decade', 'all' or an int")


# ----------------------------------------------------------------------------- kernels


def phase_from_rate(rate: np.ndarray) -> np.ndarray:
    """Phase in rate x samples units: ``u[0] = 0``, ``u[k] = sum(rate[:k] - mean(rate))``."""
    rate = np.asarray(rate, dtype=np.float64)
    u = np.empty(rate.size + 1, dtype=np.float64)
    u[0] = 0.0
    if rate.size:
        # in place in the output: no temporary the size of the record
        np.subtract(rate, rate.mean(), out=u[1:])
        np.cumsum(u[1:], out=u[1:])
    return u


def _oadev_sum(
    u: np.ndarray,
    m: int,
    start: int = 0,
    stop: int | None = None,
    u2: np.ndarray | None = None,
) -> float:
    """Sum of (u[i+2m] - 2u[i+m] + u[i])^2 over start indices i in [start, stop) (default: all
    i with i + 2m inside ``u``), in cache-sized chunks. ``u2`` may hold ``2 u`` precomputed
    (exact), which saves one pass per tau."""
    k = u.size - 2 * m if stop is None else stop
    buf = np.empty(min(_CHUNK, max(k - start, 1)))
    total = 0.0
    for a in range(start, k, _CHUNK):
        b = min(k, a + _CHUNK)
        v = buf[: b - a]
        np.add(u[a + 2 * m : b + 2 * m], u[a:b], out=v)
        if u2 is None:
            v -= u[a + m : b + m]
            v -= u[a + m : b + m]
        else:
            v -= u2[a + m : b + m]
        total += float(np.dot(v, v))
    return total


def _third_diff(x: np.ndarray, a: int, b: int, m: int, out: np.ndarray, tmp: np.ndarray) -> None:
    """out = x[i+3m] - 3 x[i+2m] + 3 x[i+m] - x[i] for i in [a, b)."""
    np.subtract(x[a + 3 * m : b + 3 * m], x[a:b], out=out)
    np.subtract(x[a + m : b + m], x[a + 2 * m : b + 2 * m], out=tmp)
    tmp *= 3.0
    out += tmp


def _ohdev_sum(u: np.ndarray, m: int, start: int = 0, stop: int | None = None) -> float:
    """Sum of (u[i+3m] - 3u[i+2m] + 3u[i+m] - u[i])^2 over i in [start, stop), in chunks."""
    k = u.size - 3 * m if stop is None else stop
    buf = np.empty(min(_CHUNK, max(k - start, 1)))
    tmp = np.empty_like(buf)
    total = 0.0
    for a in range(start, k, _CHUNK):
        b = min(k, a + _CHUNK)
        v = buf[: b - a]
        _third_diff(u, a, b, m, v, tmp[: b - a])
        total += float(np.dot(v, v))
    return total


def _oadev_sum_any(u: np.ndarray, m: int, start: int = 0, stop: int | None = None) -> float:
    """``_oadev_sum``, by the compiled kernel when ``allan_kernels.enabled("oadev")``."""
    k = u.size - 2 * m if stop is None else stop
    if allan_kernels.enabled("oadev"):
        return allan_kernels.oadev_sum(u, m, start, k) if k > start else 0.0
    return _oadev_sum(u, m, start, k)


def _ohdev_sum_any(u: np.ndarray, m: int, start: int = 0, stop: int | None = None) -> float:
    """``_ohdev_sum``, by the compiled kernel when ``allan_kernels.enabled("ohdev")``."""
    k = u.size - 3 * m if stop is None else stop
    if allan_kernels.enabled("ohdev"):
        return allan_kernels.ohdev_sum(u, m, start, k) if k > start else 0.0
    return _ohdev_sum(u, m, start, k)


#: Overlapping kernels by kind: ``f(u, m, start, stop)`` -> sum of squared differences
#: (compiled or numpy, as ``allan_kernels.enabled(kind)`` says).
OVERLAP_KERNELS = {"oadev": _oadev_sum_any, "ohdev": _ohdev_sum_any}


def _adev_sum(u: np.ndarray, m: int) -> tuple[float, int]:
    x = u[::m]
    if x.size < 3:
        return 0.0, 0
    v = x[2:] - 2.0 * x[1:-1] + x[:-2]
    return float(np.dot(v, v)), int(v.size)


def _running_sum_split(u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Prefix sums U (U[0] = 0, N + 1 points) of ``u`` as a float64 pair ``hi + lo``, summed in
    double-double by the compiled kernel (else in long double): differences of U over m points
    then keep full float64 precision even when U itself is large."""
    if allan_kernels.enabled("mdev", u.size):
        # the same sums carried in double-double: as exact, without the slow long double
        return allan_kernels.running_sum_split(u, float(u.mean()))
    uu = np.empty(u.size + 1, dtype=np.longdouble)
    uu[0] = 0.0
    np.cumsum(u - u.mean(), dtype=np.longdouble, out=uu[1:])
    hi = uu.astype(np.float64)
    lo = (uu - hi).astype(np.float64)
    return hi, lo


def _mdev_sum(hi: np.ndarray, lo: np.ndarray, m: int) -> float:
    """Modified Allan sum: the second difference of m-point phase sums is the third difference
    of the prefix sum U at spacing m; summed over its N - 3m + 1 start indices."""
    k = hi.size - 3 * m
    buf = np.empty(min(_CHUNK, max(k, 1)))
    tmp = np.empty_like(buf)
    low = np.empty_like(buf)
    total = 0.0
    for a in range(0, k, _CHUNK):
        b = min(k, a + _CHUNK)
        v = buf[: b - a]
        w = low[: b - a]
        _third_diff(hi, a, b, m, v, tmp[: b - a])
        _third_diff(lo, a, b, m, w, tmp[: b - a])
        v += w
        total += float(np.dot(v, v))
    return total


def segment_sums(
    u: np.ndarray, ms: np.ndarray, kind: str, workers: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalised sums of squared differences and their counts for one contiguous segment.

    Args:
        u: phase of the segment (rate x samples units), N points.
        ms: averaging factors.
        kind: one of ``KINDS``.
        workers: threads sharing the taus (numpy and the compiled kernels release the GIL).
    """
    spec = KINDS[kind]
    ms = np.asarray(ms, dtype=np.int64)
    n = u.size
    # Scale by an exact power of two so the numbers are of order one: very small values
    # (clock phase in seconds) are many times slower in the dot products and risk underflow.
    peak = max(float(u.max()), -float(u.min())) if n else 0.0  # max |u| without a copy
    if peak > 0.0 and not 2.0**-8 < peak < 2.0**8:
        e = -int(np.floor(np.log2(peak)))
        sums, counts = segment_sums(np.ldexp(u, e), ms, kind, workers)
        return np.ldexp(sums, -2 * e), counts
    compiled = allan_kernels.enabled(kind, n)
    if kind == "mdev":
        hi, lo = _running_sum_split(u)
        counts = np.maximum(n - 3 * ms + 1, 0).astype(np.int64)
        mdev_kernel = allan_kernels.mdev_sum if compiled else _mdev_sum
        sums = np.array(
            [mdev_kernel(hi, lo, int(k)) if c > 0 else 0.0 for k, c in zip(ms, counts, strict=True)]
        )
        return sums, counts
    if kind == "adev":
        pairs = [_adev_sum(u, int(m)) for m in ms]
        return (
            np.array([p[0] for p in pairs], dtype=np.float64),
            np.array([p[1] for p in pairs], dtype=np.int64),
        )
    counts = np.maximum(n - spec.span * ms, 0).astype(np.int64)
    if compiled:
        return _compiled_sums(u, ms, counts, kind, workers), counts
    if kind == "oadev":
        u2 = np.ldexp(u, 1)

        def kernel(j: int) -> float:
            return _oadev_sum(u, int(ms[j]), u2=u2)
    else:

        def kernel(j: int) -> float:
            return _ohdev_sum(u, int(ms[j]))

    todo = [j for j in range(ms.size) if counts[j] > 0]
    sums = np.zeros(ms.size)
    if workers > 1 and len(todo) > 1:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for j, s in zip(todo, pool.map(kernel, todo), strict=True):
                sums[j] = s
    else:
        for j in todo:
            sums[j] = kernel(j)
    return sums, counts


def _compiled_sums(
    u: np.ndarray, ms: np.ndarray, counts: np.ndarray, kind: str, workers: int
) -> np.ndarray:
    """Overlapping sums by the compiled kernels, nearby m sharing one sweep over ``u``."""
    sweep = allan_kernels.oadev_sums if kind == "oadev" else allan_kernels.ohdev_sums
    groups = allan_kernels.groups(ms, counts)
    sums = np.zeros(ms.size)

    def run(idx: np.ndarray) -> np.ndarray:
        return sweep(u, np.ascontiguousarray(ms[idx]), np.ascontiguousarray(counts[idx]))

    if workers > 1 and len(groups) > 1:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            for idx, s in zip(groups, pool.map(run, groups), strict=True):
                sums[idx] = s
    else:
        for idx in groups:
            sums[idx] = run(idx)
    return sums


def normalise(sums: np.ndarray, counts: np.ndarray, ms: np.ndarray, kind: str) -> np.ndarray:
    """Variance from pooled sums: rate units squared; ``nan`` where there is no term."""
    spec = KINDS[kind]
    ms = np.asarray(ms, dtype=np.float64)
    scale = spec.norm * ms**2 * (ms**2 if spec.modified else 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 0, sums / (scale * np.maximum(counts, 1)), np.nan)


# ----------------------------------------------------------------------------- public API


@lru_cache(maxsize=4096)
def _edf_cached(alpha: int, d: int, m: int, n: int, overlapping: bool, modified: bool) -> float:
    return greenhall_edf(alpha, d, m, n, overlapping, modified)


def edf_for(kind: str, alpha: np.ndarray, ms: np.ndarray, seg_phase_points: Sequence[int]):
    """Greenhall edf per tau, summed over independent segments (segments without a term add 0)."""
    spec = KINDS[kind]
    out = np.zeros(len(ms))
    for j, m in enumerate(ms):
        total = 0.0
        for n in seg_phase_points:
            if n - spec.span * int(m) < 1:
                continue
            e = _edf_cached(int(alpha[j]), spec.d, int(m), int(n), spec.overlapping, spec.modified)
            if np.isfinite(e):
                total += e
        out[j] = total if total > 0 else np.nan
    return out


def alpha_range(kind: str) -> tuple[int, int]:
    """Noise exponents for which the kind's edf is defined (alpha > 1 - 2d), capped at 2."""
    return (2 - 2 * KINDS[kind].d, 2)


def _validate(values: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ValueError(f"{what} must be a 1-D array, got shape {arr.shape}")
    if arr.dtype.kind not in "fiu":
        raise ValueError(f"{what} must be numeric, got dtype {arr.dtype}")
    arr = arr.astype(np.float64, copy=False)
    if not arr.size:
        return arr
    # the largest magnitude from two reductions, which propagate a NaN or an infinity: no
    # mask and no copy of the record (20 ms -> 5.5 ms on 1e7 samples, of a curve's 0.42 s)
    reach = max(float(arr.max()), -float(arr.min()))
    if reach <= SAMPLE_LIMIT:
        return arr
    if not np.all(np.isfinite(arr)):
        bad = int(np.flatnonzero(~np.isfinite(arr))[0])
        raise ValueError(f"{what} contains a non-finite value at index {bad}")
    if float(np.max(np.abs(arr))) > SAMPLE_LIMIT:  # the sums would overflow
        bad = int(np.flatnonzero(np.abs(arr) > SAMPLE_LIMIT)[0])
        raise ValueError(f"{what} has a value beyond {SAMPLE_LIMIT:g} at index {bad} "
                         f"({arr[bad]:.3g})")
    return arr


def _segments(n: int, segment_starts) -> list[tuple[int, int]]:
    if segment_starts is None:
        return [(0, n)] if n > 0 else []
    starts = np.asarray(segment_starts, dtype=np.int64).ravel()
    if starts.size and (np.any(np.diff(starts) < 0) or starts[0] < 0 or starts[-1] > n):
        raise ValueError("segment_starts must be increasing indices within the data")
    bounds = np.unique(np.concatenate(([0], starts, [n])))
    return [(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]


def _intervals(kind: str, dev: np.ndarray, ms: np.ndarray, counts: np.ndarray,
               seg_points: list[int], phases: list[np.ndarray], alpha_arr: np.ndarray | None,
               ci: float | None, var: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Noise type per tau, equivalent degrees of freedom and the deviation's ``ci``
    interval: ``(alpha, edf, ci_low, ci_high)``; without ``ci`` no noise identification and
    NaN intervals. ``var``: the variance at each m (pooled over the segments)."""
    if ci is None:
        nan = np.full(ms.size, np.nan)
        alpha = alpha_arr if alpha_arr is not None else np.zeros(ms.size, dtype=np.int64)
        return np.asarray(alpha, dtype=np.int64), nan, nan.copy(), nan.copy()
    if alpha_arr is None:
        if phases:
            u_long = phases[int(np.argmax(seg_points))]
            # one segment: its sums are the curve's, which the R(n) test can reuse
            known = (ms, var) if var is not None and kind == "oadev" and len(phases) == 1 \
                else None
            alpha_arr = identify_noise(u_long, ms, kind, n_terms=counts, oadev_var=known)
        else:
            alpha_arr = np.zeros(0, dtype=np.int64)
    lo, hi = alpha_range(kind)
    alpha_arr = np.clip(alpha_arr, lo, hi).astype(np.int64)
    edf = edf_for(kind, alpha_arr, ms, seg_points)
    ci_low, ci_high = chi2_interval(dev, edf, ci)
    return alpha_arr, edf, ci_low, ci_high


def allan(
    data: np.ndarray,
    fs_hz: float,
    kind: str = "oadev",
    m: str | int | Sequence[int] | np.ndarray = "octave",
    segment_starts: np.ndarray | Sequence[int] | None = None,
    ci: float | None = ONE_SIGMA_CI,
    alpha: int | Sequence[int] | np.ndarray | None = None,
    data_type: str = "freq",
    max_m: int | None = None,
    workers: int = 1,
) -> AllanCurve:
    """Allan-family deviation of evenly sampled data, with a chi-square confidence interval.

    Args:
        data: rate samples (``data_type="freq"``, e.g. rad/s) or phase samples
            (``"phase"``, e.g. rad; the rate is then its difference over ``1/fs_hz``).
        fs_hz: sampling rate, Hz (``1 / tau0``).
        kind: ``"oadev"``, ``"adev"``, ``"mdev"`` or ``"ohdev"``.
        m: a grid name or count for ``tau_grid``, or explicit averaging factors.
        segment_starts: indices where contiguous segments begin (as
            ``imunoise.core.series.ChannelSeries``); each is processed on its own.
        ci: two-sided confidence level of ``ci_low``/``ci_high``; ``None`` for the deviations
            only (no noise identification: ``edf``, ``ci_low``, ``ci_high`` and ``ci`` are
            nan, ``alpha`` is the given one or 0).
        alpha: noise exponent(s) for the edf: ``None`` identifies it per tau (lag-1 ACF on
            the longest segment), an int applies to every tau, an array gives one per tau.
        data_type: ``"freq"`` (rate) or ``"phase"``.
        max_m: largest m for a named grid (default ``default_max_m``).
        workers: threads used by the overlapping kernels.

    Returns:
        AllanCurve with only the taus that have at least one term.

    Raises:
        ValueError: bad kind, grid, data (non-finite, not 1-D) or rate.
    """
    if kind not in KINDS:
        raise ValueError(f"unknown deviation kind {kind!r}: use one of {sorted(KINDS)}")
    if data_type not in ("freq", "phase"):
        raise ValueError(f"data_type must be 'freq' or 'phase', got {data_type!r}")
    if not (np.isfinite(fs_hz) and fs_hz > 0):
        raise ValueError(f"sampling rate must be a positive number, got {fs_hz}")
    values = _validate(data, "data")
    segs = _segments(values.size, segment_starts)

    phases: list[np.ndarray] = []
    for a, b in segs:
        seg = values[a:b]
        if data_type == "freq":
            phases.append(phase_from_rate(seg))
        elif seg.size >= 2:
            # phase -> rate x samples units; a constant rate offset is removed exactly by
            # every difference, so subtract the end-to-end line to keep the numbers small
            u = (seg - seg[0]) * fs_hz
            u -= np.linspace(0.0, u[-1], u.size)
            phases.append(u)
    seg_points = [u.size for u in phases]
    longest = max(seg_points, default=0)

    if isinstance(m, str) or (isinstance(m, (int, np.integer)) and not isinstance(m, bool)):
        ms = tau_grid(longest - 1, m, max_m=max_m, dev_kind=kind)
    else:
        ms = np.asarray(m, dtype=np.int64).ravel()
        if ms.size and ms.min() < 1:
            raise ValueError("averaging factors must be >= 1")

    alpha_arr = None
    if alpha is not None:
        alpha_arr = np.broadcast_to(np.asarray(alpha, dtype=np.int64), ms.shape).copy()

    sums = np.zeros(ms.size)
    counts = np.zeros(ms.size, dtype=np.int64)
    with single_thread_blas():
        for u in phases:
            s, c = segment_sums(u, ms, kind, workers=workers)
            sums += s
            counts += c
    keep = counts > 0
    ms, sums, counts = ms[keep], sums[keep], counts[keep]
    if alpha_arr is not None:
        alpha_arr = alpha_arr[keep]
    var = normalise(sums, counts, ms, kind)
    dev = np.sqrt(var)

    alpha_arr, edf, ci_low, ci_high = _intervals(kind, dev, ms, counts, seg_points, phases,
                                                 alpha_arr, ci, var)
    return AllanCurve(
        kind=kind,
        fs_hz=float(fs_hz),
        tau_s=ms / float(fs_hz),
        m=ms,
        dev=dev,
        n_terms=counts,
        edf=edf,
        alpha=alpha_arr,
        ci_low=ci_low,
        ci_high=ci_high,
        ci=float("nan") if ci is None else float(ci),
        exact_upto_m=int(ms.max()) if ms.size else 0,
    )


def identify_noise(
    u: np.ndarray, ms: np.ndarray, kind: str, n_terms: np.ndarray | None = None,
    oadev_var: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Noise exponent alpha per m from one segment's phase ``u`` (rate x samples units).

    The series examined at each m is the m-sample averages of the rate,
    ``diff(u[::m]) / m``, for rate and phase input alike: this reproduces the noise types
    Stable32 prints for its phase data sets (decimating the phase instead disagrees with
    them at long tau). With at least ``LAG1_MIN_POINTS`` averages the lag-1 ACF decides
    (Hadamard allows one more differencing than Allan: dmax 3 instead of 2); with fewer, the
    B1 ratio and R(n) (``imunoise.analysis.edf.noise_id_b1_rn``), evaluated at ``n_terms``, the
    number
    of terms of the statistic at each m (default: those of ``kind`` on this one segment).
    ``oadev_var``: ``(m, variance)`` of the overlapping Allan variance of this segment where
    already known (R(n) then does not sum it again).
    """
    ms = np.asarray(ms, dtype=np.int64)
    if n_terms is None:
        n_terms = term_counts(u.size, ms, kind)
    lo, hi = alpha_range(kind)
    mdev_of = _MdevAt(u)
    known: dict[int, float] = {}
    if oadev_var is not None:
        known = {int(k): float(v) for k, v in zip(*oadev_var, strict=True)}
    with single_thread_blas():
        alpha = noise_id_lag1_phase(u, ms, "freq", dmax=KINDS[kind].d, alpha_range=(lo, hi))
        for j in np.flatnonzero((u.size - 1) // np.maximum(ms, 1) < LAG1_MIN_POINTS):
            m = int(ms[j])
            z = np.diff(u[::m]) / m

            def rn(m: int = m) -> float:
                mvar = normalise(*mdev_of(m), np.array([m]), "mdev")
                if m in known:
                    return float(mvar[0] / known[m])
                avar = normalise(*segment_sums(u, np.array([m]), "oadev"), np.array([m]), "oadev")
                return float(mvar[0] / avar[0])

            found = noise_id_b1_rn(z, int(n_terms[j]), m, rn)
            if found is not None:
                alpha[j] = min(max(found, lo), hi)
    return alpha


class _MdevAt:
    """``segment_sums(u, [m], "mdev")`` for one phase ``u`` at any m, the running sums it needs
    (a full pass over ``u``) formed once, on the first call."""

    def __init__(self, u: np.ndarray) -> None:
        self.u = u
        self.split: tuple[np.ndarray, np.ndarray, int] | None = None

    def __call__(self, m: int) -> tuple[np.ndarray, np.ndarray]:
        u = self.u
        n = u.size
        count = max(n - 3 * m + 1, 0)
        if count == 0:
            return np.zeros(1), np.zeros(1, dtype=np.int64)
        if self.split is None:
            # the power-of-two scaling of segment_sums, so that the sums are the same numbers
            peak = max(float(u.max()), -float(u.min()))
            e = -int(np.floor(np.log2(peak))) if peak > 0.0 and not 2.0**-8 < peak < 2.0**8 \
                else 0
            hi, lo = _running_sum_split(np.ldexp(u, e) if e else u)
            self.split = (hi, lo, e)
        hi, lo, e = self.split
        kernel = allan_kernels.mdev_sum if allan_kernels.enabled("mdev", n) else _mdev_sum
        total = np.array([kernel(hi, lo, int(m))])
        return (np.ldexp(total, -2 * e) if e else total), np.array([count], dtype=np.int64)


def term_counts(n_phase: int, ms: np.ndarray, kind: str) -> np.ndarray:
    """Number of terms of ``kind`` at each m on one segment of ``n_phase`` phase points."""
    ms = np.asarray(ms, dtype=np.int64)
    if kind == "adev":
        return np.maximum((n_phase - 1) // ms - 1, 0)
    if kind == "mdev":
        return np.maximum(n_phase - 3 * ms + 1, 0)
    return np.maximum(n_phase - KINDS[kind].span * ms, 0)


_M = str | int | Sequence[int] | np.ndarray
_SEGMENTS = np.ndarray | Sequence[int] | None
_ALPHA = int | Sequence[int] | np.ndarray | None


def oadev(rate: np.ndarray, fs_hz: float, m: _M = "octave", segment_starts: _SEGMENTS = None,
          ci: float | None = ONE_SIGMA_CI, alpha: _ALPHA = None, data_type: str = "freq",
          max_m: int | None = None, workers: int = 1) -> AllanCurve:
    """Overlapping Allan deviation of rate samples (units of the rate).

    With the phase x (the rate's running sum times tau0) and tau = m tau0,
    ``sigma^2(tau) = sum_{i=1}^{N-2m} (x_{i+2m} - 2 x_{i+m} + x_i)^2 / (2 tau^2 (N - 2m))``
    (NIST SP 1065, W. J. Riley 2008, eq. 14). Arguments as :func:`allan`.
    """
    return allan(rate, fs_hz, "oadev", m, segment_starts, ci, alpha, data_type, max_m, workers)


def adev(rate: np.ndarray, fs_hz: float, m: _M = "octave", segment_starts: _SEGMENTS = None,
         ci: float | None = ONE_SIGMA_CI, alpha: _ALPHA = None, data_type: str = "freq",
         max_m: int | None = None, workers: int = 1) -> AllanCurve:
    """Non-overlapping (normal) Allan deviation of rate samples (units of the rate).

    Over the M adjacent m-sample averages ybar_k,
    ``sigma^2(tau) = sum_{k=1}^{M-1} (ybar_{k+1} - ybar_k)^2 / (2 (M - 1))``
    (NIST SP 1065 eq. 6; D. W. Allan 1966). Arguments as :func:`allan`.
    """
    return allan(rate, fs_hz, "adev", m, segment_starts, ci, alpha, data_type, max_m, workers)


def mdev(rate: np.ndarray, fs_hz: float, m: _M = "octave", segment_starts: _SEGMENTS = None,
         ci: float | None = ONE_SIGMA_CI, alpha: _ALPHA = None, data_type: str = "freq",
         max_m: int | None = None, workers: int = 1) -> AllanCurve:
    """Modified Allan deviation of rate samples (units of the rate).

    ``Mod sigma^2(tau) = sum_{j=1}^{N-3m+1} (sum_{i=j}^{j+m-1} (x_{i+2m} - 2 x_{i+m} + x_i))^2
    / (2 m^2 tau^2 (N - 3m + 1))`` (NIST SP 1065 eq. 15; Allan and Barnes 1981). It separates
    white from flicker phase (angle) noise. Arguments as :func:`allan`.
    """
    return allan(rate, fs_hz, "mdev", m, segment_starts, ci, alpha, data_type, max_m, workers)


def ohdev(rate: np.ndarray, fs_hz: float, m: _M = "octave", segment_starts: _SEGMENTS = None,
          ci: float | None = ONE_SIGMA_CI, alpha: _ALPHA = None, data_type: str = "freq",
          max_m: int | None = None, workers: int = 1) -> AllanCurve:
    """Overlapping Hadamard deviation of rate samples (units of the rate).

    ``H sigma^2(tau) = sum_{i=1}^{N-3m} (x_{i+3m} - 3 x_{i+2m} + 3 x_{i+m} - x_i)^2
    / (6 tau^2 (N - 3m))`` (NIST SP 1065 eq. 18). A third difference: insensitive to a linear
    drift of the rate (a rate ramp). Arguments as :func:`allan`.
    """
    return allan(rate, fs_hz, "ohdev", m, segment_starts, ci, alpha, data_type, max_m, workers)
