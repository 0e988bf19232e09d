"""A resonance whose centre frequency wanders through the record: the whole record's spectrum
and Allan variance are those of a :mod:`resonance <imunoise.analysis.terms.resonance>` averaged
over a Gaussian distribution of f0 with standard deviation ``spread``.

A mode tuned by temperature or by the sensor's drive loop moves while the record runs: the
ADIS16405 gyro_z peak near 20 Hz has its centroid between 18.8 and 21.1 Hz in the ten-minute
blocks of one night (run 2). The night's spectrum
then holds a peak smeared over the range it visited, wider at its foot and flatter on top than
any one resonance, and a single resonance fitted to it trades its Q against the background.

Where the wander is slow against the resonance's correlation time ``Q/(pi f0)`` and against
the taus where the resonance shows (near ``1/(2 f0)``), each stretch of the record is a
resonance at its own f0, and the expected periodogram and Allan variance of the whole record
are the average of the exact AR(2) ones over the f0 the record visited. The average is taken as
a sum over a grid of f0 across six standard deviations either side, its points no further
apart than a quarter of the peak's half-power width ``f0/Q`` (within 1e-3 of the integral; at
most 241 points, a narrower peak taken four steps wide);
points outside ``(0, fs/2)`` are left out and the weights of the others renormalised (a wander
that reaches either end is not this term).

Simulation draws f0 once a second from a first-order Gauss-Markov process with standard
deviation ``spread`` and correlation time ``wander_s`` (an option, 600 s by default), the
AR(2) recursion carrying its state across the changes of coefficients and its innovations
scaled to keep unit variance at each f0.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np

from imunoise.analysis.terms.base import Param, TermSimulator
from imunoise.analysis.terms.resonance import (
    Resonance,
    _innovation_var,
    _poles,
    resonance_avar_mixture,
    resonance_psd_mixture,
)
from imunoise.analysis.terms.shape_memo import ShapeMemo

_SHAPES = ShapeMemo()
_MAX_NODES = 241
_MIN_NODES = 17
_REACH_SD = 6.0
WANDER_S = 600.0
"""Default correlation time (s) of the simulated wander."""


@lru_cache(maxsize=256)
def _gaussian_grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """n equally spaced points over +-6 standard deviations of N(0, 1) and their normalised
    weights."""
    x = np.linspace(-_REACH_SD, _REACH_SD, n)
    w = np.exp(-0.5 * x * x)
    return x, w / w.sum()


def centre_frequencies(fs: float, f0: float, q: float, spread: float
                       ) -> tuple[np.ndarray, np.ndarray, float]:
    """The centre frequencies (Hz) the average is taken over, their weights (summing to 1) and
    the quality factor each is taken with: a grid over +-6 spread, its step no wider than a
    quarter of the peak's half-power width f0/Q (Gauss-Hermite nodes, fewer, miss a peak
    narrower than their spacing: with the spread three times the width, 51 of them left
    ripples of 24 %). At most ``_MAX_NODES`` points: a peak narrower than four of their steps
    (a wander of more than ten times its width) is taken that wide, its Q lowered to
    ``f0/(4 step)``; the wander's Gaussian then sets the shape and Q is not resolved."""
    width = max(f0, 1e-300) / q
    n = int(np.clip(math.ceil(2.0 * _REACH_SD * spread / (0.25 * width)) + 1, _MIN_NODES,
                    _MAX_NODES)) | 1
    x, w = _gaussian_grid(n)
    step = 2.0 * _REACH_SD * spread / (n - 1)
    q_used = min(q, max(f0, 1e-300) / (4.0 * step)) if step > 0 else q
    f = f0 + spread * x
    ok = (f > 0.0) & (f < 0.5 * fs)
    if not ok.any():
        return np.array([f0]), np.array([1.0]), q
    return f[ok], w[ok] / w[ok].sum(), q_used


def wandering_avar_shape(m: np.ndarray, fs: float, f0: float, q: float, spread: float
                         ) -> np.ndarray:
    """Allan variance of the unit-variance wandering resonance at averaging factors ``m``."""
    freqs, weights, q_used = centre_frequencies(fs, f0, q, spread)
    return resonance_avar_mixture(m, fs, freqs, weights, q_used)


def wandering_psd(f: np.ndarray, fs: float, f0: float, q: float, spread: float
                  ) -> np.ndarray:
    """One-sided PSD of the unit-variance wandering resonance at ``f`` (Hz): the resonance's
    exact AR(2) spectrum averaged over the centre frequencies
    (:func:`~imunoise.analysis.terms.resonance.resonance_psd_mixture`; a fit asks for this
    thousands of times)."""
    freqs, weights, q_used = centre_frequencies(fs, f0, q, spread)
    return resonance_psd_mixture(f, fs, freqs, weights, q_used)


