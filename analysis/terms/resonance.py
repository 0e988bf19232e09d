"""Narrowband random vibration: a second-order resonance with centre frequency f0, quality
factor Q and standard deviation sigma.

Defined in discrete time, so its Allan variance and PSD are exact at every tau = m/fs: the
AR(2) process ``x_k = 2 r cos(w0) x_{k-1} - r^2 x_{k-2} + e_k`` with ``w0 = 2 pi f0/fs`` and
pole radius ``r = exp(-pi f0/(Q fs))`` (half-power bandwidth f0/Q), scaled to stationary
standard deviation sigma. Its autocorrelation is ``rho(k) = 2 Re(c p^|k|)`` with the pole
``p = r e^{i w0}``, so its Allan variance is the first-order Markov formula
(:func:`imunoise.analysis.terms.gauss_markov.ar1_avar_shape`'s closed form) evaluated at the complex
pole and weighted by ``c``. A pure sinusoid is the limit Q -> infinity; the diagnosis tells
the two apart by the width of the spectral peak.
"""

from __future__ import annotations

import math
from typing import Any, TypeVar

import numpy as np

from imunoise.analysis.terms.base import Param, Term, TermSimulator
from imunoise.analysis.terms.shape_memo import ShapeMemo

_MAX_Q = 1.0e4
_SHAPES = ShapeMemo()


def _poles(fs: float, f0: float, q: float) -> tuple[complex, float, float]:
    """The pole ``p`` and the AR coefficients ``(phi1, phi2)``."""
    r = math.exp(-math.pi * f0 / (q * fs))
    w0 = 2.0 * math.pi * f0 / fs
    return complex(r * math.cos(w0), r * math.sin(w0)), 2.0 * r * math.cos(w0), -r * r


_F = TypeVar("_F", float, np.ndarray)


def _innovation_var(phi1: _F, phi2: _F) -> _F:
    """Variance of ``e_k`` giving the AR(2) process unit variance."""
    return (1.0 + phi2) * ((1.0 - phi2) ** 2 - phi1 * phi1) / (1.0 - phi2)


def resonance_unit_psd(f: np.ndarray, fs: float, f0: float | np.ndarray, q: float
                       ) -> np.ndarray:
    """One-sided PSD (1/Hz) of the unit-variance resonance at ``f`` (Hz); ``f0`` (Hz) may be
    an array broadcasting against ``f``, one spectrum per centre frequency."""
    r = np.exp(-np.pi * np.asarray(f0, dtype=np.float64) / (q * fs))
    half_w0 = np.pi * np.asarray(f0, dtype=np.float64) / fs
    half_w = np.pi * np.asarray(f, dtype=np.float64) / fs
    # |1 - phi1 z^-1 - phi2 z^-2|^2 on the unit circle as |1 - p z^-1|^2 |1 - p* z^-1|^2,
    # each (1 - r)^2 + 4 r sin^2((w -+ w0)/2): real arithmetic without the cancellation
    # of a sharp peak (a fit through an output filter asks for this on a fine grid tens
    # of thousands of times)
    floor = (1.0 - r) ** 2
    den = (floor + 4.0 * r * np.sin(half_w - half_w0) ** 2) \
        * (floor + 4.0 * r * np.sin(half_w + half_w0) ** 2)
    innovation = _innovation_var(2.0 * r * np.cos(2.0 * half_w0), -r * r)
    return 2.0 * innovation / (fs * den)


