"""First-order low-pass output filter with a cutoff frequency: the filter of a sensor whose
filter is not known, fitted from the data; a single-pole digital filter
``y_k = a y_{k-1} + (1-a) x_k`` with ``a = exp(-2 pi f_c / fs)``."""

from __future__ import annotations

import math

import numpy as np

from imunoise.analysis.terms.base import Param, TermError
from imunoise.analysis.terms.output_filter import OutputFilter

_MIN_CUTOFF_OVER_FS = 1.0e-3
_TAIL = 1.0e-12


def _pole(fs_hz: float, cutoff: float) -> float:
    return math.exp(-2.0 * math.pi * cutoff / fs_hz)


class Lowpass(OutputFilter):
    name = "lowpass"
    order = 220
    params = (Param("fc", "Hz", 0.0, 1.0e9, "cutoff (-3 dB) frequency of the pole"),)
    amplitude = "fc"
    ripple = False
    allan_signature = "Allan deviation below the white-noise line at tau < 1/(2 pi fc)"
    effect = "low-pass output filter (first order)"
    explanation = (
        "The sensor's output passes a low-pass filter whose design is not known (an "
        "anti-aliasing stage, a digital low-pass, a phone's decimation). Modelled as a single "
        "pole at fc: white noise is smoothed over about fs/(2 pi fc) samples, so the Allan "
        "deviation at the shortest averaging times falls below the slope -1/2 line; the "
        "spectrum falls as 1/(1 + (f/fc)^2) above fc.")
    small_default = {"fc": 1.0}

    def validate(self, params, fs_hz=None, partial=False):
        super().validate(params, fs_hz, partial)
        fc = params.get("fc")
        if fs_hz is not None and fc is not None and float(fc) < _MIN_CUTOFF_OVER_FS * fs_hz:
            raise TermError(f"lowpass.fc = {float(fc):g} Hz is below fs/1000 "
                            f"({_MIN_CUTOFF_OVER_FS * fs_hz:g} Hz): such a slow pole is a "
                            f"Markov bias, not an output filter (use gauss_markov)")

    def log_fit_bounds(self, param, fs_hz, duration_s):
        # fs/1000 to Nyquist: a slower pole is a Markov bias
        return math.log(_MIN_CUTOFF_OVER_FS * fs_hz), math.log(0.5 * fs_hz)

    def start_params(self, fs_hz):
        return {"fc": 0.3 * fs_hz}

    def identity_params(self, fs_hz):
        # the upper bound: a pole at Nyquist passes the band almost unchanged
        return {"fc": 0.5 * fs_hz}

    def start_grid(self, fs_hz):
        # a cutoff from fs/200 to 0.45 fs, four per octave: the chi2 of a model that misses
        # elsewhere has several valleys in fc, and the solve from one start ends in whichever
        # the last bits of the Allan sums favour
        return [{"fc": float(fc)} for fc in np.geomspace(fs_hz / 200.0, 0.45 * fs_hz, 27)]

    def coefficients(self, fs_hz, params):
        a = _pole(fs_hz, float(params["fc"]))
        return np.array([1.0 - a]), np.array([1.0, -a])

    def impulse_response(self, fs_hz, params):
        a = _pole(fs_hz, float(params["fc"]))
        n = max(int(math.ceil(math.log(_TAIL) / math.log(a))), 1) if a > 0 else 1
        return (1.0 - a) * a ** np.arange(n, dtype=np.float64)

    def _autocorrelation(self, fs_hz, params):
        # closed form (1-a)/(1+a) a^|k|, cut where it has decayed below 1e-12
        def make() -> np.ndarray:
            a = _pole(fs_hz, float(params["fc"]))
            n = max(int(math.ceil(math.log(_TAIL) / math.log(a))), 1) if a > 0 else 1
            half = (1.0 - a) / (1.0 + a) * a ** np.arange(n, dtype=np.float64)
            return np.concatenate((half[:0:-1], half))
        return self._remember(("acf", fs_hz, tuple(sorted(params.items()))), make)

    def response(self, f, fs_hz, params):
        a = _pole(fs_hz, float(params["fc"]))
        w = 2.0 * np.pi * np.atleast_1d(np.asarray(f, dtype=np.float64)) / fs_hz
        return (1.0 - a) ** 2 / ((1.0 - a) ** 2 + 4.0 * a * np.sin(w / 2.0) ** 2)

    def length(self, fs_hz, params):
        a = _pole(fs_hz, float(params["fc"]))
        return (1.0 + a) / (1.0 - a)


TERM = Lowpass()
