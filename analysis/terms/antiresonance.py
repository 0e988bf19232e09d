"""A resonance with an anti-resonance beside it: the AR(2) resonance of
:mod:`imunoise.analysis.terms.resonance` passed through a pair of zeros on the unit circle at
frequency ``fa``, the pair's gain 1 at 0 Hz.

A sensor that sees a structural mode through the path between two points (a proof mass
coupled to its frame, a gyro's sense and drive loops) has a transfer function with a pole pair
at the mode and a zero pair beside it: the spectrum dips below its floor on one side of the
peak and stands above a resonance's skirt on the other. ADIS16405 run 1 gyro_z: a resonance
at 20 Hz leaves the measured PSD at 0.70 of the model at 17 Hz and 1.26 at 24 Hz (Whittle
deviance 47 per point with every parameter fitted to the spectrum); zeros at 14.3 Hz take it
to 3.3.

The zeros sit on the unit circle (an undamped anti-resonance): the dip's depth is then set by
the noise added after the mode (the white level), and the model is identifiable. Zeros of
any damping beside a white level would not be: white plus the resonance through zeros is an
ARMA(2,2) spectrum ``(N^2 |A|^2 + sigma^2 |B|^2)/|A|^2`` whose numerator has three
coefficients, which the four values (N, sigma, fa and the zeros' damping) would share.

In discrete time: ``y_k = (x_k - 2 cos(2 pi fa/fs) x_{k-1} + x_{k-2}) / B(1)``, ``B(1) =
2 - 2 cos(2 pi fa/fs)``, ``x`` the resonance of standard deviation ``sigma``. So ``sigma`` is
the resonance's standard deviation before the zeros, and with ``fa`` near Nyquist the term is
the resonance with a gentle roll-off.

Exact at every tau = m/fs: with ``rho(k) = 2 Re(c p^|k|)`` the resonance's autocorrelation,
``y``'s autocovariance is ``2 Re(c' p^|k|)`` at every lag from 2 on, ``c' = c sum_ij b_i b_j
p^(j-i)`` (``b`` the normalised taps), plus a correction at lags 0 and 1; the Allan
variance is the pole's closed form at ``c'`` plus that of the two-lag correction
(:func:`imunoise.analysis.terms.output_filter.avar_from_autocovariance`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from imunoise.analysis.terms.base import Param
from imunoise.analysis.terms.output_filter import avar_from_autocovariance
from imunoise.analysis.terms.resonance import (
    Resonance,
    _ResonanceSim,
    pole_and_weight,
    pole_shape,
    resonance_unit_psd,
)
from imunoise.analysis.terms.shape_memo import ShapeMemo

_SHAPES = ShapeMemo()


def zero_taps(fs: float, fa: float) -> np.ndarray:
    """The three taps of the zero pair at ``fa`` (Hz) on the unit circle, scaled to gain 1 at
    0 Hz."""
    taps = np.array([1.0, -2.0 * math.cos(2.0 * math.pi * fa / fs), 1.0])
    return taps / taps.sum()


def zero_gain(f: np.ndarray, fs: float, fa: float) -> np.ndarray:
    """Power gain ``|B(f)|^2 / B(1)^2`` of the zero pair at ``f`` (Hz):
    ``[sin((w - wa)/2) sin((w + wa)/2) / sin^2(wa/2)]^2`` with ``w = 2 pi f/fs``, in
    products of sines (no cancellation near the zeros)."""
    half_wz = math.pi * fa / fs
    half_w = np.pi * np.asarray(f, dtype=np.float64) / fs
    ratio = np.sin(half_w - half_wz) * np.sin(half_w + half_wz) / math.sin(half_wz) ** 2
    return ratio * ratio


def antiresonance_unit_psd(f: np.ndarray, fs: float, f0: float, q: float, fa: float
                           ) -> np.ndarray:
    """One-sided PSD (1/Hz) at ``f`` (Hz) of the unit-variance resonance through the zeros."""
    return resonance_unit_psd(f, fs, f0, q) * zero_gain(f, fs, fa)


def _autocovariance_parts(fs: float, f0: float, q: float, fa: float
                          ) -> tuple[complex, complex, np.ndarray]:
    """``(p, c', short)``: the autocovariance of the unit-sigma term is ``2 Re(c' p^|k|)``
    plus ``short[k]`` at lags 0 and 1."""
    p, c = pole_and_weight(fs, f0, q)
    b = zero_taps(fs, fa)
    c_pole = c * sum(b[i] * b[j] * p ** (j - i) for i in range(3) for j in range(3))
    short = np.zeros(2)
    for k in (0, 1):
        for i in range(3):
            for j in range(3):
                lag = k - i + j
                if lag < 0:  # where |lag| and lag differ, the pole form needs correcting
                    short[k] += b[i] * b[j] * 2.0 * ((c * p ** (-lag)).real
                                                    - (c * p ** lag).real)
    return p, c_pole, short


def antiresonance_variance(fs: float, f0: float, q: float, fa: float) -> float:
    """Variance of the unit-sigma term (the zeros' share of the resonance's power)."""
    _, c_pole, short = _autocovariance_parts(fs, f0, q, fa)
    return float(2.0 * c_pole.real + short[0])


def antiresonance_avar_shape(m: np.ndarray, fs: float, f0: float, q: float, fa: float
                             ) -> np.ndarray:
    """Allan variance of the unit-sigma term at averaging factors ``m``."""
    p, c_pole, short = _autocovariance_parts(fs, f0, q, fa)
    mm = np.asarray(m, dtype=np.float64)
    pole = 2.0 * np.real(c_pole * pole_shape(mm.astype(np.complex128), p))
    return np.maximum(pole + avar_from_autocovariance(short, mm).reshape(mm.shape), 0.0)


class Antiresonance(Resonance):
    name = "antiresonance"
    order = 152
    params = Resonance.params + (  # type: ignore[assignment]
        Param("fa", "Hz", 0.0, 1.0e9, "frequency of the anti-resonance (the zero pair)"),)
    allan_signature = ("a resonance's bump near tau = 1/(2 f0), its skirt below the white "
                       "line where the spectrum dips at fa")
    effect = "resonance with an anti-resonance beside it"
    explanation = (
        "A mode seen through a path with a zero pair beside its pole pair, as a sensing "
        "element coupled to its frame or a closed loop around a resonant structure shows it: "
        "the spectrum dips below its floor at the anti-resonance fa and its peak at f0 "
        "stands out of a plain resonance's shape, high on the side away from fa. Modelled as "
        "the resonance passed through two undamped zeros at fa, their gain 1 at 0 Hz; the "
        "dip's depth is the noise added after the mode.")
    small_default = {"sigma": 1e-6, "f0": 1.0, "Q": 10.0, "fa": 0.8}
    reduces_to = "resonance"  # zeros far from the peak: a plain resonance
    replaces = "resonance"  # offered in a resonance's place where the spectrum shows the zeros

    def log_fit_bounds(self, param, fs_hz, duration_s):
        # the zeros range as the centre frequency does
        return super().log_fit_bounds(self.param("f0") if param.name == "fa" else param,
                                      fs_hz, duration_s)

    def refinement_reason(self, old: str, shape: dict[str, float]) -> str:
        """Why the diagnosis offers this term in the place of resonance ``old``."""
        return (f"The spectrum dips below its floor under {old}'s peak and stands above a "
                f"resonance's skirt over it; an {self.name} has zeros at "
                f"{shape['fa']:.3g} Hz (from the spectrum).")

    def _avar(self, tau: np.ndarray, fs: float, **params: Any) -> np.ndarray:  # type: ignore[override]
        sigma, f0, q, fa = (float(params[k]) for k in ("sigma", "f0", "Q", "fa"))
        return sigma * sigma * _SHAPES.get(
            (tau.tobytes(), fs, f0, q, fa),
            lambda: antiresonance_avar_shape(tau * fs, fs, f0, q, fa))

    def _psd(self, f: np.ndarray, fs: float, **params: Any) -> np.ndarray:  # type: ignore[override]
        sigma, f0, q, fa = (float(params[k]) for k in ("sigma", "f0", "Q", "fa"))
        return sigma * sigma * antiresonance_unit_psd(f, fs, f0, q, fa)

    def start_shapes(self, fs_hz, duration_s, line):
        # each resonance start with its zeros at 0.8 f0, a third of an octave below
        return [{**c, "fa": 0.8 * c["f0"]}
                for c in super().start_shapes(fs_hz, duration_s, line)]

    def simulator(self, params, fs_hz, rng, **options):
        return _ResonanceSim(float(params["sigma"]), fs_hz, float(params["f0"]),
                             float(params["Q"]), rng, zero_taps(fs_hz, float(params["fa"])))


TERM = Antiresonance()
