"""What an output filter term is, and its exact effect on the Allan variance.

Most MEMS sensors average their samples before they leave the part: the ADIS16350/16405
``SENS_AVG`` Bartlett filter, the ITG-3200 digital low-pass, the ADXL345 bandwidth setting, a
phone's decimation. The filter pulls the Allan deviation at the shortest averaging times below
every sum of noise terms. A filter term (``kind == "filter"``) describes it by its impulse
response ``g`` (unit DC gain) at the sample rate: the PSD of every Gaussian noise term
(``role == "noise"``) is multiplied by ``|G(f)|^2``; deterministic terms pass unchanged.

Filtered Allan variance, exact where it matters:

* Terms whose sampled autocovariance ends after a few lags (white noise, quantization; see
  :meth:`Term.autocovariance`) are filtered in the time domain: the output autocovariance is
  ``R_out = R_in * r_g`` (``r_g`` the autocorrelation of ``g``) and the Allan variance of a
  stationary sequence with autocovariance ``R`` at ``m`` samples is
  ``[sum_{|k|<m} (m-|k|) R(k) - sum_{k=1}^{2m-1} (m-|k-m|) R(k)] / m^2``, which beyond the last
  lag ``K`` is ``(m sum_k R(k) - 3 sum_{k>0} k R(k)) / m^2``.
* The other noise terms (random walk, flicker, Markov) hold their power where ``|G|^2`` is 1
  to within ``(f L/fs)^2``; their filtered Allan variance is their own times the ratio
  ``I_G / I_1`` of ``I_G = (fs/2) int_0^{1/2} S(u fs) |G(u)|^2 4 sin^4(pi u m) /
  (m^2 sin^2(pi u)) du`` to the same integral without the filter, summed on a grid in
  ``u = f/fs`` with the ``sin^4`` factor bin-averaged where it oscillates faster than the
  grid (:mod:`imunoise.analysis.bin_average`). Where the term's own formula is exact the
  ratio adds exactly ``I_G - I_1``; where it is asymptotic (a flicker floor at one sample)
  the ratio stays positive. Its departure from 1 shrinks as ``(L/m)^2`` (``L`` the filter
  length); beyond ``m = 300 L`` it is below 1e-5 and left out. As ``0 <= |G|^2 <= 1`` the
  change is also smaller than the term's own Allan variance, and is left out where that is
  below 1e-4 of the model's.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from imunoise.analysis.bin_average import sin4_table_shared
from imunoise.analysis.terms.base import Term, TermError, TermSimulator

_CORRECTION_REACH = 300.0
"""Multiples of the filter length beyond which the non-white correction is left out."""
_CACHE_SIZE = 256
_NEGLIGIBLE = 1.0e-4
"""Relative size below which a term's filter correction is left out."""


def avar_from_autocovariance(r: np.ndarray, m: np.ndarray) -> np.ndarray:
    """Allan variance (units^2) at averaging factors ``m`` (samples, >= 1) of a stationary
    sequence with autocovariance ``r[k]``, ``k = 0..K`` (zero beyond ``K``).

    Exact for integer ``m``; a non-integer ``m`` above ``K`` uses the closed form, below it
    the nearest integer."""
    r = np.asarray(r, dtype=np.float64)
    m = np.atleast_1d(np.asarray(m, dtype=np.float64))
    k_last = len(r) - 1
    lags = np.arange(1, k_last + 1, dtype=np.float64)
    p0 = np.concatenate(([0.0], np.cumsum(r[1:])))          # sum_{k=1}^{n} r(k)
    p1 = np.concatenate(([0.0], np.cumsum(lags * r[1:])))   # sum_{k=1}^{n} k r(k)
    total = r[0] + 2.0 * p0[-1]
    out = (m * total - 3.0 * p1[-1]) / (m * m)
    near = m <= k_last
    if near.any():
        mi = np.maximum(np.rint(m[near]).astype(np.int64), 1)
        # the sums up to lags m - 1, m and 2m - 1, read at once (indices past the last lag
        # hold the full sums)
        idx = np.minimum(np.stack((mi - 1, mi, 2 * mi - 1)), k_last)
        q0, q1 = p0[idx], p1[idx]
        a = mi * r[0] + 2.0 * (mi * q0[0] - q1[0])
        b = q1[1] + 2.0 * mi * (q0[2] - q0[1]) - (q1[2] - q1[1])
        out[near] = (a - b) / (mi * mi).astype(np.float64)
    return out


