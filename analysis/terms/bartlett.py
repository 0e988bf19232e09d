"""Bartlett output filter: two moving averages of L taps in cascade (triangular weights).

The ADIS16350 and ADIS16405 filter their outputs this way; ``SENS_AVG`` sets L = 2^n."""

from __future__ import annotations

import numpy as np

from imunoise.analysis.terms.base import Param
from imunoise.analysis.terms.moving_average import COLD_TAPS, MAX_TAPS, boxcar, whole_taps
from imunoise.analysis.terms.moving_average import TERM as MOVING_AVERAGE
from imunoise.analysis.terms.output_filter import OutputFilter


class Bartlett(OutputFilter):
    name = "bartlett"
    order = 210
    params = (Param("taps", "samples", 1.0, MAX_TAPS, "taps of each of the two averaging "
                    "stages (L; 2L-1 triangular weights in all)", lo_open=False),)
    amplitude = "taps"
    allan_signature = "Allan deviation below the white-noise line at tau < 2L/fs"
    effect = "averaging output filter (Bartlett window)"
    explanation = (
        "The sensor passes its samples through two L-tap moving averages in cascade, a "
        "triangular (Bartlett) window of 2L-1 samples, as the ADIS16350/16405 do with their "
        "SENS_AVG setting. White noise is averaged, so the Allan deviation at the shortest "
        "averaging times falls below the slope -1/2 line; the spectrum rolls off as the "
        "square of the moving average's, (sin(pi f L/fs)/(L sin(pi f/fs)))^4.")
    small_default = {"taps": 1.5}

    def impulse_response(self, fs_hz, params):
        g = boxcar(float(params["taps"]))
        return np.convolve(g, g)

    def response(self, f, fs_hz, params):
        return MOVING_AVERAGE.response(f, fs_hz, params) ** 2

    def cold_grid(self, fs_hz):
        return [{"taps": t} for t in COLD_TAPS]

    def kink(self, params):
        return whole_taps(float(params["taps"]))

    def length(self, fs_hz, params):
        return 2.0 * float(params["taps"])


TERM = Bartlett()
