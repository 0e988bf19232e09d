"""95 % intervals of the fitted parameters: linearised in log-parameter space, or by profile
likelihood where the linearisation cannot be trusted.
"""

from __future__ import annotations

import math
from collections.abc import Collection
from typing import Any

import numpy as np
from scipy import optimize

from imunoise.analysis.fit.layout import (
    _AvarModel,
    _Layout,
    _log_weights,
    _LogResidual,
)
from imunoise.analysis.fit.problem import _Point, _Problem
from imunoise.analysis.jobs import JobMap, serial_map
from imunoise.analysis.profile import profile_bounds
from imunoise.analysis.terms import (
    get_term,
)

_Z95 = 1.959963984540054


def _intervals(prob: _Problem, point: _Point, model_final: list, avar_fit: np.ndarray,
               intervals: str, job_map: JobMap = serial_map,
               profile_terms: Collection[int] | None = None
               ) -> tuple[list[dict[str, tuple[float, float]]], np.ndarray]:
    """95 % intervals: linearised in log-parameter space, or by profile likelihood (each
    parameter's profile a job of ``job_map``); with ``profile_terms`` (``"jacobian"``
    only), the weakly determined parameters of the other terms get ``(nan, nan)``."""
    layout, fs, used, theta = prob.layout, prob.fs, point.used, point.theta
    if prob.n_free == 0:
        return ([{k: (float(v), float(v)) for (i, k), v in layout.fixed.items() if i == j}
                 for j in range(len(prob.names))], np.zeros((0, 0)))
    whiten, bias, _ = _log_weights(model_final, fs, prob.m[used], prob.n_terms[used],
                                   avar_fit[used])
    resid_final = _LogResidual(_AvarModel(layout, prob.tau[used], fs), prob.y[used], whiten,
                               bias)
    jac = resid_final.jac(theta)
    param_cov = np.linalg.pinv(jac.T @ jac)
    sd = np.sqrt(np.clip(np.diag(param_cov), 0.0, None))
    ci: list[dict[str, tuple[float, float]]] = [dict() for _ in prob.names]
    # A linearised interval is only honest for a parameter the curve determines well. For an
    # amplitude near zero the Jacobian column vanishes (the pseudo-inverse then reports a zero
    # width) or the log-scale interval runs to its bound; such parameters get the profile
    # interval even in the quick mode; so does one whose log-scale standard error exceeds 0.5
    # (a 95 % factor of 2.7 either way), where the linearisation no longer holds.
    col_norm = np.linalg.norm(jac, axis=0)
    weak = ((col_norm <= 1e-6 * max(float(col_norm.max(initial=0.0)), 1e-300))
            | ~np.isfinite(sd) | (sd > 0.5) | (theta - _Z95 * sd <= layout.lo + 1e-6))
    if intervals != "profile" and profile_terms is not None:
        skipped = weak & ~np.isin([i for i, _ in layout.keys], list(profile_terms))
        weak &= ~skipped
    else:
        skipped = np.zeros_like(weak)
    base = None
    if intervals == "profile" or np.any(weak):
        full = optimize.least_squares(resid_final, theta, jac=resid_final.jac,
                                      bounds=(layout.lo, layout.hi), method="trf", max_nfev=60)
        base = min(2.0 * float(full.cost), float(np.sum(resid_final(theta) ** 2)))
    profiled = [idx for idx in range(theta.size) if intervals == "profile" or weak[idx]]
    ends = dict(zip(profiled, job_map(_profile_at, (resid_final, theta, layout, sd, base),
                                      profiled), strict=True))
    for idx, ((i, k), th, s) in enumerate(zip(layout.keys, theta, sd, strict=True)):
        if skipped[idx]:
            ci[i][k] = (math.nan, math.nan)  # not computed: a linearisation would mislead
            continue
        lo, hi = ends[idx] if idx in ends else (th - _Z95 * s, th + _Z95 * s)
        # an amplitude whose interval reaches its lower bound is consistent with zero
        scale = get_term(prob.names[i]).param(k).is_scale
        lo_v = 0.0 if (lo <= layout.lo[idx] + 1e-6 and not scale) else math.exp(lo)
        ci[i][k] = (float(lo_v), float(math.exp(min(hi, 700.0))))
    for (i, k), v in layout.fixed.items():
        ci[i][k] = (float(v), float(v))
    return ci, param_cov


_CHI2_95_1DOF = 3.841458820694124


_PROFILE_WIDTH = 0.02
"""An interval's end is found to within this (log units: 2 % of the value)."""


def _profile_at(shared: tuple[Any, ...], idx: int) -> tuple[float, float]:
    """:func:`_profile_interval` of parameter ``idx``, as a job map calls it."""
    resid, theta, layout, sd, base = shared
    assert base is not None  # set whenever a profile is asked for
    return _profile_interval(resid, theta, idx, layout, float(sd[idx]), base)


def _profile_interval(resid: _LogResidual, theta: np.ndarray, idx: int, layout: _Layout,
                      sd: float, base: float) -> tuple[float, float]:
    """95 % profile-likelihood interval of log-parameter ``idx`` (whitening held fixed;
    ``base`` is the minimum of the plain sum of squares)."""
    others = [j for j in range(theta.size) if j != idx]

    def excess(v: float, guess: np.ndarray) -> tuple[float, np.ndarray]:
        th = theta.copy()
        th[idx] = v
        if not others:
            return float(np.sum(resid(th) ** 2)) - base, guess
        sub = _LogResidual(resid.model, resid.target, resid.whiten, np.zeros_like(resid.target),
                           base=th, free=others)
        lo_b, hi_b = layout.lo[others], layout.hi[others]
        x0 = np.clip(guess, lo_b + 1e-9, hi_b - 1e-9)
        sol = optimize.least_squares(sub, x0, jac=sub.jac, bounds=(lo_b, hi_b), method="trf",
                                     max_nfev=40)
        return 2.0 * float(sol.cost) - base, sol.x

    # the first step is four Jacobian standard deviations, at most one log unit: where the
    # Jacobian says a parameter is barely determined (a resonance's Q, sd 20 log units) a
    # longer step lands at its bound, where the rise is in the millions, and halving from
    # there to _PROFILE_WIDTH costs a dozen refits; doubling from one log unit finds the end
    # in fewer (ADIS16405 run 4 accel_x's diagnosis: 470 refits for 35 intervals, 571 with
    # the step uncapped; the intervals of the determined parameters are the same)
    step = min(max(2.0 * _Z95 * sd, 0.05), 1.0) if np.isfinite(sd) and sd > 0 else 1.0
    return profile_bounds(excess, float(theta[idx]), float(layout.lo[idx]),
                          float(layout.hi[idx]), step, _CHI2_95_1DOF, theta[others],
                          bisections=5, width=_PROFILE_WIDTH)
