"""Moving-average output filter: the mean of the last L samples (``taps``)."""

from __future__ import annotations

import math

import numpy as np

from imunoise.analysis.terms.base import Param
from imunoise.analysis.terms.output_filter import OutputFilter

MAX_TAPS = 1024.0

COLD_TAPS = (1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 11.0, 16.0, 23.0, 32.0)
"""Taps tried when an averaging filter is fitted beside terms that follow it in the model,
from no previous fit: the chi2 has a kink at every whole number of taps (a new tap starts to
take weight there), and a solve that starts on the wrong side of one stops at it (a
4-tap filter under a 20 Hz resonance was left at 3 taps, chi2 657 against 24 at the truth)."""


WHOLE_TAPS_TOLERANCE = 0.01
"""How near a whole number of taps a solve that stopped at the kink there ends (a 4-tap
filter under a resonance: 3.0017)."""


def whole_taps(taps: float) -> bool:
    """Whether ``taps`` lies within :data:`WHOLE_TAPS_TOLERANCE` of a whole number above one:
    a kink of the averaging filters' Allan variance, where the next tap starts to take
    weight."""
    return taps > 1.0 + WHOLE_TAPS_TOLERANCE \
        and abs(taps - round(taps)) < WHOLE_TAPS_TOLERANCE


def boxcar(taps: float) -> np.ndarray:
    """Weights of an L-tap moving average with unit sum. A non-integer L (the fit moves it
    continuously) weights its last tap by the fraction, so the filter, its response and its
    Allan variance pass smoothly through every integer L."""
    whole = int(math.floor(taps))
    frac = taps - whole
    g = np.ones(whole + (1 if frac > 1e-12 else 0))
    if frac > 1e-12:
        g[-1] = frac
    return g / taps


def _fractional_response(u: np.ndarray, taps: float) -> np.ndarray:
    """``|G|^2`` at ``u = f/fs`` of :func:`boxcar` weights for a non-integer ``taps``: W whole
    taps and a last one of weight ``frac``. With the Dirichlet kernel
    ``D = sin(pi u W) / sin(pi u)`` the sum of the W unit phasors is ``D`` turned by
    ``pi u (W - 1)``, and the last tap adds ``frac`` turned by ``2 pi u W``, so
    ``|G|^2 = (D^2 + frac^2 + 2 frac D cos(pi u (W + 1))) / taps^2`` (the sum over the taps in
    closed form; at ``u = 0`` the response is 1)."""
    whole = int(math.floor(taps))
    frac = taps - whole
    s1 = np.sin(np.pi * u)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.sin(np.pi * u * whole) / s1
    d = np.where(np.abs(s1) < 1e-12, float(whole), d)
    out = (d * d + frac * frac + 2.0 * frac * d * np.cos(np.pi * u * (whole + 1))) / (taps * taps)
    return np.maximum(out, 0.0)


class MovingAverage(OutputFilter):
    name = "moving_average"
    order = 200
    params = (Param("taps", "samples", 1.0, MAX_TAPS, "number of samples averaged (L)",
                    lo_open=False),)
    amplitude = "taps"
    allan_signature = ("Allan deviation below the white-noise line at tau < L/fs: "
                       "N^2/tau - N^2 (L^2-1)/(2 L fs tau^2) once tau >= L/fs")
    effect = "averaging output filter (moving average)"
    explanation = (
        "The sensor outputs the mean of its last L internal samples (a FIR moving average, "
        "what an averaging or decimation setting does). White noise is averaged over L "
        "samples, so the Allan deviation at the shortest averaging times falls below the "
        "slope -1/2 line and joins it near tau = L/fs; the spectrum rolls off as "
        "sin^2(pi f L/fs)/(L sin(pi f/fs))^2 with its first zero at fs/L.")
    small_default = {"taps": 1.5}

    def impulse_response(self, fs_hz, params):
        return boxcar(float(params["taps"]))

    def cold_grid(self, fs_hz):
        return [{"taps": t} for t in COLD_TAPS]

    def kink(self, params):
        return whole_taps(float(params["taps"]))

    def response(self, f, fs_hz, params):
        taps = float(params["taps"])
        if abs(taps - round(taps)) > 1e-12:
            # in closed form, not summed over the taps: (bins x taps) sines and cosines cost
            # a second per evaluation near MAX_TAPS, and 1.7 times the closed form's time
            # even at 2.5 taps
            return _fractional_response(np.atleast_1d(np.asarray(f, dtype=np.float64))
                                        / fs_hz, taps)
        u = np.atleast_1d(np.asarray(f, dtype=np.float64)) / fs_hz
        with np.errstate(invalid="ignore", divide="ignore"):
            out = (np.sin(np.pi * u * taps) / (taps * np.sin(np.pi * u))) ** 2
        return np.where(np.abs(np.sin(np.pi * u)) < 1e-12, 1.0, out)

    def length(self, fs_hz, params):
        return float(params["taps"])


TERM = MovingAverage()
