"""The eight stochastic and systematic error terms of an inertial sensor channel.

Each term has: its parameters with SI units and physical ranges, its overlapping Allan variance
as a function of averaging time ``tau_s`` for data sampled at ``fs_hz``, its one-sided power
spectral density, and a plain-language explanation shown to users.

Sampling model (what "exact" means here). A rate sample ``y_k`` is the average of the
continuous rate over its sampling interval (integrate-and-dump, as the decimation filter of a
MEMS sensor approximately does). Under that model the classical expressions for white noise
(N^2/tau), angle quantization (3 Q^2/tau^2), rate random walk (K^2 tau/3) and rate ramp
(R^2 tau^2/2) hold exactly at every tau = m/fs, m >= 1. Two terms are defined directly in
discrete time and use exact discrete expressions instead of the continuous ones:

* ``gauss_markov``: the point-sampled first-order Markov (AR(1)) process
  ``x_k = a x_{k-1} + w_k`` with ``a = exp(-1/(fs T))`` and stationary standard deviation sigma.
* ``sinusoid``: ``A sin(2 pi f k/fs + phi)`` sampled at ``fs``; its Allan variance uses the
  Dirichlet kernel of the m-sample average, which the continuous sinc form only approximates.

``bias_instability`` is flicker (1/f) noise; its Allan variance is the ideal plateau
(2 ln2/pi) B^2 at every tau (see docs/terms.md for the simulator's band).

Parameters are in SI units of the channel: for a gyro channel rad/s; for an accelerometer the
same with rad replaced by m/s. Spectral densities are one-sided (units^2/Hz over 0..fs/2): white
noise with Allan variance N^2/tau has one-sided PSD 2 N^2.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

BIAS_INSTABILITY_FACTOR = 2.0 * math.log(2.0) / math.pi
"""Allan variance plateau of flicker noise per B^2: sigma^2 = (2 ln2/pi) B^2."""


class TermError(ValueError):
    """Unknown term, unknown parameter, or a parameter outside its physical range."""


@dataclass(frozen=True)
class Param:
    """One parameter of a term.

    ``kind`` selects its unit for a channel (see :func:`param_unit`): ``"rate/sqrt(Hz)"``,
    ``"angle"``, ``"rate"``, ``"rate/sqrt(s)"``, ``"rate/s"``, ``"s"``, ``"Hz"``, ``"rate/degC"``.
    ``lo``/``hi`` bound physically meaningful values in SI units (``lo`` exclusive when
    ``lo_open``); ``hi`` of a frequency is further limited to the Nyquist frequency.
    """

    name: str
    kind: str
    lo: float
    hi: float
    description: str
    lo_open: bool = True


@dataclass(frozen=True)
class Term:
    """A noise term: vocabulary, Allan variance, PSD and user-facing explanation."""

    name: str
    params: tuple[Param, ...]
    allan_signature: str
    effect: str
    explanation: str
    avar_fn: Callable[..., np.ndarray]
    psd_fn: Callable[..., np.ndarray]
    linear: bool
    """True when the Allan variance is (fixed shape) x (single parameter)^2."""

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def avar(self, tau_s: np.ndarray | float, fs_hz: float, **params: float) -> np.ndarray:
        """Allan variance (units^2) at averaging times ``tau_s`` (s) for data sampled at
        ``fs_hz`` (Hz)."""
        tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
        return self.avar_fn(tau, float(fs_hz), **_only(self, params))

    def psd(self, f_hz: np.ndarray | float, fs_hz: float, **params: float) -> np.ndarray:
        """One-sided power spectral density (units^2/Hz) at frequencies ``f_hz`` (Hz)."""
        f = np.atleast_1d(np.asarray(f_hz, dtype=np.float64))
        return self.psd_fn(f, float(fs_hz), **_only(self, params))


_EXTRAS = {"temperature": ("temp_avar", "temp_psd"), "sinusoid": ("bandwidth_hz",)}


def _only(term: Term, params: dict[str, float]) -> dict[str, float]:
    allowed = set(term.param_names) | set(_EXTRAS.get(term.name, ()))
    unknown = set(params) - allowed
    if unknown:
        raise TermError(f"{term.name}: unknown parameter(s) {', '.join(sorted(unknown))}; "
                        f"expected {', '.join(term.param_names)}")
    missing = set(term.param_names) - set(params)
    if missing:
        raise TermError(f"{term.name}: missing parameter(s) {', '.join(sorted(missing))}")
    return params


# --- Allan variances -------------------------------------------------------------------------

def _avar_white(tau: np.ndarray, fs: float, N: float) -> np.ndarray:
    return N * N / tau


def _avar_quantization(tau: np.ndarray, fs: float, Q: float) -> np.ndarray:
    return 3.0 * Q * Q / (tau * tau)


def _avar_bias_instability(tau: np.ndarray, fs: float, B: float) -> np.ndarray:
    return np.full_like(tau, BIAS_INSTABILITY_FACTOR * B * B)


def _avar_random_walk(tau: np.ndarray, fs: float, K: float) -> np.ndarray:
    return K * K * tau / 3.0


def _avar_rate_ramp(tau: np.ndarray, fs: float, R: float) -> np.ndarray:
    return 0.5 * R * R * tau * tau


def ar1_avar_shape(m: np.ndarray, b: float) -> np.ndarray:
    """Allan variance of a unit-variance point-sampled AR(1) process, per sigma^2.

    ``m`` is the averaging length in samples, ``b = 1/(fs T)`` the sampling interval over the
    correlation time (``a = exp(-b)``). Exact for any m >= 1:
    ``[m(1-a^2) - 2a(1-a^m) - a(1-a^m)^2] / (m^2 (1-a)^2)``. Evaluated in extended precision
    because the bracket cancels to O((m b)^3) when m b is small; relative error below 1e-6.
    """
    m_l = np.asarray(m, dtype=np.longdouble)
    b_l = np.longdouble(b)
    a = np.exp(-b_l)
    one_minus_a = -np.expm1(-b_l)
    one_minus_am = -np.expm1(-m_l * b_l)
    num = m_l * one_minus_a * (1 + a) - 2 * a * one_minus_am - a * one_minus_am**2
    # third-order expansion of the bracket in x = m b (relative error O(x)) where the
    # extended-precision bracket would lose more digits than the expansion drops
    x = m_l * b_l
    num = np.where(x < 1e-6, (x * b_l * b_l + 2 * x**3) / 3, num)
    out = num / (m_l * m_l * one_minus_a * one_minus_a)
    return np.maximum(out.astype(np.float64), 0.0)


def _avar_gauss_markov(tau: np.ndarray, fs: float, sigma: float, T: float) -> np.ndarray:
    return sigma * sigma * ar1_avar_shape(tau * fs, 1.0 / (fs * T))


def _avar_sinusoid(tau: np.ndarray, fs: float, A: float, f: float) -> np.ndarray:
    m = tau * fs
    s1 = np.sin(np.pi * f / fs)
    return A * A * np.sin(np.pi * f * tau) ** 4 / (m * m * s1 * s1)


def _avar_temperature(tau: np.ndarray, fs: float, coef: float,
                      temp_avar: np.ndarray | None = None) -> np.ndarray:
    if temp_avar is None:
        return np.zeros_like(tau)
    return coef * coef * np.broadcast_to(np.asarray(temp_avar, dtype=np.float64), tau.shape)


# --- one-sided PSDs --------------------------------------------------------------------------

def _psd_white(f: np.ndarray, fs: float, N: float) -> np.ndarray:
    return np.full_like(f, 2.0 * N * N)


def _psd_quantization(f: np.ndarray, fs: float, Q: float) -> np.ndarray:
    # rate = first difference of a white angle error of variance Q^2, times fs
    return 8.0 * Q * Q * fs * np.sin(np.pi * f / fs) ** 2


def _psd_bias_instability(f: np.ndarray, fs: float, B: float) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return B * B / (np.pi * f)


def _psd_random_walk(f: np.ndarray, fs: float, K: float) -> np.ndarray:
    # interval averages of a Wiener process: increments are MA(1) with r0 = 2/3, r1 = 1/6
    w = 2.0 * np.pi * f / fs
    with np.errstate(divide="ignore"):
        return K * K * (2.0 + np.cos(w)) / (6.0 * fs * fs * np.sin(w / 2.0) ** 2)


def _psd_rate_ramp(f: np.ndarray, fs: float, R: float) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return 2.0 * R * R / (2.0 * np.pi * f) ** 3


def _psd_gauss_markov(f: np.ndarray, fs: float, sigma: float, T: float) -> np.ndarray:
    b = 1.0 / (fs * T)
    a = math.exp(-b)
    one_minus_a2 = -math.expm1(-2.0 * b)
    w = 2.0 * np.pi * f / fs
    # 1 - 2a cos w + a^2 = (1-a)^2 + 4a sin^2(w/2), written to avoid cancellation
    den = (-math.expm1(-b)) ** 2 + 4.0 * a * np.sin(w / 2.0) ** 2
    return 2.0 * sigma * sigma * one_minus_a2 / (fs * den)


def _psd_sinusoid(fgrid: np.ndarray, fs: float, A: float, f: float,
                  bandwidth_hz: float | None = None) -> np.ndarray:
    # A line of power A^2/2 cannot be evaluated pointwise: it is spread over one resolution
    # bandwidth (default: the spacing of the frequency grid) at the grid point nearest f.
    if bandwidth_hz is None:
        bandwidth_hz = float(np.median(np.diff(fgrid))) if fgrid.size > 1 else fs / 2.0
    out = np.zeros_like(fgrid)
    nearest = int(np.argmin(np.abs(fgrid - f)))
    if abs(fgrid[nearest] - f) <= bandwidth_hz:
        out[nearest] = 0.5 * A * A / bandwidth_hz
    return out


def _psd_temperature(f: np.ndarray, fs: float, coef: float,
                     temp_psd: np.ndarray | None = None) -> np.ndarray:
    if temp_psd is None:
        return np.zeros_like(f)
    return coef * coef * np.broadcast_to(np.asarray(temp_psd, dtype=np.float64), f.shape)


# --- the registry ----------------------------------------------------------------------------

_BIG = 1.0e3

TERMS: dict[str, Term] = {}


def _register(term: Term) -> None:
    TERMS[term.name] = term


_register(Term(
    name="white",
    params=(Param("N", "rate/sqrt(Hz)", 0.0, 10.0, "white-noise density (angle/velocity random "
                                                   "walk coefficient)"),),
    allan_signature="N^2/tau (slope -1/2 on the Allan deviation)",
    effect="angle (velocity) random walk",
    explanation=(
        "Thermo-mechanical and electronic white noise on the rate. Integrated, it makes the "
        "angle (or velocity) wander as a random walk. On the Allan deviation it is a straight "
        "line of slope -1/2 that dominates short averaging times; N is read at tau = 1 s. "
        "Its spectrum is flat: 2 N^2 one-sided."),
    avar_fn=_avar_white, psd_fn=_psd_white, linear=True))

_register(Term(
    name="quantization",
    params=(Param("Q", "angle", 0.0, 10.0, "angle (velocity) quantization step / sqrt(12)"),),
    allan_signature="3 Q^2/tau^2 (slope -1)",
    effect="angle quantization",
    explanation=(
        "The converter rounds the integrated angle (or velocity) to a finite step, adding a "
        "white error to the angle, i.e. a differenced white error to the rate. It shows as a "
        "slope -1 on the Allan deviation at the shortest averaging times, steeper than white "
        "noise, and as a spectrum rising with frequency (8 Q^2 fs sin^2(pi f/fs))."),
    avar_fn=_avar_quantization, psd_fn=_psd_quantization, linear=True))

_register(Term(
    name="bias_instability",
    params=(Param("B", "rate", 0.0, 10.0, "flicker bias-instability coefficient"),),
    allan_signature="(2 ln2/pi) B^2 (flat)",
    effect="flicker (1/f) bias noise",
    explanation=(
        "The bias drifts with flicker (1/f) noise from the electronics and material defects, "
        "with no single time constant. The Allan deviation flattens into a floor of "
        "0.664 B near its minimum, and the spectrum falls as 1/f (B^2/(pi f) one-sided). "
        "It sets the best bias a filter can hope to hold."),
    avar_fn=_avar_bias_instability, psd_fn=_psd_bias_instability, linear=True))

_register(Term(
    name="random_walk",
    params=(Param("K", "rate/sqrt(s)", 0.0, 10.0, "rate random walk coefficient"),),
    allan_signature="K^2 tau/3 (slope +1/2)",
    effect="rate random walk",
    explanation=(
        "The bias itself performs a random walk (integrated white noise, often thermal or "
        "ageing effects), so it keeps wandering further the longer one waits. It rises as a "
        "slope +1/2 on the Allan deviation at long averaging times (K read at tau = 3 s) and "
        "falls as 1/f^2 in the spectrum."),
    avar_fn=_avar_random_walk, psd_fn=_psd_random_walk, linear=True))

_register(Term(
    name="rate_ramp",
    params=(Param("R", "rate/s", 0.0, 10.0, "rate ramp (drift rate)"),),
    allan_signature="R^2 tau^2/2 (slope +1)",
    effect="slow monotonic drift",
    explanation=(
        "A slow, steady drift of the bias over the whole record, for instance while the "
        "sensor warms up. It is deterministic rather than noise: the Allan deviation climbs "
        "with slope +1 at the longest averaging times; the spectrum (conventionally "
        "2 R^2/(2 pi f)^3) piles up at the lowest frequencies."),
    avar_fn=_avar_rate_ramp, psd_fn=_psd_rate_ramp, linear=True))

_register(Term(
    name="gauss_markov",
    params=(Param("sigma", "rate", 0.0, _BIG, "standard deviation of the correlated bias"),
            Param("T", "s", 0.0, 1.0e8, "correlation time")),
    allan_signature="bump near tau = 1.9 T: sigma^2 tau/T rising, sigma^2 T/tau falling",
    effect="exponentially correlated bias (first-order Markov)",
    explanation=(
        "A bias that wanders but is pulled back to its mean with a single correlation time "
        "T, as a thermal or mechanical process with one time constant. On the Allan deviation "
        "it makes a hump peaking near tau = 1.9 T (about 0.62 sigma); in the spectrum a flat "
        "level below 1/(2 pi T) rolling off as 1/f^2 above it."),
    avar_fn=_avar_gauss_markov, psd_fn=_psd_gauss_markov, linear=False))

_register(Term(
    name="sinusoid",
    params=(Param("A", "rate", 0.0, _BIG, "amplitude"),
            Param("f", "Hz", 0.0, math.inf, "frequency")),
    allan_signature="A^2 sin^4(pi f tau)/(pi f tau)^2: oscillating, peak near tau = 0.37/f",
    effect="vibration, pump, fan or mains pickup",
    explanation=(
        "A periodic disturbance at one frequency: a fan, pump, vibration of the mount or "
        "mains pickup. The Allan deviation shows a bump near tau = 0.37/f followed by "
        "ripples that fall off as 1/tau, with dips where tau is a whole number of periods; "
        "the spectrum has a sharp line at f holding power A^2/2."),
    avar_fn=_avar_sinusoid,
    psd_fn=_psd_sinusoid,
    linear=False))

_register(Term(
    name="temperature",
    params=(Param("coef", "rate/degC", -10.0, 10.0, "bias change per degree Celsius",
                  lo_open=False),),
    allan_signature="coef^2 x Allan variance of the temperature record",
    effect="thermal sensitivity of the bias",
    explanation=(
        "The bias follows the sensor temperature. Its Allan and spectral signature copy "
        "those of the temperature record scaled by coef^2, usually a slow rise at long "
        "averaging times. It is removed by regressing the rate on the recorded temperature; "
        "the remaining terms are then judged on the corrected series."),
    avar_fn=_avar_temperature, psd_fn=_psd_temperature, linear=False))


TERM_NAMES: tuple[str, ...] = tuple(TERMS)
"""All term names in the order of the contract's table."""


