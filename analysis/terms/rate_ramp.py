"""Rate ramp (deterministic drift), R."""

from __future__ import annotations

import numpy as np

from imunoise.analysis.terms.base import Param, Term, TermSimulator


class _RampSim(TermSimulator):
    """``R t`` at the interval mid-points ``t = (k + 1/2)/fs`` from the stream start."""

    def __init__(self, R: float, fs_hz: float) -> None:
        self.R, self.fs, self.k = R, fs_hz, 0

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        k = np.arange(self.k, self.k + n, dtype=np.float64)
        self.k += n
        return self.R * (k + 0.5) / self.fs


class RateRamp(Term):
    name = "rate_ramp"
    order = 50
    params = (Param("R", "rate/s", 0.0, 10.0, "rate ramp (drift rate)"),)
    amplitude = "R"
    linear = True
    role = "ramp"
    allan_signature = "R^2 tau^2/2 (slope +1)"
    effect = "slow monotonic drift"
    explanation = (
        "A slow, steady drift of the bias over the whole record, for instance while the "
        "sensor warms up. It is deterministic rather than noise: the Allan deviation climbs "
        "with slope +1 at the longest averaging times; the spectrum (conventionally "
        "2 R^2/(2 pi f)^3) piles up at the lowest frequencies.")
    small_default = {"R": 1e-10}

    def _avar(self, tau: np.ndarray, fs: float, R: float) -> np.ndarray:
        return 0.5 * R * R * tau * tau

    def _psd(self, f: np.ndarray, fs: float, R: float) -> np.ndarray:
        with np.errstate(divide="ignore"):
            return 2.0 * R * R / (2.0 * np.pi * f) ** 3

    def ramp_slope(self, params):
        return float(params["R"])

    def simulator(self, params, fs_hz, rng, **options):
        return _RampSim(float(params["R"]), fs_hz)

    def add_discrete(self, dm, params):
        dm.ramp_rate += params["R"]


TERM = RateRamp()
