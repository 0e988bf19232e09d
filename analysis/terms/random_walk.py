"""Rate random walk, K."""

from __future__ import annotations

import math

import numpy as np

from imunoise.analysis.terms.base import Param, Term, TermSimulator


def sampled_walk_avar(tau_s: np.ndarray, fs_hz: float, K: float) -> np.ndarray:
    """Exact Allan variance (units^2) of a point-sampled random walk ``b_{k+1} = b_k + w_k``
    with step ``K sqrt(dt)`` (the discrete-time state of :mod:`imunoise.analysis.discrete`):
    ``K^2 dt (2 m^2 + 1) / (6 m)``, ``m = tau fs``. The interval-averaged walk of the
    continuous model gives ``K^2 tau/3`` instead."""
    m = np.asarray(tau_s, dtype=np.float64) * fs_hz
    return K**2 / fs_hz * (2.0 * m**2 + 1.0) / (6.0 * m)


class _RandomWalkSim(TermSimulator):
    """Interval averages of a Wiener process of intensity ``K^2`` (exact ``K^2 tau/3``)."""

    def __init__(self, K: float, fs_hz: float, rng: np.random.Generator) -> None:
        self.step = K / math.sqrt(fs_hz)
        self.rng = rng
        self.w = 0.0

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        z = self.rng.standard_normal((n, 2))
        step = self.step
        # running sum seeded with the state: the same additions in the same order as one
        # long run, so block boundaries leave no trace even in the last bit
        path = np.cumsum(np.concatenate(([self.w], z[:, 0] * step)))
        self.w = float(path[-1])
        return path[:-1] + step * (0.5 * z[:, 0] + z[:, 1] / math.sqrt(12.0))


class RandomWalk(Term):
    name = "random_walk"
    order = 40
    params = (Param("K", "rate/sqrt(s)", 0.0, 10.0, "rate random walk coefficient"),)
    amplitude = "K"
    linear = True
    estimators = frozenset({"allan", "block_likelihood"})
    allan_signature = "K^2 tau/3 (slope +1/2)"
    effect = "rate random walk"
    explanation = (
        "The bias itself performs a random walk (integrated white noise, often thermal or "
        "ageing effects), so it keeps wandering further the longer one waits. It rises as a "
        "slope +1/2 on the Allan deviation at long averaging times (K read at tau = 3 s) and "
        "falls as 1/f^2 in the spectrum.")
    small_default = {"K": 1e-9}

    def _avar(self, tau: np.ndarray, fs: float, K: float) -> np.ndarray:
        return K * K * tau / 3.0

    def _psd(self, f: np.ndarray, fs: float, K: float) -> np.ndarray:
        # interval averages of a Wiener process: increments are MA(1) with r0 = 2/3, r1 = 1/6
        w = 2.0 * np.pi * f / fs
        with np.errstate(divide="ignore"):
            return K * K * (2.0 + np.cos(w)) / (6.0 * fs * fs * np.sin(w / 2.0) ** 2)

    def simulator(self, params, fs_hz, rng, **options):
        return _RandomWalkSim(float(params["K"]), fs_hz, rng)

    def add_discrete(self, dm, params):
        # b_{k+1} = b_k + w_k, w_k ~ N(0, K^2 dt)
        k_total = np.hypot(dm.random_walk_step * np.sqrt(dm.fs_hz), params["K"])
        dm.random_walk_step = float(k_total / np.sqrt(dm.fs_hz))


TERM = RandomWalk()
