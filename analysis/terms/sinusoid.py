"""A deterministic sinusoid (vibration, pump, fan or mains pickup), A and f.

Sampled at ``fs``: ``A sin(2 pi f k/fs + phi)``; its Allan variance uses the Dirichlet kernel
of the m-sample average, which the continuous sinc form only approximates.
"""

from __future__ import annotations

import math

import numpy as np

from imunoise.analysis.terms.base import Param, Term, TermSimulator

_BIG = 1.0e3


class _SinusoidSim(TermSimulator):
    """``A sin(2 pi f k/fs + phi)`` with a random phase drawn once."""

    def __init__(self, A: float, f: float, fs_hz: float, rng: np.random.Generator) -> None:
        self.A, self.f, self.fs, self.k = A, f, fs_hz, 0
        self.phase = rng.uniform(0.0, 2.0 * math.pi)

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        k = np.arange(self.k, self.k + n, dtype=np.float64)
        self.k += n
        return self.A * np.sin(2.0 * math.pi * self.f * k / self.fs + self.phase)


class Sinusoid(Term):
    name = "sinusoid"
    order = 70
    params = (Param("A", "rate", 0.0, _BIG, "amplitude"),
              Param("f", "Hz", 0.0, math.inf, "frequency"))
    amplitude = "A"
    role = "line"
    continuous_psd = False
    repeatable = True
    avar_extras = ("bandwidth_hz",)
    allan_signature = "A^2 sin^4(pi f tau)/(pi f tau)^2: oscillating, peak near tau = 0.37/f"
    effect = "vibration, pump, fan or mains pickup"
    explanation = (
        "A periodic disturbance at one frequency: a fan, pump, vibration of the mount or "
        "mains pickup. The Allan deviation shows a bump near tau = 0.37/f followed by "
        "ripples that fall off as 1/tau, with dips where tau is a whole number of periods; "
        "the spectrum has a sharp line at f holding power A^2/2.")
    small_default = {"A": 1e-6, "f": 1.0}

    def _avar(self, tau: np.ndarray, fs: float, A: float, f: float,
              bandwidth_hz: float | None = None) -> np.ndarray:
        m = tau * fs
        s1 = np.sin(np.pi * f / fs)
        return A * A * np.sin(np.pi * f * tau) ** 4 / (m * m * s1 * s1)

    def _psd(self, fgrid: np.ndarray, fs: float, A: float, f: float,
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

    def line(self, params):
        return float(params["A"]), float(params["f"])

    def start_shapes(self, fs_hz, duration_s, line):
        if line is not None:
            return [{"f": float(line[0])}]
        return [{"f": float(f)} for f in np.geomspace(2.0 / duration_s, 0.45 * fs_hz, 60)]

    def start_amplitude(self, fitted, line):
        # the linear solve may leave a line out that the spectrum shows plainly
        return line[1] if line is not None and fitted <= 0 else fitted

    def simulator(self, params, fs_hz, rng, **options):
        return _SinusoidSim(float(params["A"]), float(params["f"]), fs_hz, rng)

    def add_discrete(self, dm, params):
        dm.sinusoids.append((params["A"], params["f"]))


TERM = Sinusoid()
