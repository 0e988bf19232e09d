"""Angle (velocity) quantization, Q."""

from __future__ import annotations

import numpy as np

from imunoise.analysis.terms.base import Param, Term, TermSimulator


class _QuantizationSim(TermSimulator):
    """``(e_k - e_{k-1}) fs`` with ``e`` Gaussian white of variance ``Q^2``: the rounding error
    of the integrated angle. Rounding error is closer to uniform, but the Allan variance and
    spectrum depend only on its variance, and a Gaussian error keeps the simulated data inside
    the Gaussian model that the misfit statistics assume."""

    def __init__(self, Q: float, fs_hz: float, rng: np.random.Generator) -> None:
        self.Q, self.fs, self.rng = Q, fs_hz, rng
        self.e_prev = rng.standard_normal() * Q

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        e = np.concatenate(([self.e_prev], self.rng.standard_normal(n) * self.Q))
        self.e_prev = e[-1]
        return np.diff(e) * self.fs


class Quantization(Term):
    name = "quantization"
    order = 20
    params = (Param("Q", "angle", 0.0, 10.0, "angle (velocity) quantization step / sqrt(12)"),)
    amplitude = "Q"
    linear = True
    allan_signature = "3 Q^2/tau^2 (slope -1)"
    effect = "angle quantization"
    explanation = (
        "The converter rounds the integrated angle (or velocity) to a finite step, adding a "
        "white error to the angle, i.e. a differenced white error to the rate. It shows as a "
        "slope -1 on the Allan deviation at the shortest averaging times, steeper than white "
        "noise, and as a spectrum rising with frequency (8 Q^2 fs sin^2(pi f/fs)).")
    small_default = {"Q": 1e-9}

    def _avar(self, tau: np.ndarray, fs: float, Q: float) -> np.ndarray:
        return 3.0 * Q * Q / (tau * tau)

    def _psd(self, f: np.ndarray, fs: float, Q: float) -> np.ndarray:
        # rate = first difference of a white angle error of variance Q^2, times fs
        return 8.0 * Q * Q * fs * np.sin(np.pi * f / fs) ** 2

    def autocovariance(self, fs_hz, params):
        # (e_k - e_{k-1}) fs: variance 2 Q^2 fs^2, lag-one covariance -Q^2 fs^2
        v = (params["Q"] * fs_hz) ** 2
        return np.array([2.0 * v, -v])

    def simulator(self, params, fs_hz, rng, **options):
        return _QuantizationSim(float(params["Q"]), fs_hz, rng)

    def add_discrete(self, dm, params):
        # (e_k - e_{k-1})/dt with e_k ~ N(0, Q^2)
        dm.quantization_sigma = float(np.hypot(dm.quantization_sigma, params["Q"]))


TERM = Quantization()
