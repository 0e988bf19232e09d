"""One fit: the usable part of the curve, the layout of the model, and the reported chi2 of
a candidate solution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from imunoise.analysis.fit.layout import (
    _avar_of,
    _covariance,
    _default_nu,
    _fixed_keys,
    _Layout,
    _layout,
    _model_terms,
    _unpack,
)
from imunoise.analysis.fit.result import CurveLike
from imunoise.analysis.misfit import misfit
from imunoise.analysis.terms import (
    ModelSpec,
    TermError,
    get_term,
)


@dataclass
class _Problem:
    """One fit: the model's layout and the usable part of the curve."""

    names: list[str]
    spec: list[tuple[str, dict[str, float] | None]]
    layout: _Layout
    fs: float
    tau: np.ndarray
    m: np.ndarray
    n_terms: np.ndarray
    avar: np.ndarray
    y: np.ndarray
    nu0: np.ndarray
    duration: float
    family_rate: float
    max_nfev: int

    @property
    def n_free(self) -> int:
        return len(self.layout.keys)


@dataclass
class _Point:
    """A candidate solution: log-parameters, taus it rests on and its reported chi2."""

    theta: np.ndarray
    used: np.ndarray
    chi2: float


def _problem(curve: CurveLike, parsed: ModelSpec, fixed: dict | None, family_rate: float,
             max_nfev: int) -> _Problem:
    names = parsed.names
    fixed = {**parsed.fixed, **(fixed or {})}
    fs = float(curve.fs_hz)
    tau = np.asarray(curve.tau_s, dtype=np.float64)
    m = np.asarray(curve.m, dtype=np.float64)
    n_terms = np.asarray(curve.n_terms, dtype=np.float64)
    avar = np.asarray(curve.dev, dtype=np.float64) ** 2
    keep = np.isfinite(avar) & (avar > 0) & (n_terms > 0)
    # the averaging times are m/fs exactly: a rate read with a last-digit difference must
    # not move the fit
    tau = (m / fs)[keep] if np.allclose(tau, m / fs, rtol=1e-6) else tau[keep]
    m, n_terms, avar = m[keep], n_terms[keep], avar[keep]
    duration = float((n_terms[0] + 2 * m[0] - 1) / fs) if len(m) else 0.0
    layout = _layout(names, fs, duration, _fixed_keys(names, fixed, fs))
    n_free = len(layout.keys)
    if not any(get_term(n).role != "regressor" for n in names):
        raise TermError("the model has no noise term to fit to the Allan curve")
    if len(tau) == 0 and len(curve.tau_s):
        raise ValueError("the Allan deviation is zero at every tau: the channel is constant")
    if len(tau) <= n_free:
        raise ValueError(f"the Allan curve has {len(tau)} usable taus, too few for "
                         f"{n_free} free parameters: record longer")
    return _Problem(names, [(e.name, e.start) for e in parsed.entries], layout, fs, tau, m,
                    n_terms, avar, np.log(avar), _default_nu(curve)[keep], duration,
                    family_rate, max_nfev)


def _theta_of(prob: _Problem, params: list[dict[str, float]]) -> np.ndarray:
    lay = prob.layout
    theta = np.array([math.log(max(params[i][k], 1e-300)) for i, k in lay.keys])
    return np.clip(theta, lay.lo + 1e-9, lay.hi - 1e-9)


def _chi2(prob: _Problem, theta: np.ndarray) -> float:
    """The reported misfit chi2 (every tau, the model's own covariance)."""
    params = _unpack(prob.layout, theta)
    avar_fit = _avar_of(prob.layout, params, prob.tau, prob.fs)
    cov = _covariance(_model_terms(prob.layout, params), prob.fs, prob.m, prob.n_terms)
    return misfit(prob.avar, avar_fit, cov, prob.n_free, prob.family_rate).chi2