@functools.lru_cache(maxsize=64)
def _bins(u_lo: float, n_lin: int) -> tuple[np.ndarray, ...]:
    """Bins ``(ua, ub, um, width, sin2)`` in ``u = f/fs`` from ``u_lo`` to 1/2: 60 log-spaced
    per decade joined with ``n_lin`` linear ones, with their widths and ``sin^2(pi um)``
    (read-only; a fit moving a filter's parameters asks for the same bins again and
    again)."""
    decades = math.log10(0.5 / u_lo)
    log_edges = np.geomspace(u_lo, 0.5, int(decades * 60) + 2)
    lin = np.linspace(0.0, 0.5, n_lin + 1)
    edges = np.unique(np.concatenate((log_edges, lin[lin > u_lo])))
    ua, ub = edges[:-1], edges[1:]
    um = 0.5 * (ua + ub)
    width = ub - ua
    sin2 = np.sin(np.pi * um) ** 2
    for a in (ua, ub, um, width, sin2):
        a.setflags(write=False)
    return ua, ub, um, width, sin2


@dataclass(frozen=True)
class FilteredNoise:
    """The Allan variance (units^2) of noise terms seen through an output filter, term by
    term (see :meth:`OutputFilter.filtered_noise`)."""

    total: np.ndarray
    parts: list[np.ndarray]
    """Each term's part of ``total``, in the order the terms were given."""
    unfiltered: list[np.ndarray | None]
    """A long-memory term's own Allan variance, before the filter's correction; None for a
    term filtered in the time domain (white noise, quantization)."""
    matters: list[np.ndarray | None]
    """Where a long-memory term's correction is computed (its own Allan variance is at
    least 1e-4 of the model's); None for the others."""


def _symmetric(r: np.ndarray) -> np.ndarray:
    """``r[-K..K]`` from ``r[0..K]``."""
    return np.concatenate((r[:0:-1], r))


class FilterSimulator(TermSimulator):
    """Applies the filter to the sum of the noise terms, keeping its state across blocks."""

    def __init__(self, b: np.ndarray, a: np.ndarray) -> None:
        self.b, self.a = np.asarray(b, float), np.asarray(a, float)
        self.zi = np.zeros(max(len(self.a), len(self.b)) - 1)
        self.started = False

    def apply(self, x: np.ndarray) -> np.ndarray:
        """The next block of filter output for the input block ``x``."""
        from scipy.signal import lfilter, lfilter_zi  # slow to import: see analysis.dsp

        if x.size == 0:
            return x
        if not self.started:
            # start in the steady state of the first input value (no turn-on transient)
            self.zi = lfilter_zi(self.b, self.a) * x[0] if len(self.zi) else self.zi
            self.started = True
        if not len(self.zi):
            return self.b[0] / self.a[0] * x
        y, self.zi = lfilter(self.b, self.a, x, zi=self.zi)
        return y

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        return np.zeros(int(n))


