"""Over-bounding noise models: filter-ready states whose Allan variance is never below the
measurement's upper 95 % bound.

A Kalman filter fed the fitted (nominal) noise is right on average and overconfident wherever
the real sensor is noisier than the fit: at the taus where the model fails, and everywhere the
estimate itself is uncertain. Engineers multiply Kalibr numbers by 10-20 by hand for that. Here
the bound is computed instead: a model made of the states a filter carries (white noise, a
random-walk bias, first-order Markov biases) whose Allan variance lies on or above the measured
curve's upper 95 % bound at every tau, and, when a band is given, whose PSD lies on or above the
measured PSD's upper bound there, with the least excess those states allow.

For fixed Markov time constants every state's Allan variance and PSD are linear in its variance
(N^2, K^2, sigma_j^2), so the bound is a linear programme: minimise the summed relative excess
``sum_i A(tau_i) x / U_i`` subject to ``A x >= U`` (and the PSD rows) with ``x >= 0``, over a
grid of Markov time constants (``MARKOV_PER_DECADE`` per decade between two sample periods and
half the record); the simplex picks the few states it needs. Each state's Allan variance and
PSD are those of the discrete-time model the filter runs (``imunoise.analysis.discrete``): white
samples,
a point-sampled random walk, AR(1) Markov sequences.

The excess reported per tau is ``model_adev / upper_adev - 1`` (>= 0 where the bound holds).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import linprog

from imunoise.analysis.discrete import DiscreteModel, markov_avar, markov_state, random_walk_avar
from imunoise.analysis.terms import get_term

MARKOV_PER_DECADE = 2
_TOL = 1e-9  # relative slack of the constraints after the solver (it works in floating point)


@dataclass
class Overbound:
    """A bounding model and how far above the measured upper bound it lies.

    Attributes:
        fs_hz: sample rate (Hz).
        N: white-noise density (units/sqrt(Hz)).
        K: random-walk density (units/sqrt(s)).
        markov: ``(sigma, T_s)`` of each first-order Markov state kept.
        tau_s: averaging times of the measured curve (s).
        upper_adev: the measured upper 95 % bound of the Allan deviation (units).
        model_adev: the bounding model's Allan deviation there (units).
        f_hz, upper_psd, model_psd: the PSD band bounded, when one was given (units^2/Hz).
    """

    fs_hz: float
    N: float
    K: float
    markov: list[tuple[float, float]]
    tau_s: np.ndarray
    upper_adev: np.ndarray
    model_adev: np.ndarray
    f_hz: np.ndarray = field(default_factory=lambda: np.zeros(0))
    upper_psd: np.ndarray = field(default_factory=lambda: np.zeros(0))
    model_psd: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def excess(self) -> np.ndarray:
        """``model_adev / upper_adev - 1`` per tau (>= 0 where the bound holds)."""
        return self.model_adev / self.upper_adev - 1.0

    @property
    def holds(self) -> bool:
        return bool(np.all(self.excess >= -1e-6)
                    and np.all(self.model_psd >= self.upper_psd * (1 - 1e-6)))

    def model(self) -> list[tuple[str, dict[str, float]]]:
        """As noise terms (``gauss_markov`` for each Markov state)."""
        out: list[tuple[str, dict[str, float]]] = [("white", {"N": self.N}),
                                                   ("random_walk", {"K": self.K})]
        out += [("gauss_markov", {"sigma": s, "T": t}) for s, t in self.markov]
        return out

    def discrete(self, units: str = "") -> DiscreteModel:
        """The filter-ready discrete model at the sample period."""
        dt = 1.0 / self.fs_hz
        return DiscreteModel(fs_hz=self.fs_hz, units=units,
                             white_sigma=self.N * math.sqrt(self.fs_hz),
                             random_walk_step=self.K * math.sqrt(dt),
                             markov=[markov_state("gauss_markov", s, t, self.fs_hz)
                                     for s, t in self.markov])

    def to_dict(self) -> dict:
        """JSON-ready (``discrete_model.overbound`` of ``analyze --json``)."""
        ex = self.excess
        d = {"N": self.N, "K": self.K,
             "markov": [{"sigma": s, "T_s": t} for s, t in self.markov],
             "discrete": self.discrete().to_dict(), "holds": self.holds,
             "tau_s": self.tau_s.tolist(), "upper_adev": self.upper_adev.tolist(),
             "model_adev": self.model_adev.tolist(), "excess": ex.tolist(),
             "max_excess": float(ex.max()) if ex.size else None,
             "median_excess": float(np.median(ex)) if ex.size else None}
        if self.f_hz.size:
            d["psd_band_hz"] = [float(self.f_hz.min()), float(self.f_hz.max())]
            d["psd_excess_max"] = float(np.max(self.model_psd / self.upper_psd) - 1.0)
        return d


def _state_columns(tau: np.ndarray, fs: float, Ts: Sequence[float]) -> np.ndarray:
    """Allan variance of each state at unit variance: white, random walk, Markov(T_j)."""
    cols = [get_term("white").avar(tau, fs, N=1.0), random_walk_avar(tau, fs, 1.0)]
    cols += [markov_avar(tau, fs, 1.0, T) for T in Ts]
    return np.column_stack(cols)


def _psd_columns(f: np.ndarray, fs: float, Ts: Sequence[float]) -> np.ndarray:
    """One-sided PSD of each discrete state at unit variance (units^2/Hz)."""
    w = 2.0 * np.pi * f / fs
    white = np.full(f.shape, 2.0)  # samples of std sqrt(fs): 2 N^2 one-sided
    walk = 1.0 / (2.0 * fs * fs * np.sin(w / 2.0) ** 2)  # point-sampled walk, step sqrt(dt)
    markov = [get_term("gauss_markov").psd(f, fs, sigma=1.0, T=T) for T in Ts]
    return np.column_stack([white, walk, *markov])


def markov_grid(fs_hz: float, duration_s: float, per_decade: int = MARKOV_PER_DECADE
                ) -> np.ndarray:
    """Candidate Markov time constants (s): two sample periods to half the record."""
    lo, hi = 2.0 / fs_hz, max(0.5 * duration_s, 4.0 / fs_hz)
    n = max(2, int(math.ceil(math.log10(hi / lo) * per_decade)) + 1)
    return np.geomspace(lo, hi, n)


def overbound(tau_s: np.ndarray, upper_adev: np.ndarray, fs_hz: float, *,
              duration_s: float | None = None, markov: bool = True,
              psd: tuple[np.ndarray, np.ndarray] | None = None,
              band_hz: tuple[float, float] | None = None) -> Overbound:
    """The least-excess bounding model of a measured Allan curve's upper 95 % bound.

    Args:
        tau_s: averaging times (s).
        upper_adev: upper 95 % bound of the measured Allan deviation at ``tau_s`` (units).
        fs_hz: sample rate (Hz).
        duration_s: record length (s), for the Markov grid (default 4 x the longest tau).
        markov: allow first-order Markov states (False: white and random walk only, the two a
            Kalibr file can hold).
        psd: ``(f_hz, upper_psd)``, the measured PSD's upper bound (one-sided, units^2/Hz).
        band_hz: ``(f_lo, f_hi)``: bound the PSD there as well (needs ``psd``).

    Raises:
        ValueError: no usable tau, or a bound the states cannot meet.
    """
    tau = np.asarray(tau_s, dtype=np.float64)
    up = np.asarray(upper_adev, dtype=np.float64)
    ok = np.isfinite(tau) & np.isfinite(up) & (up > 0) & (tau > 0)
    tau, up = tau[ok], up[ok]
    if tau.size == 0:
        raise ValueError("no tau with a finite upper bound to cover")
    duration = float(duration_s) if duration_s else 4.0 * float(tau.max())
    Ts = markov_grid(fs_hz, duration) if markov else np.zeros(0)
    target = up * up
    rows = _state_columns(tau, fs_hz, Ts) / target[:, None]
    f_band = s_band = np.zeros(0)
    if band_hz is not None:
        if psd is None:
            raise ValueError("a PSD band needs the measured PSD's upper bound")
        f, s = (np.asarray(a, dtype=np.float64) for a in psd)
        sel = (f >= band_hz[0]) & (f <= band_hz[1]) & np.isfinite(s) & (s > 0) & (f > 0)
        sel &= f < 0.5 * fs_hz
        f_band, s_band = f[sel], s[sel]
        if f_band.size:
            rows = np.vstack([rows, _psd_columns(f_band, fs_hz, Ts) / s_band[:, None]])
    scale = rows.max(axis=0)
    usable = scale > 0
    a = rows[:, usable] / scale[usable]
    cost = a[: tau.size].sum(axis=0)  # summed relative excess over the taus
    res = linprog(cost, A_ub=-a, b_ub=-np.ones(a.shape[0]) * (1.0 + _TOL), bounds=(0, None),
                  method="highs")
    if res.status != 0:
        raise ValueError(f"no bounding model with these states: {res.message}")
    x = np.zeros(scale.size)
    x[usable] = np.maximum(res.x, 0.0) / scale[usable]
    N, K = math.sqrt(x[0]), math.sqrt(x[1])
    kept = [(math.sqrt(v), float(T)) for v, T in zip(x[2:], Ts, strict=True)
            if v > 1e-12 * max(x.max(), 1e-300)]
    cols = _state_columns(tau, fs_hz, [t for _, t in kept])
    variances = np.array([N * N, K * K] + [s * s for s, _ in kept])
    model_adev = np.sqrt(cols @ variances)
    model_psd = (_psd_columns(f_band, fs_hz, [t for _, t in kept]) @ variances
                 if f_band.size else np.zeros(0))
    return Overbound(float(fs_hz), N, K, kept, tau, up, model_adev, f_band, s_band, model_psd)
