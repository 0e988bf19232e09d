"""The filter a record's channels share, its response measured from the other channels.

Its power response is the shape the record's other channels have in common with this one
(:mod:`imunoise.analysis.chain_shape`), raised to ``depth`` (1: as measured). It needs that
shape: the commands that read a record install it (``fit``, ``diagnose``); anywhere else the
term is not available and naming it is an error that says why.
"""

from __future__ import annotations

import math
from typing import Any

from imunoise.analysis import chain_shape
from imunoise.analysis.terms.base import Param, TermError
from imunoise.analysis.terms.output_filter import OutputFilter

DEPTH_BOUNDS = (0.5, 2.0)
"""Range of ``depth`` a fit may move it in: a channel filtered half as deep as the others, or
twice as deep, still has their shape; beyond that it is another filter."""


class ChainFilter(OutputFilter):
    name = "chain_filter"
    order = 240
    params = (Param("depth", "ratio", 0.0, 4.0,
                    "exponent of the measured response (1: as the other channels show it)"),)
    amplitude = "depth"
    live = False  # measured from a whole record's other channels
    needs_record = "channels"
    allan_signature = ("Allan deviation below the white-noise line at short tau, in the "
                       "shape the record's other channels share")
    effect = "the filter the record's channels share (measured from the other channels)"
    explanation = (
        "Every channel of the record passed through one filter before it was stored (a "
        "phone's decimation, a logger's smoothing): their spectra have one shape and no "
        "signal in common. The filter's power response is taken from the other channels "
        "(the geometric mean of their spectra, each divided by its median over fs/500 to "
        "fs/100; 1 below fs/100) and applied to this channel's noise terms; depth raises it "
        "to a power (1: as measured).")
    small_default = {"depth": 1.0}

    def usable(self) -> bool:
        return chain_shape.current() is not None

    def _shape(self) -> chain_shape.ChainShape:
        shape = chain_shape.current()
        if shape is None:
            raise TermError(
                "chain_filter needs the record's other channels: its response is the shape "
                "they share with this channel, which imunoise fit and diagnose measure from "
                "the file they read (imunoise analyze lists shared shapes); none is "
                "available here")
        return shape

    def _remember(self, key: tuple, make: Any) -> Any:
        # the same parameters mean another filter on another record
        return super()._remember((self._shape().token, *key), make)

    def log_fit_bounds(self, param, fs_hz, duration_s):
        return math.log(DEPTH_BOUNDS[0]), math.log(DEPTH_BOUNDS[1])

    def start_params(self, fs_hz):
        return {"depth": 1.0}

    def identity_params(self, fs_hz):
        # the measured response itself: the point of the term (depth towards 0 is no filter,
        # which the model without it already is)
        return {"depth": 1.0}

    def start_grid(self, fs_hz):
        # with the filter in place the noise amplitudes differ from the model's without it
        # (the unfiltered fit puts the filter's dip into the bias instability): each depth is
        # scored with every amplitude solved again
        return [{"depth": float(d)} for d in (0.7, 0.85, 1.0, 1.15, 1.4)]

    def impulse_response(self, fs_hz, params):
        return self._shape().impulse_response(float(params["depth"]))

    def _autocorrelation(self, fs_hz, params):
        shape = self._shape()
        return self._remember(("acf", fs_hz, tuple(sorted(params.items()))),
                              lambda: shape.autocorrelation(float(params["depth"])))

    def response(self, f, fs_hz, params):
        return self._shape().response(f, float(params["depth"]))

    def length(self, fs_hz, params):
        r = self._autocorrelation(fs_hz, params)
        return float(1.0 / r[len(r) // 2])

    def validate(self, params, fs_hz=None, partial=False):
        super().validate(params, fs_hz, partial)
        shape = chain_shape.current()
        if shape is not None and fs_hz is not None \
                and not math.isclose(shape.fs_hz, float(fs_hz), rel_tol=1e-6):
            raise TermError(f"chain_filter: the shared shape was measured at "
                            f"{shape.fs_hz:g} Hz, the channel is sampled at {float(fs_hz):g} Hz")


TERM = ChainFilter()

