"""Seeded, stateful simulation of the noise terms, block by block with bounded memory.

``NoiseStream(model, fs_hz, seed).take(n)`` returns the next ``n`` samples (SI units) of the sum
of the model's terms. Each term draws from its own child generator of ``seed``, always in sample
order, so a run taken in blocks equals one long run: ``take(1000)`` ten times gives exactly the
samples of a fresh ``take(10000)``. Memory is a few numbers per term whatever the run length.

Simulators (``Ts = 1/fs``):

* ``white``: independent Gaussian samples of variance ``N^2 fs``.
* ``quantization``: ``(e_k - e_{k-1}) fs`` with ``e`` Gaussian white of variance ``Q^2``, the
  rounding error of the integrated angle. Rounding error is closer to uniform, but the Allan
  variance and spectrum depend only on its variance, and a Gaussian error keeps the simulated
  data inside the Gaussian model that the misfit statistics assume.
* ``bias_instability``: a sum of first-order Markov processes with correlation times spaced
  ``FLICKER_PER_DECADE`` per decade across ``flicker_band_s`` (default half a sample period
  to 1e5 s), each of variance ``B^2 ln(r)/pi`` for the spacing ratio r: this reproduces the
  1/f spectrum ``B^2/(pi f)`` between the band's edges. Its Allan variance is flat at
  ``(2 ln2/pi) B^2`` within 3.5 % for tau from 4 sample periods to ``t_max/10`` (+20 % at one
  sample period, +4 % at two); see :func:`flicker_avar`, :func:`flicker_flat_band` and the
  tests.
* ``random_walk``: interval averages of a Wiener process of intensity ``K^2`` (exact
  ``K^2 tau/3``).
* ``rate_ramp``: ``R t`` at the interval mid-points ``t = (k + 1/2) Ts`` from the stream start.
* ``gauss_markov``: ``x_k = a x_{k-1} + w_k``, ``a = exp(-Ts/T)``, started in its stationary
  distribution.
* ``sinusoid``: ``A sin(2 pi f k Ts + phi)`` with a random phase drawn once.
* ``temperature``: ``coef (temperature - temperature[0])``, the temperature record (degC) passed
  to :meth:`NoiseStream.take`; the reference is the first temperature sample the stream saw.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.signal import lfilter

from analysis.terms import BIAS_INSTABILITY_FACTOR, ar1_avar_shape, get_term, validate_params

FLICKER_PER_DECADE = 3
"""Markov processes per decade of correlation time in the flicker simulator."""

DEFAULT_FLICKER_TMAX_S = 1.0e5

Model = Sequence[tuple[str, dict[str, float]]]


def flicker_times(fs_hz: float, band_s: tuple[float | None, float | None] = (None, None)
                  ) -> tuple[np.ndarray, float]:
    """Correlation times (s) of the flicker simulator and their log spacing ratio r."""
    t_lo = band_s[0] if band_s[0] is not None else 0.5 / fs_hz
    t_hi = band_s[1] if band_s[1] is not None else DEFAULT_FLICKER_TMAX_S
    if not (0 < t_lo < t_hi):
        raise ValueError(f"bad flicker band {band_s}: need 0 < t_min < t_max")
    n = int(math.ceil(math.log10(t_hi / t_lo) * FLICKER_PER_DECADE)) + 1
    times = np.geomspace(t_lo, t_hi, n)
    ratio = float(times[1] / times[0])
    return times, ratio


def flicker_avar(tau_s: np.ndarray, fs_hz: float, B: float,
                 band_s: tuple[float | None, float | None] = (None, None)) -> np.ndarray:
    """Exact Allan variance of the flicker simulator (sum of its Markov processes)."""
    times, ratio = flicker_times(fs_hz, band_s)
    var_each = B * B * math.log(ratio) / math.pi
    m = np.asarray(tau_s, dtype=np.float64) * fs_hz
    return var_each * sum(ar1_avar_shape(m, 1.0 / (fs_hz * t)) for t in times)


class _Ar1Bank:
    """Parallel AR(1) processes x_k = a x_{k-1} + w_k with stationary start."""

    def __init__(self, rng: np.random.Generator, fs_hz: float, times: np.ndarray,
                 sigmas: np.ndarray) -> None:
        self.rng = rng
        b = 1.0 / (fs_hz * np.asarray(times, dtype=np.float64))
        self.a = np.exp(-b)
        self.w_sd = np.asarray(sigmas) * np.sqrt(-np.expm1(-2.0 * b))
        self.x = rng.standard_normal(len(self.a)) * np.asarray(sigmas)

    def take(self, n: int) -> np.ndarray:
        w = self.rng.standard_normal((n, len(self.a))) * self.w_sd
        out = np.zeros(n)
        for j, a in enumerate(self.a):
            y, zf = lfilter([1.0], [1.0, -a], w[:, j], zi=[a * self.x[j]])
            self.x[j] = y[-1] if n else self.x[j]
            out += y
            del zf
        return out


class _TermSim:
    def __init__(self, name: str, params: dict[str, float], fs_hz: float,
                 rng: np.random.Generator, flicker_band_s: tuple[float | None, float | None]
                 ) -> None:
        self.name = name
        self.p = {k: float(v) for k, v in params.items()}
        self.fs = fs_hz
        self.rng = rng
        self.k = 0
        if name == "quantization":
            self.e_prev = rng.standard_normal() * self.p["Q"]
        elif name == "bias_instability":
            times, ratio = flicker_times(fs_hz, flicker_band_s)
            sd = self.p["B"] * math.sqrt(math.log(ratio) / math.pi)
            self.bank = _Ar1Bank(rng, fs_hz, times, np.full(len(times), sd))
        elif name == "random_walk":
            self.w = 0.0
        elif name == "gauss_markov":
            self.bank = _Ar1Bank(rng, fs_hz, np.array([self.p["T"]]),
                                 np.array([self.p["sigma"]]))
        elif name == "sinusoid":
            self.phase = rng.uniform(0.0, 2.0 * math.pi)
        elif name == "temperature":
            self.t_ref: float | None = None

    def take(self, n: int, temperature: np.ndarray | None) -> np.ndarray:
        fs, p = self.fs, self.p
        k = np.arange(self.k, self.k + n, dtype=np.float64)
        self.k += n
        if self.name == "white":
            return self.rng.standard_normal(n) * (p["N"] * math.sqrt(fs))
        if self.name == "quantization":
            e = np.concatenate(([self.e_prev], self.rng.standard_normal(n) * p["Q"]))
            self.e_prev = e[-1]
            return np.diff(e) * fs
        if self.name in ("bias_instability", "gauss_markov"):
            return self.bank.take(n)
        if self.name == "random_walk":
            z = self.rng.standard_normal((n, 2))
            step = p["K"] / math.sqrt(fs)
            # running sum seeded with the state: the same additions in the same order as one
            # long run, so block boundaries leave no trace even in the last bit
            path = np.cumsum(np.concatenate(([self.w], z[:, 0] * step)))
            self.w = float(path[-1])
            return path[:-1] + step * (0.5 * z[:, 0] + z[:, 1] / math.sqrt(12.0))
        if self.name == "rate_ramp":
            return p["R"] * (k + 0.5) / fs
        if self.name == "sinusoid":
            return p["A"] * np.sin(2.0 * math.pi * p["f"] * k / fs + self.phase)
        if self.name == "temperature":
            if temperature is None:
                raise ValueError("the temperature term needs a temperature record: "
                                 "take(n, temperature=array_degC)")
            temp = np.asarray(temperature, dtype=np.float64)
            if temp.shape != (n,):
                raise ValueError(f"temperature must have shape ({n},), got {temp.shape}")
            if self.t_ref is None and n:
                self.t_ref = float(temp[0])
            return p["coef"] * (temp - (self.t_ref or 0.0))
        raise AssertionError(self.name)


class NoiseStream:
    """Seeded generator of a noise model's samples, continuing across calls.

    Args:
        model: ``[(term, {param: value})]`` in SI units (see :mod:`analysis.terms`).
        fs_hz: sampling rate in Hz.
        seed: seed of the generator (``None``: fresh entropy).
        flicker_band_s: ``(t_min, t_max)`` correlation-time band of the flicker simulator in s
            (``None`` entries: half a sample period and 1e5 s).
    """

    def __init__(self, model: Model, fs_hz: float, seed: int | None = None,
                 flicker_band_s: tuple[float | None, float | None] = (None, None)) -> None:
        if not (fs_hz > 0 and math.isfinite(fs_hz)):
            raise ValueError(f"sampling rate must be positive, got {fs_hz}")
        for name, params in model:
            get_term(name)
            validate_params(name, dict(params), fs_hz)
        self.model = [(name, dict(params)) for name, params in model]
        self.fs_hz = float(fs_hz)
        children = np.random.SeedSequence(seed).spawn(len(self.model))
        self._sims = [_TermSim(name, params, self.fs_hz, np.random.default_rng(ss),
                               flicker_band_s)
                      for (name, params), ss in zip(self.model, children, strict=True)]
        self.samples_taken = 0

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        """The next ``n`` samples (float64, SI units). ``temperature`` (degC, length n) is
        required when the model holds a ``temperature`` term."""
        n = int(n)
        if n < 0:
            raise ValueError("n must be >= 0")
        out = np.zeros(n)
        for sim in self._sims:
            out += sim.take(n, temperature)
        self.samples_taken += n
        return out

    def take_terms(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        """Like :meth:`take` but one row per term (shape ``(len(model), n)``)."""
        rows = np.stack([sim.take(int(n), temperature) for sim in self._sims]) if self._sims \
            else np.zeros((0, int(n)))
        self.samples_taken += int(n)
        return rows


def simulate(model: Model, n: int, fs_hz: float, rng: int | np.random.Generator | None = None,
             temperature: np.ndarray | None = None) -> np.ndarray:
    """``n`` samples of ``model`` at ``fs_hz`` in one call (see :class:`NoiseStream`).

    ``rng`` may be a seed or a Generator (a seed is then drawn from it)."""
    seed = int(rng.integers(2**63)) if isinstance(rng, np.random.Generator) else rng
    return NoiseStream(model, fs_hz, seed).take(n, temperature=temperature)


def flicker_flat_band(fs_hz: float, t_max_s: float = DEFAULT_FLICKER_TMAX_S
                      ) -> tuple[float, float]:
    """Tau band (s) where the flicker simulator's Allan variance is within 3.5 % of the
    plateau (default band of correlation times ending at ``t_max_s``)."""
    return 4.0 / fs_hz, t_max_s / 10.0


def flicker_psd(f_hz: np.ndarray, fs_hz: float, B: float,
                band_s: tuple[float | None, float | None] = (None, None)) -> np.ndarray:
    """Exact one-sided PSD of the flicker simulator (sum of its Markov processes)."""
    times, ratio = flicker_times(fs_hz, band_s)
    sd = B * math.sqrt(math.log(ratio) / math.pi)
    gm = get_term("gauss_markov")
    return sum(gm.psd(f_hz, fs_hz, sigma=sd, T=float(t)) for t in times)


__all__ = ["NoiseStream", "simulate", "flicker_avar", "flicker_times", "flicker_flat_band",
           "flicker_psd", "BIAS_INSTABILITY_FACTOR", "FLICKER_PER_DECADE"]