def resonance_psd_mixture(f: np.ndarray, fs: float, f0: np.ndarray, weights: np.ndarray,
                          q: float) -> np.ndarray:
    """``sum_k weights[k] * resonance_unit_psd(f, fs, f0[k], q)`` (1/Hz) at ``f`` (Hz): the
    spectrum of a resonance whose centre frequency takes the values ``f0`` with those weights.

    The same expression as :func:`resonance_unit_psd`, with the sines of the half-angle
    difference and sum taken from those of the two angles (``sin(a -+ b) = sin a cos b -+ cos
    a sin b``): one sine and cosine per frequency and per centre frequency instead of two
    sines per pair, which made a fit with a wandering resonance behind an output filter spend
    half its time in ``np.sin`` (the values agree to about 1e-13, relative, at Q = 1e4)."""
    at = np.atleast_1d(np.asarray(f, dtype=np.float64))
    centres = np.atleast_1d(np.asarray(f0, dtype=np.float64))
    w = np.atleast_1d(np.asarray(weights, dtype=np.float64))
    half_w = np.pi * at / fs
    sin_w, cos_w = np.sin(half_w), np.cos(half_w)
    out = np.zeros(at.shape)
    rows = min(_MIXTURE_BLOCK, centres.size)
    minus, plus, cross = (np.empty((rows, at.size)) for _ in range(3))
    for a in range(0, centres.size, _MIXTURE_BLOCK):
        c = centres[a:a + _MIXTURE_BLOCK, None]
        n = c.shape[0]
        d, s, x = minus[:n], plus[:n], cross[:n]
        r = np.exp(-np.pi * c / (q * fs))
        half_w0 = np.pi * c / fs
        floor = (1.0 - r) ** 2
        four_r = 4.0 * r
        scale = w[a:a + _MIXTURE_BLOCK, None] \
            * (2.0 * _innovation_var(2.0 * r * np.cos(2.0 * half_w0), -r * r) / fs)
        np.multiply(sin_w, np.cos(half_w0), out=d)
        np.multiply(cos_w, np.sin(half_w0), out=x)
        np.add(d, x, out=s)  # sin((w + w0)/2)
        d -= x  # sin((w - w0)/2)
        for y in (d, s):
            np.square(y, out=y)
            y *= four_r
            y += floor
        d *= s
        np.divide(scale, d, out=d)
        out += d.sum(axis=0)
    return out.reshape(np.shape(f))


_MIXTURE_BLOCK = 32
"""Centre frequencies taken together by :func:`resonance_psd_mixture` (bounds its scratch
arrays to 32 rows of the frequency grid)."""


def resonance_avar_shape(m: np.ndarray, fs: float, f0: float, q: float) -> np.ndarray:
    """Allan variance of the unit-variance resonance at averaging factors ``m``."""
    p, c = pole_and_weight(fs, f0, q)
    return _pole_avar(np.asarray(m, dtype=np.complex128), p, c)


def pole_and_weight(fs: float, f0: float, q: float) -> tuple[complex, complex]:
    """The pole ``p`` and weight ``c`` of the unit-variance resonance's autocorrelation
    ``rho(k) = 2 Re(c p^|k|)``."""
    p, phi1, phi2 = _poles(fs, f0, q)
    rho1 = phi1 / (1.0 - phi2)
    # rho(0) = 1 and rho(1) = rho1 fix c
    c = complex(0.5, (p.real - rho1) / (2.0 * p.imag)) if p.imag != 0 else complex(0.5, 0.0)
    return p, c


def _pole_avar(mm: Any, p: Any, c: Any) -> Any:
    """Allan variance at averaging factors ``mm`` (complex) of the unit-variance sequence with
    autocorrelation ``rho(k) = 2 Re(c p^|k|)``: the first-order Markov closed form at the
    complex pole ``p``. ``p`` and ``c`` are scalars, or columns of poles broadcasting against a
    row of ``mm``."""
    return np.maximum(2.0 * np.real(c * pole_shape(mm, p)), 0.0)


def pole_shape(mm: Any, p: Any) -> Any:
    """The complex factor of :func:`_pole_avar`: the Allan variance at averaging factors
    ``mm`` of a sequence with autocovariance ``2 Re(c p^|k|)`` is ``2 Re(c pole_shape)``."""
    pm = np.exp(mm * np.log(p))
    one_minus_pm = 1.0 - pm
    num = mm * (1.0 - p * p) - 2.0 * p * one_minus_pm - p * one_minus_pm**2
    return num / (mm * mm * (1.0 - p) ** 2)


def resonance_avar_mixture(m: np.ndarray, fs: float, f0: np.ndarray, weights: np.ndarray,
                           q: float) -> np.ndarray:
    """``sum_k weights[k] * resonance_avar_shape(m, fs, f0[k], q)``: the Allan variance at
    averaging factors ``m`` of a unit-variance resonance whose centre frequency takes the
    values ``f0`` (Hz) with those weights, every centre frequency at once."""
    mm = np.asarray(m, dtype=np.complex128).reshape(1, -1)
    centres = np.atleast_1d(np.asarray(f0, dtype=np.float64))[:, None]
    r = np.exp(-np.pi * centres / (q * fs))
    w0 = 2.0 * np.pi * centres / fs
    p = r * np.exp(1j * w0)
    phi1, phi2 = 2.0 * r * np.cos(w0), -r * r
    rho1 = phi1 / (1.0 - phi2)
    # as in resonance_avar_shape: rho(0) = 1 and rho(1) = rho1 fix c
    safe_imag = np.where(p.imag != 0.0, p.imag, 1.0)
    c = 0.5 + 1j * np.where(p.imag != 0.0, (p.real - rho1) / (2.0 * safe_imag), 0.0)
    each = _pole_avar(mm, p, c)
    return (np.asarray(weights, dtype=np.float64) @ each).reshape(np.shape(m))