class OutputFilter(Term):
    """Base class of the filter terms. Subclasses give :meth:`impulse_response` (``g``, unit
    sum; an infinite response cut where it has decayed below 1e-12) and may give
    :meth:`response` in closed form and :meth:`coefficients` for simulation."""

    kind = "filter"
    role = "filter"
    continuous_psd = False
    live = False
    ripple = True
    """Whether the power response has sidelobes (sets the frequency grid's density)."""

    def __init__(self) -> None:
        self._cache: OrderedDict[tuple, Any] = OrderedDict()
        self._lock = threading.Lock()

    # no Allan variance or spectrum of its own: it acts on the noise terms
    def _avar(self, tau: np.ndarray, fs: float, **params: Any) -> np.ndarray:
        return np.zeros_like(tau)

    def _psd(self, f: np.ndarray, fs: float, **params: Any) -> np.ndarray:
        return np.zeros_like(f)

    def impulse_response(self, fs_hz: float, params: dict[str, float]) -> np.ndarray:
        raise NotImplementedError

    def start_params(self, fs_hz: float) -> dict[str, float]:
        """Starting parameters of a fit: a mild filter (a real sensor's is short)."""
        return dict(self.small_default)

    def identity_params(self, fs_hz: float) -> dict[str, float]:
        """The parameters nearest to no filter at all: where a fit that appends this filter
        to a solved model starts (default: the parameter's lower bound, one tap)."""
        return {self.amplitude: self.param(self.amplitude).lo}

    def start_grid(self, fs_hz: float) -> list[dict[str, float]]:
        """Candidate parameters scored on a solved smaller model's residual when this filter
        is appended to it (see :func:`imunoise.analysis.fit.starts._residual_starts`); empty
        when the solve from :meth:`identity_params` finds the filter by itself."""
        return []

    def kink(self, params: dict[str, float]) -> bool:
        """Whether the Allan variance has a kink in the filter's parameter at ``params`` (a
        solve can stop there; default: none)."""
        return False

    def cold_grid(self, fs_hz: float) -> list[dict[str, float]]:
        """Candidate parameters scored when the filter is fitted together with terms after it
        in the model, from no previous fit (see
        :func:`imunoise.analysis.fit.starts._inner_filter_starts`; default: the
        :meth:`start_grid`)."""
        return self.start_grid(fs_hz)

    def coefficients(self, fs_hz: float, params: dict[str, float]
                     ) -> tuple[np.ndarray, np.ndarray]:
        """``(b, a)`` of the filter as a difference equation (default: the FIR ``g``)."""
        return self.impulse_response(fs_hz, params), np.array([1.0])

    def length(self, fs_hz: float, params: dict[str, float]) -> float:
        """Effective length in samples (sets the grids and the reach of the correction)."""
        g = self.impulse_response(fs_hz, params)
        return float(1.0 / np.sum(g * g))

    def response(self, f: np.ndarray, fs_hz: float, params: dict[str, float]) -> np.ndarray:
        g = self.impulse_response(fs_hz, params)
        w = 2.0 * np.pi * np.atleast_1d(np.asarray(f, dtype=np.float64)) / fs_hz
        k = np.arange(len(g), dtype=np.float64)
        phase = np.outer(w, k)
        return (np.cos(phase) @ g) ** 2 + (np.sin(phase) @ g) ** 2

    def _remember(self, key: tuple, make: Any) -> Any:
        """``make()`` remembered under ``key`` (a fit asks again for the same filter while it
        moves only the noise amplitudes)."""
        with self._lock:
            hit = self._cache.get(key)
            if hit is not None:
                self._cache.move_to_end(key)
                return hit
        hit = make()
        with self._lock:
            self._cache[key] = hit
            while len(self._cache) > _CACHE_SIZE:
                self._cache.popitem(last=False)
        return hit

    def _autocorrelation(self, fs_hz: float, params: dict[str, float]) -> np.ndarray:
        """``r_g[-K..K]`` of the impulse response."""
        def make() -> np.ndarray:
            g = self.impulse_response(fs_hz, params)
            return np.correlate(g, g, mode="full")
        return self._remember(("acf", fs_hz, tuple(sorted(params.items()))), make)

    def filtered_avar(self, noise: list[tuple[Term, dict[str, float]]], tau: np.ndarray,
                      fs_hz: float, params: dict[str, float]) -> np.ndarray:
        return self.filtered_noise(noise, tau, fs_hz, params).total

    def filtered_parts(self, noise: list[tuple[Term, dict[str, float]]], tau: np.ndarray,
                       fs_hz: float, params: dict[str, float]
                       ) -> tuple[np.ndarray, list[np.ndarray]]:
        """The filtered Allan variance of the ``noise`` terms (units^2) and each term's part
        of it, in the order given. A part scales with the square of its term's amplitude
        (a fit's derivative by that amplitude is twice the part)."""
        found = self.filtered_noise(noise, tau, fs_hz, params)
        return found.total, found.parts

    def filtered_noise(self, noise: list[tuple[Term, dict[str, float]]], tau: np.ndarray,
                       fs_hz: float, params: dict[str, float], *,
                       like: FilteredNoise | None = None, moved: int | None = None
                       ) -> FilteredNoise:
        """:meth:`filtered_parts` with what it was computed from.

        ``like`` is the result for the same terms, ``tau`` and filter where only the term at
        position ``moved`` had other parameters (a fit's difference step on that term's shape):
        the other terms are taken from it, and a term's correction is computed again only
        where the new total moves the threshold below which it is left out. The result is
        the one computed from nothing, to the last bit; a fit's derivative by one term's
        shape then costs that term's correction instead of every term's."""
        tau = np.atleast_1d(np.asarray(tau, dtype=np.float64))
        m = tau * fs_hz
        out = np.zeros_like(tau)
        parts: list[np.ndarray] = [out] * len(noise)
        own: list[np.ndarray | None] = [None] * len(noise)
        for n, (term, p) in enumerate(noise):
            if like is not None and n != moved:
                own[n] = like.unfiltered[n]
                if own[n] is None:
                    parts[n] = like.parts[n]
                    out += parts[n]
            elif term.autocovariance(fs_hz, p) is not None:
                parts[n] = self._short_memory_avar(term, p, m, fs_hz, params)
                out += parts[n]
            else:
                own[n] = term.avar_fast(tau, fs_hz, p)
        total = out + sum((a for a in own if a is not None), np.zeros_like(tau))
        matters: list[np.ndarray | None] = [None] * len(noise)
        for n, (term, p) in enumerate(noise):
            a = own[n]
            if a is None:
                continue
            # 0 <= |G|^2 <= 1, so the correction is smaller than the term's own Allan variance:
            # where that is below 1e-4 of the model's, it is left out
            mask = a > _NEGLIGIBLE * total
            matters[n] = mask
            kept = like if like is not None and n != moved else None
            if kept is not None and np.array_equal(mask, kept.matters[n]):  # type: ignore[arg-type]
                parts[n] = kept.parts[n]
            else:
                parts[n] = a * self._ratio(term, p, np.where(mask, m, np.inf), fs_hz, params)
            out += parts[n]
        return FilteredNoise(out, parts, own, matters)

    def filtered_autocovariance(self, r_in: np.ndarray, fs_hz: float,
                                params: dict[str, float]) -> np.ndarray:
        """Autocovariance ``R(0), R(1), ...`` at the filter's output of a stationary input
        whose autocovariance ``r_in`` (``R(0), R(1), ...``) ends after a few lags."""
        full = np.convolve(_symmetric(np.asarray(r_in, float)),
                           self._autocorrelation(fs_hz, params))
        return full[len(full) // 2:]

    def _short_memory_avar(self, term: Term, p: dict[str, float], m: np.ndarray,
                           fs_hz: float, params: dict[str, float]) -> np.ndarray:
        """Filtered Allan variance of a term whose autocovariance ends after a few lags
        (white noise, quantization). Computed at unit amplitude (the autocovariance scales
        with its square) and remembered for the other parameters: a fit's step on the
        amplitude, or on another term, finds it."""
        shape = {k: v for k, v in p.items() if k != term.amplitude}

        def make() -> np.ndarray:
            r_in = term.autocovariance(fs_hz, {**shape, term.amplitude: 1.0})
            assert r_in is not None  # filtered_parts sends only such terms
            avar = avar_from_autocovariance(self.filtered_autocovariance(r_in, fs_hz, params),
                                            m)
            avar.setflags(write=False)
            return avar
        unit = self._remember(("short", term.name, fs_hz, tuple(sorted(shape.items())),
                               tuple(sorted(params.items())), m.tobytes()), make)
        return unit * float(p[term.amplitude]) ** 2

    def _ratio(self, term: Term, p: dict[str, float], m: np.ndarray, fs_hz: float,
               params: dict[str, float]) -> np.ndarray:
        """Filtered over unfiltered Allan variance of one noise term (see the module), 1 beyond
        the correction's reach.

        The term's own Allan variance is scaled by this ratio, not shifted by the difference
        of the two integrals: where the own formula is asymptotic (a flicker floor, constant
        down to one sample, while the sampled 1/f spectrum gives more at m = 1) and the filter
        removes most of the band, the difference exceeds the own value and the filtered
        variance came out negative (a 20-tap moving average on B = 1.6e-3 at 10 Hz: -2.0e-7
        at tau = 0.1 s). The ratio is the same where the formula and the integral agree."""
        length = self.length(fs_hz, params)
        near = m <= _CORRECTION_REACH * max(length, 1.0)
        out = np.ones_like(m)
        if not np.any(near):
            return out
        # computed at unit amplitude (the ratio does not depend on it), so a fit that moves
        # only amplitudes finds it remembered
        shape = {k: v for k, v in p.items() if k != term.amplitude}
        key = ("ratio", term.name, fs_hz, tuple(sorted(shape.items())),
               tuple(sorted(params.items())), m[near].tobytes())

        def make() -> np.ndarray:
            bins_key, (ua, ub, um, width, sin2), excess = self._grid(
                fs_hz, params, float(m[near].max()))
            s = term.psd(um * fs_hz, fs_hz, **{**shape, term.amplitude: 1.0})
            weight = 0.5 * fs_hz * s * 4.0 / sin2 * width
            table = sin4_table_shared(m[near][:, None], um, ua, ub, bins_key)
            unfiltered = table @ weight
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = 1.0 + (table @ (weight * excess)) / unfiltered
            return np.clip(np.where(unfiltered > 0.0, ratio, 1.0), 0.0, None)

        out[near] = self._remember(key, make)
        return out

    def _grid(self, fs_hz: float, params: dict[str, float], m_max: float
              ) -> tuple[tuple[float, int], tuple[np.ndarray, ...], np.ndarray]:
        """Bins in ``u = f/fs`` (log-spaced from well below ``1/m_max``, linear and fine enough
        for the response's ripple near Nyquist): the key that names them, :func:`_bins`, and
        ``|G|^2 - 1`` at their mid-points."""
        # the grid is shared by every m_max of one tenth of an octave, and is a function of
        # that tenth alone: which m_max asked first must not change the result
        octave = math.ceil(10.0 * math.log2(max(m_max, 1.0))) / 10.0

        def make() -> tuple[tuple[float, int], tuple[np.ndarray, ...], np.ndarray]:
            length = max(self.length(fs_hz, params), 1.0)
            u_lo = 1e-3 / 2.0 ** octave
            # a response with ripple (a moving average's sidelobes, period fs/L) needs a
            # few dozen points per lobe; a smooth one only the log grid and a coarse cover
            n_lin = int(min(max(32.0 * length, 512.0), 8192.0)) if self.ripple else 256
            bins = _bins(u_lo, n_lin)
            return (u_lo, n_lin), bins, self.response(bins[2] * fs_hz, fs_hz, params) - 1.0
        return self._remember(("grid", fs_hz, tuple(sorted(params.items())), octave), make)

    def simulator(self, params, fs_hz, rng, **options):
        b, a = self.coefficients(fs_hz, params)
        return FilterSimulator(b, a)

    def add_discrete(self, dm, params):
        raise TermError(f"{self.name}: the block likelihood has no output-filter states; use "
                        f"the Allan estimator")
