"""Fit of a noise model to an Allan variance curve, and ranking of the terms it misses.

The model Allan variance is a sum of terms, each linear in one power (``N^2``, ``B^2`` ...), so
for fixed shape parameters (a sinusoid's frequency, a Gauss-Markov correlation time) the fit is
a non-negative weighted linear least-squares problem. Shape parameters are found by a search over
a log-spaced grid inside the measured tau range. Residuals are weighted by the chi-square spread
of each estimate, ``sigma_i = avar_i * sqrt(2 / edf_i)``.

Used by the live analyzer, where it must be cheap enough to run every few seconds.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

# Parameter name, Allan variance per unit power at tau (for fixed shape), shape parameter name.
_LN2 = math.log(2.0)


def _gm_shape(tau: np.ndarray, t_corr: float) -> np.ndarray:
    """Allan variance of a first-order Gauss-Markov process of unit variance, correlation time T."""
    x = tau / t_corr
    return (2.0 / x) * (1.0 - (3.0 - 4.0 * np.exp(-x) + np.exp(-2.0 * x)) / (2.0 * x))


def _sin_shape(tau: np.ndarray, f_hz: float) -> np.ndarray:
    """Allan variance of a sinusoid of unit amplitude at frequency f."""
    x = math.pi * f_hz * tau
    return np.sin(x) ** 4 / x**2


@dataclass(frozen=True)
class TermSpec:
    """One noise term: how its Allan variance and one-sided PSD depend on its parameters."""

    name: str
    power_param: str
    shape_param: str | None
    avar: Callable[[np.ndarray, float], np.ndarray]  # (tau_s, shape) -> avar per unit power
    power_to_param: Callable[[float], float]         # fitted power -> reported parameter
    why: str


TERMS: dict[str, TermSpec] = {
    "white": TermSpec("white", "N", None, lambda t, _s: 1.0 / t, math.sqrt,
                      "Allan deviation falls as tau^-1/2: white rate noise (angle or velocity "
                      "random walk) from thermo-mechanical and electronic noise."),
    "quantization": TermSpec("quantization", "Q", None, lambda t, _s: 3.0 / t**2, math.sqrt,
                             "Allan deviation falls as 1/tau at short tau: quantization of the "
                             "converter output."),
    "bias_instability": TermSpec(
        "bias_instability", "B", None, lambda t, _s: np.full_like(t, 2.0 * _LN2 / math.pi),
        math.sqrt, "A flat floor of the Allan deviation: flicker (1/f) noise of the bias."),
    "random_walk": TermSpec("random_walk", "K", None, lambda t, _s: t / 3.0, math.sqrt,
                            "Allan deviation rises as tau^+1/2 at long tau: rate random walk of "
                            "the bias."),
    "rate_ramp": TermSpec("rate_ramp", "R", None, lambda t, _s: t**2 / 2.0, math.sqrt,
                          "Allan deviation rises as tau at the longest tau: a slow monotonic "
                          "drift of the bias (warm-up, ageing)."),
    "gauss_markov": TermSpec("gauss_markov", "sigma", "T", _gm_shape, math.sqrt,
                             "A bump of the Allan deviation near tau = 1.9 T: an exponentially "
                             "correlated (first-order Markov) bias."),
    "sinusoid": TermSpec("sinusoid", "A", "f", _sin_shape, math.sqrt,
                         "Allan deviation oscillates with a peak near tau = 0.37/f: a periodic "
                         "disturbance such as vibration, a pump, a fan or mains pickup."),
}

ORDER = list(TERMS)


@dataclass
class LiveFit:
    """Result of :func:`fit_model`.

    Attributes:
        model: term names in the model.
        params: per term, reported parameters in SI units of the channel.
        ci95: per term, 95 % intervals of the parameters.
        model_avar: model Allan variance at the curve's taus.
        term_avar: per term, its Allan variance at the curve's taus.
        z: standardised residual (measured - model) / sigma at each tau.
        chi2_per_dof: misfit normalised by the estimates' uncertainty (about 1 when it fits).
        failures: tau ranges where |z| > 3, as ``{"tau_s": [lo, hi], "max_abs_z", "direction"}``.
    """

    model: list[str]
    params: dict[str, dict[str, float]]
    ci95: dict[str, dict[str, list[float]]]
    model_avar: np.ndarray
    term_avar: dict[str, np.ndarray]
    z: np.ndarray
    chi2: float
    dof: int
    chi2_per_dof: float
    failures: list[dict] = field(default_factory=list)

    @property
    def max_abs_z(self) -> float:
        return float(np.max(np.abs(self.z))) if self.z.size else 0.0


def _shape_grid(name: str, tau: np.ndarray, fs_hz: float) -> list[float]:
    if name == "gauss_markov":
        return list(np.geomspace(tau[0] / 2.0, tau[-1] / 2.0, 24))
    if name == "sinusoid":
        return list(np.geomspace(max(0.37 / tau[-1], 1e-6), min(0.37 / tau[0], 0.5 * fs_hz), 32))
    return [0.0]


def _solve(tau: np.ndarray, avar: np.ndarray, sigma: np.ndarray,
           model: Sequence[str], shapes: dict[str, float]) -> tuple[np.ndarray, np.ndarray, float]:
    basis = np.column_stack([TERMS[t].avar(tau, shapes.get(t, 0.0)) for t in model])
    a = basis / sigma[:, None]
    b = avar / sigma
    scale = np.maximum(np.abs(a).max(axis=0), 1e-300)
    power, _ = optimize.nnls(a / scale, b)
    power = power / scale
    chi2 = float(np.sum((a @ power - b) ** 2))
    return power, basis, chi2


def _refine(tau: np.ndarray, y: np.ndarray, sigma: np.ndarray, model: Sequence[str],
            shapes: dict[str, float], name: str, start: float, grid: list[float]) -> float:
    """Polish a grid optimum of one shape parameter by a bounded search in log space."""
    step = math.log(grid[1] / grid[0]) if len(grid) > 1 else 0.0
    if step == 0.0:
        return start

    def cost(log_s: float) -> float:
        return _solve(tau, y, sigma, model, dict(shapes, **{name: math.exp(log_s)}))[2]

    res = optimize.minimize_scalar(cost, bounds=(math.log(start) - step, math.log(start) + step),
                                   method="bounded", options={"xatol": 1e-4})
    best = math.exp(res.x) if res.fun <= cost(math.log(start)) else start
    return float(best)


def _failures(tau: np.ndarray, z: np.ndarray, threshold: float = 3.0) -> list[dict]:
    out: list[dict] = []
    bad = np.abs(z) > threshold
    i = 0
    while i < len(z):
        if not bad[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(z) and bad[j + 1] and np.sign(z[j + 1]) == np.sign(z[i]):
            j += 1
        seg = z[i:j + 1]
        out.append({"tau_s": [float(tau[i]), float(tau[j])],
                    "max_abs_z": float(np.max(np.abs(seg))),
                    "direction": "measured above model" if seg[0] > 0 else "measured below model"})
        i = j + 1
    return out


def fit_model(tau_s: np.ndarray, avar: np.ndarray, edf: np.ndarray, model: Sequence[str],
              fs_hz: float) -> LiveFit:
    """Fit ``model`` (term names) to an Allan variance curve.

    Args:
        tau_s: averaging times in s.
        avar: measured Allan variance (channel units^2).
        edf: equivalent degrees of freedom of each estimate.
        model: term names from :data:`TERMS`.
        fs_hz: sampling rate in Hz (bounds the sinusoid frequency search).
    """
    unknown = [t for t in model if t not in TERMS]
    if unknown:
        raise ValueError(f"unknown term(s) {unknown}; valid: {', '.join(ORDER)}")
    model = [t for t in ORDER if t in model]
    tau = np.asarray(tau_s, dtype=np.float64)
    y = np.asarray(avar, dtype=np.float64)
    sigma = y * np.sqrt(2.0 / np.maximum(np.asarray(edf, dtype=np.float64), 1.0))
    sigma = np.maximum(sigma, 1e-300)
    if tau.size == 0 or not model:
        return LiveFit(list(model), {}, {}, np.zeros_like(tau), {}, np.zeros_like(tau),
                       0.0, 0, 0.0, [])
    shaped = [t for t in model if TERMS[t].shape_param]
    shapes = {n: _shape_grid(n, tau, fs_hz)[len(_shape_grid(n, tau, fs_hz)) // 2]
              for n in shaped}
    # Coordinate search over each shaped term's grid (at most two such terms in practice).
    for _ in range(2 if len(shaped) > 1 else 1):
        for name in shaped:
            best = (math.inf, 0.0)
            for s in _shape_grid(name, tau, fs_hz):
                trial = dict(shapes, **{name: s})
                _, _, chi2 = _solve(tau, y, sigma, model, trial)
                if chi2 < best[0]:
                    best = (chi2, s)
            shapes[name] = _refine(tau, y, sigma, model, shapes, name, best[1],
                                   _shape_grid(name, tau, fs_hz))
    power, basis, chi2 = _solve(tau, y, sigma, model, shapes)
    model_avar = basis @ power
    n_params = len(model) + len(shaped)
    dof = max(tau.size - n_params, 1)
    chi2_per_dof = chi2 / dof
    # Parameter intervals from the linearised covariance, inflated when the model misfits.
    a = basis / sigma[:, None]
    try:
        cov = np.linalg.pinv(a.T @ a) * max(1.0, chi2_per_dof)
    except np.linalg.LinAlgError:
        cov = np.full((len(model), len(model)), np.inf)
    params: dict[str, dict[str, float]] = {}
    ci95: dict[str, dict[str, list[float]]] = {}
    term_avar: dict[str, np.ndarray] = {}
    for k, name in enumerate(model):
        spec = TERMS[name]
        sd = math.sqrt(max(float(cov[k, k]), 0.0))
        lo_p, hi_p = max(power[k] - 1.96 * sd, 0.0), power[k] + 1.96 * sd
        params[name] = {spec.power_param: spec.power_to_param(float(power[k]))}
        ci95[name] = {spec.power_param: [spec.power_to_param(lo_p), spec.power_to_param(hi_p)]}
        if spec.shape_param:
            params[name][spec.shape_param] = float(shapes[name])
        term_avar[name] = basis[:, k] * power[k]
    model_sigma = np.maximum(model_avar, 1e-300) * np.sqrt(2.0 / np.maximum(edf, 1.0))
    z = (y - model_avar) / model_sigma
    return LiveFit(list(model), params, ci95, model_avar, term_avar, z, chi2, dof,
                   chi2_per_dof, _failures(tau, z))


def rank_missing_terms(tau_s: np.ndarray, avar: np.ndarray, edf: np.ndarray,
                       model: Sequence[str], fs_hz: float, base: LiveFit | None = None,
                       p_threshold: float = 1e-3) -> list[dict]:
    """Refit with each term not in ``model``; best (lowest chi2 after) first.

    A suggestion is ``significant`` when the drop in chi-square is unlikely by chance under the
    smaller model (F test of the nested fits at ``p_threshold``) and the new term is non-zero.
    """
    base = base or fit_model(tau_s, avar, edf, model, fs_hz)
    out: list[dict] = []
    for name in ORDER:
        if name in model:
            continue
        trial = fit_model(tau_s, avar, edf, list(model) + [name], fs_hz)
        spec = TERMS[name]
        extra = 2 if spec.shape_param else 1
        drop = base.chi2 - trial.chi2
        significant = False
        if drop > 0 and trial.dof > 0 and trial.params[name][spec.power_param] > 0:
            f_stat = (drop / extra) / max(trial.chi2_per_dof, 1.0)
            p = float(stats.f.sf(f_stat, extra, trial.dof))
            significant = p < p_threshold and base.chi2_per_dof > 1.5
        out.append({"term": name, "params": trial.params[name],
                    "chi2_per_dof_after": trial.chi2_per_dof, "significant": bool(significant),
                    "why": spec.why})
    out.sort(key=lambda s: (not s["significant"], s["chi2_per_dof_after"]))
    return out
