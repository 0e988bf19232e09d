"""Streaming overlapping Allan (and Hadamard) deviation with bounded memory.

``StreamingAllan`` is fed blocks of rate samples of any size and returns, at any moment, the
curve of everything fed so far, with chi-square confidence intervals.

Exact and strided parts
-----------------------
* ``m <= m0`` (default 4096): **exact**. Every start index is used, as in the batch
  estimator. The accumulator keeps the last ``span * m0`` samples of the current segment
  (span = 2 for OADEV, 3 for OHDEV); each new sample completes one term per averaging factor,
  whose square is added to a running sum. The result equals ``imunoise.analysis.allan`` on the same
  data to about 1e-12 relative.
* ``m > m0``: **strided**. The phase (running sum of the rate) of the current segment is kept
  at every ``d``-th sample, ``d`` a power of two. When that history holds ``history_points``
  values, every other one is dropped and ``d`` doubles, so its size never exceeds
  ``history_points`` however long the record. The curve uses the terms starting at every
  ``d``-th index: each term is exact, only fewer of them are averaged, and with ``d`` much
  smaller than ``m`` they carry nearly all the information of the full set. The averaging
  factor is rounded to a multiple of ``d`` (the reported ``m`` is the one used; with the
  default grid and settings no rounding happens below about 2e8 samples).
  ``n_terms`` reports the number of terms of the full overlapping estimate: the strided mean
  of a segment is weighted by that count when segments are pooled, as the batch estimator
  weights them; ``edf`` is likewise that of the full estimate, which the strided one
  approximates.

Gaps: ``new_segment()`` closes the current segment. Nothing spans a gap: exact sums simply
continue with a fresh tail, and the strided sums of the closed segment are frozen at that
moment and pooled with the others (sum and count).

Noise identification (lag-1 ACF, as the batch estimator) uses bounded state only: for
``m <= noise_window / 30`` the last ``noise_window`` samples, and beyond that the strided
phase history (averages over ``m`` are phase differences over ``m``), both of the longest
segment (as the batch estimator; a copy is kept when a segment longer than the current one
closes). Where neither has 30 averages the alpha of the next shorter tau is used.

Memory: ``8 * (2 * (noise_window + history_points) + flush_samples)`` bytes plus a few kB of
sums, about 6.8 MB with the defaults, independent of the record length (``state_nbytes``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imunoise.analysis.allan import (
    KINDS,
    OVERLAP_KERNELS,
    AllanCurve,
    alpha_range,
    default_max_m,
    edf_for,
    normalise,
    segment_sums,
)
from imunoise.analysis.blas import single_thread_blas
from imunoise.analysis.edf import (
    LAG1_MIN_POINTS,
    chi2_interval,
    noise_id_b1_rn,
    noise_id_lag1_series,
)

STREAMING_KINDS = tuple(OVERLAP_KERNELS)


def default_streaming_grid(max_m: int = 1 << 40) -> np.ndarray:
    """Averaging factors 1..7, then 4 per octave: {4, 5, 6, 7} x 2^j (int64, up to max_m).

    Every value above 7 is a multiple of a power of two no smaller than a quarter of it,
    which keeps the strided part exact in m as the history stride grows.
    """
    grid = [1, 2, 3, 4, 5, 6, 7]
    j = 1
    while 4 << j <= max_m:
        grid.extend(k << j for k in (4, 5, 6, 7))
        j += 1
    arr = np.array(grid, dtype=np.int64)
    return arr[arr <= max_m]


@dataclass(frozen=True)
class _NoiseState:
    """What noise identification reads of one segment: its last samples (rate units), its
    strided phase history (None before any sample), the history's stride and the segment's
    length in samples."""

    recent: np.ndarray
    hist: np.ndarray | None
    stride: int
    seg_n: int


class StreamingAllan:
    """Bounded-memory overlapping Allan/Hadamard accumulator for one channel.

    Args:
        fs_hz: sampling rate, Hz.
        kinds: deviations to accumulate, any of ``"oadev"`` and ``"ohdev"``.
        m0: largest averaging factor computed exactly (every start index).
        m_grid: averaging factors reported (default ``default_streaming_grid``).
        max_m: drop grid values above this.
        history_points: capacity of the strided phase history (values).
        noise_window: recent samples kept for noise identification (>= span * m0).
        flush_samples: samples buffered before the exact sums are brought up to date
            (``curve()`` always flushes first).
    """

    def __init__(
        self,
        fs_hz: float,
        kinds: Sequence[str] = ("oadev",),
        m0: int = 4096,
        m_grid: Sequence[int] | np.ndarray | None = None,
        max_m: int | None = None,
        history_points: int = 1 << 18,
        noise_window: int = 1 << 17,
        flush_samples: int = 1 << 16,
    ) -> None:
        if not (np.isfinite(fs_hz) and fs_hz > 0):
            raise ValueError(f"sampling rate must be a positive number, got {fs_hz}")
        for k in kinds:
            if k not in STREAMING_KINDS:
                raise ValueError(f"streaming supports {list(STREAMING_KINDS)}, not {k!r}")
        if m0 < 1 or history_points < 16 or flush_samples < 1:
            raise ValueError("m0, history_points and flush_samples must be positive")
        self.fs_hz = float(fs_hz)
        self.kinds = tuple(kinds)
        self.m0 = int(m0)
        grid = default_streaming_grid() if m_grid is None else np.asarray(m_grid, dtype=np.int64)
        grid = np.unique(grid)
        if grid.size and grid[0] < 1:
            raise ValueError("averaging factors must be >= 1")
        if max_m is not None:
            grid = grid[grid <= max_m]
        self.m_grid = grid
        self._span = max(KINDS[k].span for k in self.kinds)
        self.history_points = int(history_points)
        self.noise_window = max(int(noise_window), self._span * self.m0)
        self.flush_samples = int(flush_samples)

        self._exact_m = grid[grid <= self.m0]
        self._long_m = grid[grid > self.m0]
        self._sum = {k: np.zeros(self._exact_m.size) for k in self.kinds}
        self._count = {k: np.zeros(self._exact_m.size, dtype=np.int64) for k in self.kinds}
        # strided sums of closed segments, per long m: sum, count
        self._closed_sum = {k: np.zeros(self._long_m.size) for k in self.kinds}
        self._closed_count = {k: np.zeros(self._long_m.size, dtype=np.int64) for k in self.kinds}
        self._closed_lengths: dict[int, int] = {}  # phase points -> number of closed segments

        self._offset: float | None = None  # rate subtracted before integrating
        self._n_total = 0
        self._pending: list[np.ndarray] = []
        self._pending_n = 0
        self._recent = np.zeros(self.noise_window)  # ring of recent samples, oldest first
        self._recent_n = 0  # valid samples at the end of _recent
        self._seg_n = 0  # samples flushed in the current segment
        self._base = np.longdouble(0.0)  # phase at the end of flushed samples (segment)
        self._hist = np.zeros(self.history_points)
        self._hist_n = 0
        self._stride = 1
        self._longest_closed: _NoiseState | None = None  # noise-id data, longest closed segment

    # ------------------------------------------------------------------ feeding

    @property
    def n_samples(self) -> int:
        """Samples fed so far, all segments."""
        return self._n_total

    @property
    def state_nbytes(self) -> int:
        """Bytes held by the accumulator's arrays (bounded, independent of record length)."""
        arrays = [self._recent, self._hist, self.m_grid, self._exact_m, self._long_m]
        for k in self.kinds:
            arrays += [self._sum[k], self._count[k], self._closed_sum[k], self._closed_count[k]]
        if self._longest_closed is not None:
            arrays.append(self._longest_closed.recent)
            if self._longest_closed.hist is not None:
                arrays.append(self._longest_closed.hist)
        pending = sum(a.nbytes for a in self._pending)
        return int(sum(a.nbytes for a in arrays) + pending + 16 * len(self._closed_lengths))

    @property
    def state_bound_nbytes(self) -> int:
        """Upper bound on ``state_nbytes`` (without closed-segment bookkeeping, 16 bytes per
        distinct closed-segment length): recent window and phase history (twice: the current
        segment's and the longest closed one's, for noise identification) + flush buffer +
        sums."""
        sums = 8 * (3 + 4 * len(self.kinds)) * self.m_grid.size
        return 8 * (2 * (self.noise_window + self.history_points) + self.flush_samples) + sums

    def update(self, block: np.ndarray) -> None:
        """Feed rate samples (1-D, finite; units of the channel). Any block size."""
        arr = np.asarray(block)
        if arr.ndim != 1:
            raise ValueError(f"block must be 1-D, got shape {arr.shape}")
        if arr.size == 0:
            return
        arr = arr.astype(np.float64, copy=False)
        if not np.all(np.isfinite(arr)):
            bad = int(np.flatnonzero(~np.isfinite(arr))[0])
            raise ValueError(f"block contains a non-finite value at index {bad}; not fed")
        if self._offset is None:
            self._offset = float(arr.mean())
        self._n_total += arr.size
        # big blocks are processed in flush-sized views, small ones buffered
        for a in range(0, arr.size, self.flush_samples):
            part = arr[a : a + self.flush_samples]
            self._pending.append(part.copy())  # the caller may reuse its buffer
            self._pending_n += part.size
            if self._pending_n >= self.flush_samples:
                self._flush()

    def new_segment(self) -> None:
        """A gap: the next sample starts a new contiguous segment."""
        self._flush()
        if self._seg_n == 0:
            return
        for k in self.kinds:
            s, c = self._strided_sums(k)
            self._closed_sum[k] += s
            self._closed_count[k] += c
        n_phase = self._seg_n + 1
        if self._longest_closed is None or self._seg_n > self._longest_closed.seg_n:
            now = self._noise_state()
            self._longest_closed = _NoiseState(now.recent.copy(), None if now.hist is None
                                               else now.hist.copy(), now.stride, now.seg_n)
        self._closed_lengths[n_phase] = self._closed_lengths.get(n_phase, 0) + 1
        self._seg_n = 0
        self._base = np.longdouble(0.0)
        self._hist_n = 0
        self._stride = 1

    def _flush(self) -> None:
        if not self._pending:
            return
        new = np.concatenate(self._pending) if len(self._pending) > 1 else self._pending[0]
        self._pending = []
        self._pending_n = 0
        off = self._offset if self._offset is not None else 0.0
        tail_n = min(self._seg_n, self._span * self.m0, self._recent_n)
        ext = np.empty(tail_n + new.size + 1)
        ext[0] = 0.0
        if tail_n:
            np.subtract(self._recent[-tail_n:], off, out=ext[1 : tail_n + 1])
        np.subtract(new, off, out=ext[tail_n + 1 :])
        np.cumsum(ext, out=ext)  # local phase, rate x samples units
        with single_thread_blas():
            for k in self.kinds:
                span = KINDS[k].span
                kernel = OVERLAP_KERNELS[k]
                for j, m in enumerate(self._exact_m):
                    m = int(m)
                    stop = ext.size - span * m
                    start = max(0, tail_n + 1 - span * m)
                    if stop > start:
                        self._sum[k][j] += kernel(ext, m, start, stop)
                        self._count[k][j] += stop - start
        self._append_history(ext, tail_n, new.size)
        self._remember(new)
        self._seg_n += new.size

    def _append_history(self, ext: np.ndarray, tail_n: int, n_new: int) -> None:
        """Store the segment phase at every stride-th sample of the new part."""
        # phase after sample j of the segment = base + (ext[tail_n + 1 + i] - ext[tail_n])
        local0 = ext[tail_n]
        first = self._seg_n  # segment index of the phase point before the new samples
        if first == 0:
            self._hist_put(np.array([0.0]))
        idx = np.arange(first + 1, first + n_new + 1)
        while True:
            sel = idx[idx % self._stride == 0]
            room = self.history_points - self._hist_n
            if sel.size <= room:
                break
            # decimate: keep every other stored value, double the stride
            kept = self._hist[: self._hist_n : 2].copy()
            self._hist_n = kept.size
            self._hist[: kept.size] = kept
            self._stride *= 2
        if sel.size:
            local = ext[tail_n + (sel - first)] - local0
            self._hist_put(np.asarray(self._base + local, dtype=np.float64))
        self._base += np.longdouble(ext[-1] - local0)

    def _hist_put(self, values: np.ndarray) -> None:
        self._hist[self._hist_n : self._hist_n + values.size] = values
        self._hist_n += values.size

    def _remember(self, new: np.ndarray) -> None:
        w = self.noise_window
        if new.size >= w:
            self._recent[:] = new[-w:]
        else:
            self._recent[:-new.size] = self._recent[new.size :]
            self._recent[-new.size :] = new
        self._recent_n = min(w, self._recent_n + new.size)

    # ------------------------------------------------------------------ results

    def _long_effective_m(self) -> np.ndarray:
        d = self._stride
        return np.maximum(d, np.round(self._long_m / d).astype(np.int64) * d)

    def _strided_sums(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """Sums over the current segment's phase history per long m, scaled to the number of
        terms the full overlapping estimate has there (returned as the count). Each strided
        term stands for ``stride`` of them, so that segments of different strides are pooled
        with the weights the batch estimator gives them (its own term counts)."""
        span = KINDS[kind].span
        kernel = OVERLAP_KERNELS[kind]
        h = self._hist[: self._hist_n]
        sums = np.zeros(self._long_m.size)
        counts = np.zeros(self._long_m.size, dtype=np.int64)
        n_phase = self._seg_n + 1
        with single_thread_blas():
            for j, m in enumerate(self._long_effective_m()):
                s = int(m) // self._stride
                stop = h.size - span * s
                full = n_phase - span * int(m)
                if stop > 0 and full > 0:
                    sums[j] = kernel(h, s, 0, stop) * (full / stop)
                    counts[j] = full
        return sums, counts

    def curve(
        self, kind: str = "oadev", ci: float = 0.683, max_m: int | None = None
    ) -> AllanCurve:
        """The curve of everything fed so far.

        Args:
            kind: one of the accumulated kinds.
            ci: two-sided confidence level.
            max_m: largest m reported; default as the batch estimator
                (``default_max_m`` of the longest segment).
        """
        if kind not in self.kinds:
            raise ValueError(f"{kind!r} is not accumulated; this accumulator has {self.kinds}")
        self._flush()
        cur_s, cur_c = self._strided_sums(kind)
        long_sum = self._closed_sum[kind] + cur_s
        long_count = self._closed_count[kind] + cur_c
        long_m = self._long_effective_m() if self._seg_n else self._long_m
        ms = np.concatenate((self._exact_m, long_m))
        sums = np.concatenate((self._sum[kind], long_sum))
        counts = np.concatenate((self._count[kind], long_count))

        seg_points = self._segment_points()
        longest = max(seg_points, default=0)
        if max_m is None:
            max_m = default_max_m(longest, kind)
        keep = (counts > 0) & (ms <= max_m)
        ms, sums, counts = ms[keep], sums[keep], counts[keep]
        dev = np.sqrt(normalise(sums, counts, ms, kind))
        alpha = self._noise_alpha(ms, kind, counts)
        edf = edf_for(kind, alpha, ms, seg_points)
        lo, hi = chi2_interval(dev, edf, ci)
        return AllanCurve(
            kind=kind,
            fs_hz=self.fs_hz,
            tau_s=ms / self.fs_hz,
            m=ms,
            dev=dev,
            n_terms=counts,
            edf=edf,
            alpha=alpha,
            ci_low=lo,
            ci_high=hi,
            ci=float(ci),
            exact_upto_m=self.m0,
        )

    def _segment_points(self) -> list[int]:
        points = []
        for n_phase, count in self._closed_lengths.items():
            points.extend([n_phase] * count)
        if self._seg_n:
            points.append(self._seg_n + 1)
        return points

    def _noise_state(self) -> _NoiseState:
        """The current segment's recent samples and phase history (views, not copies)."""
        n_recent = min(self._recent_n, self._seg_n) if self._seg_n else self._recent_n
        return _NoiseState(self._recent[self.noise_window - n_recent :],
                           self._hist[: self._hist_n] if self._seg_n else None,
                           self._stride, self._seg_n)

    def _noise_alpha(self, ms: np.ndarray, kind: str, n_terms: np.ndarray) -> np.ndarray:
        """Noise alpha per m from the longest segment's recent window and strided history (as
        the batch ``identify_noise`` looks at the longest segment): the lag-1 ACF where 30 or
        more averages exist, the B1 ratio and R(n) below that, at ``n_terms`` terms (R(n) comes
        from the strided history, which is enough to tell phase noise from rate noise)."""
        lo, hi = alpha_range(kind)
        dmax = KINDS[kind].d
        state = self._noise_state()
        if self._longest_closed is not None and self._longest_closed.seg_n > state.seg_n:
            state = self._longest_closed
        n_recent = state.recent.size
        recent = state.recent
        u_recent = np.concatenate(([0.0], np.cumsum(recent - recent.mean()))) if n_recent else None
        hist = state.hist
        if not state.seg_n:
            n_terms = None
        out = np.zeros(ms.size, dtype=np.int64)
        last: int | None = None
        with single_thread_blas():
            for j in np.argsort(ms, kind="stable"):
                m = int(ms[j])
                z, step = self._averages(m, u_recent, n_recent, hist, state.stride)
                res = noise_id_lag1_series(z, "freq", dmax) if z is not None else None
                found = res[0] if res is not None else None
                if found is None and z is not None and n_terms is not None:
                    found = noise_id_b1_rn(z, int(n_terms[j]), m,
                                           lambda h=hist, s=step: _strided_rn(h, s))
                if found is not None:
                    last = found
                out[j] = last if last is not None else 0
        return np.clip(out, lo, hi)

    @staticmethod
    def _averages(m: int, u_recent: np.ndarray | None, n_recent: int,
                  hist: np.ndarray | None, stride: int) -> tuple[np.ndarray | None, int]:
        """The m-sample averages of the rate from the recent window when it holds 30 of them,
        else from the strided history of ``stride`` samples per point (and the history step
        that spans m)."""
        if u_recent is not None and n_recent // m >= LAG1_MIN_POINTS:
            return np.diff(u_recent[::m]) / m, 0
        if hist is not None and m >= stride:
            step = max(1, round(m / stride))
            if (hist.size - 1) // step >= 3:
                return np.diff(hist[::step]) / (step * stride), step
        return None, 0


def _strided_rn(hist: np.ndarray | None, step: int) -> float:
    """MVAR / AVAR at ``step`` history points from the strided phase history."""
    if hist is None or step < 1 or hist.size <= 3 * step:
        return float("nan")
    m = np.array([step])
    mvar = normalise(*segment_sums(hist, m, "mdev"), m, "mdev")
    avar = normalise(*segment_sums(hist, m, "oadev"), m, "oadev")
    return float(mvar[0] / avar[0])
