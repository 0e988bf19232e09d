"""White rate noise (angle / velocity random walk), N."""

from __future__ import annotations

import math

import numpy as np

from imunoise.analysis.terms.base import Param, Term, TermSimulator


class _WhiteSim(TermSimulator):
    def __init__(self, N: float, fs_hz: float, rng: np.random.Generator) -> None:
        self.sd = N * math.sqrt(fs_hz)
        self.rng = rng

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        # independent Gaussian samples of variance N^2 fs
        return self.rng.standard_normal(n) * self.sd


class White(Term):
    name = "white"
    order = 10
    params = (Param("N", "rate/sqrt(Hz)", 0.0, 10.0, "white-noise density (angle/velocity "
                                                     "random walk coefficient)"),)
    amplitude = "N"
    linear = True
    estimators = frozenset({"allan", "block_likelihood"})
    allan_signature = "N^2/tau (slope -1/2 on the Allan deviation)"
    effect = "angle (velocity) random walk"
    explanation = (
        "Thermo-mechanical and electronic white noise on the rate. Integrated, it makes the "
        "angle (or velocity) wander as a random walk. On the Allan deviation it is a straight "
        "line of slope -1/2 that dominates short averaging times; N is read at tau = 1 s. "
        "Its spectrum is flat: 2 N^2 one-sided.")
    small_default = {"N": 1e-6}

    def _avar(self, tau: np.ndarray, fs: float, N: float) -> np.ndarray:
        return N * N / tau

    def _psd(self, f: np.ndarray, fs: float, N: float) -> np.ndarray:
        return np.full_like(f, 2.0 * N * N)

    def autocovariance(self, fs_hz, params):
        return np.array([params["N"] ** 2 * fs_hz])

    def simulator(self, params, fs_hz, rng, **options):
        return _WhiteSim(float(params["N"]), fs_hz, rng)

    def add_discrete(self, dm, params):
        # v_k ~ N(0, sigma_d^2), sigma_d = N sqrt(fs); independent white parts add in power
        dm.white_sigma = float(np.hypot(dm.white_sigma, params["N"] * np.sqrt(dm.fs_hz)))


TERM = White()