# --- helpers ---------------------------------------------------------------------------------

def get_term(name: str) -> Term:
    """The term called ``name``; :class:`TermError` naming the valid terms otherwise."""
    try:
        return TERMS[name]
    except KeyError:
        raise TermError(f"unknown term {name!r}; valid terms: {', '.join(TERM_NAMES)}") from None


def parse_terms(text: str | Sequence[str]) -> list[str]:
    """Term names from ``"white,bias_instability"`` (or a list); validates and de-duplicates."""
    names = [s.strip() for s in text.split(",")] if isinstance(text, str) else list(text)
    names = [n for n in names if n]
    if not names:
        raise TermError(f"empty model; valid terms: {', '.join(TERM_NAMES)}")
    unknown = [n for n in names if n not in TERMS]
    if unknown:
        raise TermError(f"unknown term(s) {', '.join(unknown)}; valid terms: "
                        f"{', '.join(TERM_NAMES)}")
    seen: list[str] = []
    for n in names:
        if n in seen and n not in ("gauss_markov", "sinusoid"):
            raise TermError(f"term {n!r} given twice")
        seen.append(n)
    return names


def validate_params(name: str, params: dict[str, float], fs_hz: float | None = None) -> None:
    """Raise :class:`TermError` naming any parameter that is missing, unknown, not finite or
    outside its physical range (a frequency must also lie below the Nyquist frequency)."""
    term = get_term(name)
    _only(term, params)
    for p in term.params:
        v = float(params[p.name])
        hi = p.hi
        if p.name == "f" and fs_hz is not None:
            hi = fs_hz / 2.0
        bad_lo = v <= p.lo if p.lo_open else v < p.lo
        if not math.isfinite(v) or bad_lo or v > hi:
            lo_txt = f"({p.lo:g}" if p.lo_open else f"[{p.lo:g}"
            raise TermError(f"{name}.{p.name} = {v:g} outside its physical range "
                            f"{lo_txt}, {hi:g}]")