class _ResonanceSim(TermSimulator):
    """The AR(2) recursion, its output through the FIR ``taps`` where given (at most three:
    an antiresonance's zeros)."""

    def __init__(self, sigma: float, fs: float, f0: float, q: float,
                 rng: np.random.Generator, taps: np.ndarray | None = None) -> None:
        from scipy.signal import lfilter  # slow to import: see analysis.dsp

        _, phi1, phi2 = _poles(fs, f0, q)
        self.a = np.array([1.0, -phi1, -phi2])
        self.b = np.ones(1) if taps is None else np.asarray(taps, dtype=np.float64)
        self.e_sd = sigma * math.sqrt(_innovation_var(phi1, phi2))
        self.rng = rng
        # start in the stationary law: run the recursion over its settling time first
        burn = int(min(50.0 * q * fs / (math.pi * f0), 2e6)) + 10
        _, self.zi = lfilter(self.b, self.a, rng.standard_normal(burn) * self.e_sd,
                             zi=np.zeros(2))

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        from scipy.signal import lfilter

        if n <= 0:
            return np.zeros(0)
        y, self.zi = lfilter(self.b, self.a, self.rng.standard_normal(n) * self.e_sd,
                             zi=self.zi)
        return y


class Resonance(Term):
    name = "resonance"
    order = 150
    params = (Param("sigma", "rate", 0.0, 1.0e3, "standard deviation of the vibration"),
              Param("f0", "Hz", 0.0, 1.0e9, "centre frequency"),
              Param("Q", "ratio", 0.5, _MAX_Q, "quality factor (centre frequency over the "
                    "half-power bandwidth)", lo_open=False))
    amplitude = "sigma"
    repeatable = True
    allan_signature = ("a bump near tau = 1/(2 f0) whose ripples decay faster the lower Q; "
                       "sigma^2/tau falling beyond it")
    effect = "narrowband random vibration (second-order resonance)"
    explanation = (
        "Vibration within a band: a mount, fan or structural mode, or the sensor's own proof "
        "mass ringing, excited at random. Unlike a pure sinusoid its phase wanders, so its "
        "spectral peak at f0 has a width f0/Q; on the Allan deviation it makes a bump near "
        "tau = 1/(2 f0) with fewer ripples than a sinusoid's.")
    small_default = {"sigma": 1e-6, "f0": 1.0, "Q": 10.0}
    reduces_to = "gauss_markov"  # without a peak: a bend of the Allan curve, no line

    def log_fit_bounds(self, param, fs_hz, duration_s):
        if param.name == "f0":
            return math.log(20.0 / duration_s), math.log(0.49 * fs_hz)
        return param.log_fit_bounds(fs_hz, duration_s)

    def unresolved(self, params, ci95):
        # With the pole radius exp(-pi f0/(Q fs)) the spectrum has a peak only for Q above
        # its lower bound 0.5 (the critically damped limit, for f0 well below fs/2); an
        # interval reaching it means the data show no peak, only a bend a Markov term makes.
        lo = ci95.get("Q", (math.nan, math.nan))[0]
        q_min = self.param("Q").lo
        if not math.isfinite(lo) or lo <= q_min * (1.0 + 1e-6):
            return (f"its spectral peak is not resolved (the interval of Q reaches "
                    f"{q_min:g}, where the spectrum has no peak)")
        return None

    def _avar(self, tau: np.ndarray, fs: float, sigma: float, f0: float, Q: float
              ) -> np.ndarray:
        return sigma * sigma * _SHAPES.get((tau.tobytes(), fs, f0, Q),
                                           lambda: resonance_avar_shape(tau * fs, fs, f0, Q))

    def _psd(self, f: np.ndarray, fs: float, sigma: float, f0: float, Q: float) -> np.ndarray:
        return sigma * sigma * resonance_unit_psd(f, fs, f0, Q)

    def start_shapes(self, fs_hz, duration_s, line):
        f_lo = 40.0 / duration_s
        freqs = list(np.geomspace(f_lo, 0.45 * fs_hz, 20)) if f_lo < 0.45 * fs_hz else []
        if line is not None:
            freqs.append(float(line[0]))
        return [{"f0": float(f), "Q": q} for f in freqs for q in (3.0, 30.0)]

    def simulator(self, params, fs_hz, rng, **options):
        return _ResonanceSim(float(params["sigma"]), fs_hz, float(params["f0"]),
                             float(params["Q"]), rng)


TERM = Resonance()
