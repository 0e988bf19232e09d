"""First-order Gauss-Markov (exponentially correlated) bias, sigma and T.

Defined in discrete time: the point-sampled AR(1) process ``x_k = a x_{k-1} + w_k`` with
``a = exp(-1/(fs T))`` and stationary standard deviation sigma, so its Allan variance and PSD
are exact at every tau = m/fs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imunoise.analysis.terms.base import Param, Term, TermSimulator
from imunoise.analysis.terms.shape_memo import ShapeMemo


@dataclass(frozen=True)
class MarkovState:
    """One first-order Markov state ``x_{k+1} = a_d x_k + w_k`` at the sample period.

    Attributes:
        term: the continuous term it comes from (``gauss_markov`` or ``bias_instability``).
        T_s: correlation time in s.
        sigma: stationary standard deviation (channel units).
        a_d: ``exp(-dt/T)``.
        driving_sigma: standard deviation of ``w_k``, ``sigma sqrt(1 - a_d^2)`` (channel units).
    """

    term: str
    T_s: float
    sigma: float
    a_d: float
    driving_sigma: float


def markov_state(term: str, sigma: float, T_s: float, fs_hz: float) -> MarkovState:
    """The Markov state of stationary deviation ``sigma`` and correlation time ``T_s`` (s) at
    the sample period ``1/fs_hz`` (the discrete model's form, :mod:`imunoise.analysis.discrete`)."""
    x = 1.0 / (fs_hz * T_s)
    a = float(np.exp(-x))
    return MarkovState(term=term, T_s=float(T_s), sigma=float(sigma), a_d=a,
                       driving_sigma=float(sigma * np.sqrt(-np.expm1(-2.0 * x))))


_BIG = 1.0e3
_SHAPES = ShapeMemo()

MIN_T_SAMPLES = 2.0
"""Shortest correlation time the fit may give, in sample periods: below about two its
spectrum is flat across the sampled band (white noise), and a fit could trade the white
level for it."""


def half_angle_sin2(f_hz: np.ndarray, fs_hz: float) -> np.ndarray:
    """``sin^2(w/2)`` at the frequencies ``f_hz`` (Hz), ``w = 2 pi f / fs`` the angular
    frequency per sample: what :func:`ar1_psd` needs of the grid."""
    w = 2.0 * np.pi * f_hz / fs_hz
    return np.sin(w / 2.0) ** 2


def ar1_psd(sin2: np.ndarray, fs_hz: float, sigma: float, T: float) -> np.ndarray:
    """One-sided PSD (units^2/Hz) of the sampled first-order Markov process of standard
    deviation ``sigma`` and correlation time ``T`` (s), on a grid given by
    :func:`half_angle_sin2` (computed once for a sum of such processes)."""
    b = 1.0 / (fs_hz * T)
    a = math.exp(-b)
    one_minus_a2 = -math.expm1(-2.0 * b)
    # 1 - 2a cos w + a^2 = (1-a)^2 + 4a sin^2(w/2), written to avoid cancellation
    den = (-math.expm1(-b)) ** 2 + 4.0 * a * sin2
    return 2.0 * sigma * sigma * one_minus_a2 / (fs_hz * den)


def ar1_avar_shape(m: np.ndarray, b: float) -> np.ndarray:
    """Allan variance of a unit-variance point-sampled AR(1) process, per sigma^2.

    ``m`` is the averaging length in samples, ``b = 1/(fs T)`` the sampling interval over the
    correlation time (``a = exp(-b)``). Exact for any m >= 1:
    ``[m(1-a^2) - 2a(1-a^m) - a(1-a^m)^2] / (m^2 (1-a)^2)``. Evaluated in extended precision
    because the bracket cancels when m b is small; below m b = 1e-4, where even extended
    precision loses about 1/(m b)^2 of its digits, its Taylor series in b is used instead:
    ``[b m (2 m^2 + 1)/3 - (m^2 b)^2/2] / m^2`` (relative error about 0.35 (m b)^2).
    """
    m_l = np.asarray(m, dtype=np.longdouble)
    b_l = np.longdouble(b)
    a = np.exp(-b_l)
    one_minus_a = -np.expm1(-b_l)
    one_minus_am = -np.expm1(-m_l * b_l)
    num = m_l * one_minus_a * (1 + a) - 2 * a * one_minus_am - a * one_minus_am**2
    out = (num / (m_l * m_l * one_minus_a * one_minus_a)).astype(np.float64)
    # series of the bracket (lag weights c_k with sum c_k k = -m (2 m^2 + 1)/3 and
    # sum c_k k^2 = -m^4) where the closed form cancels
    m_f = np.asarray(m, dtype=np.float64)
    series = (b * m_f * (2.0 * m_f**2 + 1.0) / 3.0 - 0.5 * (m_f**2 * b) ** 2) / m_f**2
    out = np.where(m_f * b < 1e-4, series, out)
    return np.maximum(out, 0.0)


class Ar1Bank(TermSimulator):
    """Parallel AR(1) processes ``x_k = a x_{k-1} + w_k`` started in their stationary law."""

    def __init__(self, rng: np.random.Generator, fs_hz: float, times: np.ndarray,
                 sigmas: np.ndarray) -> None:
        self.rng = rng
        b = 1.0 / (fs_hz * np.asarray(times, dtype=np.float64))
        self.a = np.exp(-b)
        self.w_sd = np.asarray(sigmas) * np.sqrt(-np.expm1(-2.0 * b))
        self.x = rng.standard_normal(len(self.a)) * np.asarray(sigmas)

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        from scipy.signal import lfilter  # slow to import: see analysis.dsp

        w = self.rng.standard_normal((n, len(self.a))) * self.w_sd
        out = np.zeros(n)
        for j, a in enumerate(self.a):
            y, _ = lfilter([1.0], [1.0, -a], w[:, j], zi=[a * self.x[j]])
            self.x[j] = y[-1] if n else self.x[j]
            out += y
        return out


class GaussMarkov(Term):
    name = "gauss_markov"
    order = 60
    params = (Param("sigma", "rate", 0.0, _BIG, "standard deviation of the correlated bias"),
              Param("T", "s", 0.0, 1.0e8, "correlation time"))
    amplitude = "sigma"
    repeatable = True
    estimators = frozenset({"allan", "block_likelihood"})
    allan_signature = "bump near tau = 1.9 T: sigma^2 tau/T rising, sigma^2 T/tau falling"
    effect = "exponentially correlated bias (first-order Markov)"
    explanation = (
        "A bias that wanders but is pulled back to its mean with a single correlation time "
        "T, as a thermal or mechanical process with one time constant. On the Allan deviation "
        "it makes a hump peaking near tau = 1.9 T (about 0.62 sigma); in the spectrum a flat "
        "level below 1/(2 pi T) rolling off as 1/f^2 above it.")
    small_default = {"sigma": 1e-6, "T": 10.0}

    def _avar(self, tau: np.ndarray, fs: float, sigma: float, T: float) -> np.ndarray:
        return sigma * sigma * _SHAPES.get((tau.tobytes(), fs, T),
                                           lambda: ar1_avar_shape(tau * fs, 1.0 / (fs * T)))

    def _psd(self, f: np.ndarray, fs: float, sigma: float, T: float) -> np.ndarray:
        return ar1_psd(half_angle_sin2(f, fs), fs, sigma, T)

    def log_fit_bounds(self, param, fs_hz, duration_s):
        if param.name == "T":
            lo, hi = param.log_fit_bounds(fs_hz, duration_s)
            return math.log(MIN_T_SAMPLES / fs_hz), max(hi, math.log(4.0 * MIN_T_SAMPLES / fs_hz))
        return param.log_fit_bounds(fs_hz, duration_s)

    def start_shapes(self, fs_hz, duration_s, line):
        # correlation times from two samples to half the record
        return [{"T": float(t)} for t in
                np.geomspace(2.0 / fs_hz, max(duration_s / 2.0, 4.0 / fs_hz), 36)]

    def simulator(self, params, fs_hz, rng, **options):
        return Ar1Bank(rng, fs_hz, np.array([float(params["T"])]),
                       np.array([float(params["sigma"])]))

    def add_discrete(self, dm, params):
        dm.markov.append(markov_state(self.name, params["sigma"], params["T"], dm.fs_hz))


TERM = GaussMarkov()