_RATE_UNITS = {"rad/s": ("rad", "rad/s^2"), "m/s^2": ("m/s", "m/s^3"), "deg/s": ("deg",
                                                                              "deg/s^2")}


def param_unit(param: Param, channel_units: str = "rad/s") -> str:
    """Unit string of a parameter for a channel whose samples are in ``channel_units``."""
    angle, ramp = _RATE_UNITS.get(channel_units, (f"{channel_units}*s", f"{channel_units}/s"))
    return {
        "rate/sqrt(Hz)": f"{channel_units}/sqrt(Hz)",
        "angle": angle,
        "rate": channel_units,
        "rate/sqrt(s)": f"{channel_units}/sqrt(s)",
        "rate/s": ramp,
        "s": "s",
        "Hz": "Hz",
        "rate/degC": f"{channel_units}/degC",
    }[param.kind]


def model_avar(model: Sequence[tuple[str, dict[str, float]]], tau_s: np.ndarray,
               fs_hz: float) -> np.ndarray:
    """Allan variance of a sum of independent terms (the terms' variances add)."""
    tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
    total = np.zeros_like(tau)
    for name, params in model:
        total += get_term(name).avar(tau, fs_hz, **params)
    return total


def model_psd(model: Sequence[tuple[str, dict[str, float]]], f_hz: np.ndarray,
              fs_hz: float) -> np.ndarray:
    """One-sided PSD of a sum of independent terms."""
    f = np.atleast_1d(np.asarray(f_hz, dtype=np.float64))
    total = np.zeros_like(f)
    for name, params in model:
        total += get_term(name).psd(f, fs_hz, **params)
    return total
