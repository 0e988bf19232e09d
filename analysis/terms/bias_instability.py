"""Bias instability (flicker, 1/f noise), B.

Its Allan variance is the ideal plateau ``(2 ln2/pi) B^2`` at every tau. The simulator is a
sum of first-order Markov processes with correlation times spaced ``FLICKER_PER_DECADE`` per
decade across a band (default half a sample period to 1e5 s), each of variance
``B^2 ln(r)/pi`` for the spacing ratio r: this reproduces the 1/f spectrum ``B^2/(pi f)``
between the band's edges. Its Allan variance is flat at the plateau within 3.5 % for tau from
4 sample periods to ``t_max/10`` (+20 % at one sample period, +4 % at two); see
:func:`flicker_avar` and :func:`flicker_flat_band`.
"""

from __future__ import annotations

import math

import numpy as np

from imunoise.analysis.terms.base import Param, Term
from imunoise.analysis.terms.gauss_markov import (
    Ar1Bank,
    ar1_avar_shape,
    ar1_psd,
    half_angle_sin2,
)

BIAS_INSTABILITY_FACTOR = 2.0 * math.log(2.0) / math.pi
"""Allan variance plateau of flicker noise per B^2: sigma^2 = (2 ln2/pi) B^2."""

FLICKER_PER_DECADE = 3
"""Markov processes per decade of correlation time in the flicker simulator."""

DEFAULT_FLICKER_TMAX_S = 1.0e5

Band = tuple[float | None, float | None]


def flicker_times(fs_hz: float, band_s: Band = (None, None)) -> tuple[np.ndarray, float]:
    """Correlation times (s) of the flicker simulator and their log spacing ratio r."""
    t_lo = band_s[0] if band_s[0] is not None else 0.5 / fs_hz
    t_hi = band_s[1] if band_s[1] is not None else DEFAULT_FLICKER_TMAX_S
    if not (0 < t_lo < t_hi):
        raise ValueError(f"bad flicker band {band_s}: need 0 < t_min < t_max")
    n = int(math.ceil(math.log10(t_hi / t_lo) * FLICKER_PER_DECADE)) + 1
    times = np.geomspace(t_lo, t_hi, n)
    ratio = float(times[1] / times[0])
    return times, ratio


def flicker_avar(tau_s: np.ndarray, fs_hz: float, B: float, band_s: Band = (None, None)
                 ) -> np.ndarray:
    """Exact Allan variance of the flicker simulator (sum of its Markov processes)."""
    times, ratio = flicker_times(fs_hz, band_s)
    var_each = B * B * math.log(ratio) / math.pi
    m = np.asarray(tau_s, dtype=np.float64) * fs_hz
    return var_each * sum(ar1_avar_shape(m, 1.0 / (fs_hz * t)) for t in times)


def flicker_psd(f_hz: np.ndarray, fs_hz: float, B: float, band_s: Band = (None, None)
                ) -> np.ndarray:
    """Exact one-sided PSD of the flicker simulator (sum of its Markov processes)."""
    times, ratio = flicker_times(fs_hz, band_s)
    sd = B * math.sqrt(math.log(ratio) / math.pi)
    # the grid's sines once for all the processes (they were most of the time)
    sin2 = half_angle_sin2(np.atleast_1d(np.asarray(f_hz, dtype=np.float64)), float(fs_hz))
    return sum(ar1_psd(sin2, float(fs_hz), sd, float(t)) for t in times)


def flicker_flat_band(fs_hz: float, t_max_s: float = DEFAULT_FLICKER_TMAX_S
                      ) -> tuple[float, float]:
    """Tau band (s) where the flicker simulator's Allan variance is within 3.5 % of the
    plateau (default band of correlation times ending at ``t_max_s``)."""
    return 4.0 / fs_hz, t_max_s / 10.0


class BiasInstability(Term):
    name = "bias_instability"
    order = 30
    params = (Param("B", "rate", 0.0, 10.0, "flicker bias-instability coefficient"),)
    amplitude = "B"
    linear = True
    allan_signature = "(2 ln2/pi) B^2 (flat)"
    effect = "flicker (1/f) bias noise"
    explanation = (
        "The bias drifts with flicker (1/f) noise from the electronics and material defects, "
        "with no single time constant. The Allan deviation flattens into a floor of "
        "0.664 B near its minimum, and the spectrum falls as 1/f (B^2/(pi f) one-sided). "
        "It sets the best bias a filter can hope to hold.")
    small_default = {"B": 1e-7}

    def _avar(self, tau: np.ndarray, fs: float, B: float) -> np.ndarray:
        return np.full_like(tau, BIAS_INSTABILITY_FACTOR * B * B)

    def _psd(self, f: np.ndarray, fs: float, B: float) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return B * B / (np.pi * f)

    def simulator(self, params, fs_hz, rng, flicker_band_s: Band = (None, None), **options):
        times, ratio = flicker_times(fs_hz, flicker_band_s)
        sd = float(params["B"]) * math.sqrt(math.log(ratio) / math.pi)
        return Ar1Bank(rng, fs_hz, times, np.full(len(times), sd))

    def add_discrete(self, dm, params):
        # approximated by Markov states once the whole model is known (imunoise.analysis.discrete)
        dm.flicker_B = float(np.hypot(dm.flicker_B, params["B"]))


TERM = BiasInstability()