class _WanderingSim(TermSimulator):
    """AR(2) resonance whose f0 follows a Gauss-Markov process, updated once a second."""

    def __init__(self, sigma: float, fs: float, f0: float, q: float, spread: float,
                 wander_s: float, rng: np.random.Generator) -> None:
        self.sigma, self.fs, self.f0, self.q, self.spread = sigma, fs, f0, q, spread
        self.block = max(1, int(round(fs)))
        self.phi = math.exp(-self.block / (fs * wander_s))
        self.rng = rng
        self.offset = float(rng.standard_normal()) * spread
        self.zi = np.zeros(2)
        self.left = 0
        self._coefficients()
        # settle into the stationary law of the first f0
        burn = int(min(50.0 * q * fs / (math.pi * f0), 2e6)) + 10
        self._run(burn)

    def _coefficients(self) -> None:
        f = float(np.clip(self.f0 + self.offset, 1e-6 * self.fs, 0.499 * self.fs))
        _, phi1, phi2 = _poles(self.fs, f, self.q)
        self.a = np.array([1.0, -phi1, -phi2])
        self.e_sd = self.sigma * math.sqrt(_innovation_var(phi1, phi2))

    def _run(self, n: int) -> np.ndarray:
        from scipy.signal import lfilter  # slow to import: see analysis.dsp

        y, self.zi = lfilter([1.0], self.a, self.rng.standard_normal(n) * self.e_sd,
                             zi=self.zi)
        return y

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        out = np.empty(max(n, 0))
        done = 0
        while done < n:
            if self.left == 0:
                self.offset = self.phi * self.offset + math.sqrt(1.0 - self.phi ** 2) \
                    * self.spread * float(self.rng.standard_normal())
                self._coefficients()
                self.left = self.block
            k = min(self.left, n - done)
            out[done:done + k] = self._run(k)
            done += k
            self.left -= k
        return out


class WanderingResonance(Resonance):
    name = "wandering_resonance"
    order = 151
    params = Resonance.params + (  # type: ignore[assignment]
        Param("spread", "Hz", 0.0, 1.0e9, "standard deviation of the centre frequency over "
              "the record"),)
    allan_signature = ("a resonance's bump near tau = 1/(2 f0), lower and wider where f0 "
                       "wanders by more than the peak's width")
    effect = "resonance whose frequency wanders"
    explanation = (
        "A resonance whose centre frequency moves through the record, as a mode tuned by "
        "temperature does: each stretch of the record rings at its own f0, and the whole "
        "record's spectrum holds the peak smeared over the frequencies it visited, with a "
        "wider foot and a flatter top than one resonance has. Modelled as a resonance "
        "averaged over a Gaussian distribution of f0 with standard deviation spread.")
    small_default = {"sigma": 1e-6, "f0": 1.0, "Q": 10.0, "spread": 0.05}
    reduces_to = "resonance"  # without a resolved wander: one centre frequency
    replaces = "resonance"  # offered where a resonance's peak is found to move

    def log_fit_bounds(self, param, fs_hz, duration_s):
        if param.name == "spread":
            # from a wander no record can see to a tenth of the rate (a peak spread that wide
            # is a hump, not a resonance)
            return math.log(0.5 / duration_s), math.log(0.1 * fs_hz)
        return super().log_fit_bounds(param, fs_hz, duration_s)

    def unresolved(self, params, ci95):
        lo = ci95.get("spread", (math.nan, math.nan))[0]
        if not math.isfinite(lo) or lo <= 0.0:
            return ("its centre frequency's wander is not resolved (the interval of spread "
                    "reaches zero): a resonance of one frequency describes it")
        return super().unresolved(params, ci95)

    def refinement_reason(self, old: str, shape: dict[str, float]) -> str:
        """Why the diagnosis offers this term in the place of resonance ``old``."""
        return (f"The peak of {old} moves through the record; a {self.name} averages it over "
                f"the centre frequencies it visits (spread {shape['spread']:.2g} Hz from the "
                f"spectrum).")

    def _avar(self, tau: np.ndarray, fs: float, **params: Any) -> np.ndarray:  # type: ignore[override]
        sigma, f0, q, spread = (float(params[k]) for k in ("sigma", "f0", "Q", "spread"))
        return sigma * sigma * _SHAPES.get(
            (tau.tobytes(), fs, f0, q, spread),
            lambda: wandering_avar_shape(tau * fs, fs, f0, q, spread))

    def _psd(self, f: np.ndarray, fs: float, **params: Any) -> np.ndarray:  # type: ignore[override]
        sigma, f0, q, spread = (float(params[k]) for k in ("sigma", "f0", "Q", "spread"))
        return sigma * sigma * wandering_psd(f, fs, f0, q, spread)

    def start_shapes(self, fs_hz, duration_s, line):
        # each resonance start with a wander of half its peak's width
        return [{**c, "spread": 0.5 * c["f0"] / c["Q"]}
                for c in super().start_shapes(fs_hz, duration_s, line)]

    def simulator(self, params, fs_hz, rng, **options):
        return _WanderingSim(float(params["sigma"]), fs_hz, float(params["f0"]),
                             float(params["Q"]), float(params["spread"]),
                             float(options.get("wander_s", WANDER_S)), rng)


TERM = WanderingResonance()
