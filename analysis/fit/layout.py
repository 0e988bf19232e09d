"""A model's free parameters as one log-parameter vector (bounds, held values), its Allan
variance, and the covariance of the Allan estimates under it (remembered per model).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import special

from imunoise.analysis.fit.result import CurveLike
from imunoise.analysis.misfit import avar_covariance
from imunoise.analysis.terms import (
    TermError,
    get_term,
    model_avar,
)


@dataclass
class _Layout:
    names: list[str]
    keys: list[tuple[int, str]]
    lo: np.ndarray
    hi: np.ndarray
    fixed: dict[tuple[int, str], float]


def _layout(names: list[str], fs: float, duration_s: float,
            fixed: dict[tuple[int, str], float]) -> _Layout:
    keys: list[tuple[int, str]] = []
    lo: list[float] = []
    hi: list[float] = []
    for i, n in enumerate(names):
        term = get_term(n)
        if term.role == "regressor":
            continue
        for p in term.params:
            if (i, p.name) in fixed:
                continue
            keys.append((i, p.name))
            a, b = term.log_fit_bounds(p, fs, duration_s)
            lo.append(a)
            hi.append(b)
    return _Layout(names, keys, np.array(lo), np.array(hi), dict(fixed))


def _unpack(layout: _Layout, theta: np.ndarray) -> list[dict[str, float]]:
    params: list[dict[str, float]] = [dict() for _ in layout.names]
    for (i, name), v in layout.fixed.items():
        params[i][name] = float(v)
    for (i, name), v in zip(layout.keys, theta, strict=True):
        params[i][name] = float(math.exp(v))
    return params


def _model_terms(layout: _Layout, params: list[dict[str, float]]
                 ) -> list[tuple[str, dict[str, float]]]:
    return [(n, p) for n, p in zip(layout.names, params, strict=True)
            if get_term(n).role != "regressor"]


def _avar_of(layout: _Layout, params: list[dict[str, float]], tau: np.ndarray, fs: float
             ) -> np.ndarray:
    # parameters already validated by the layout's bounds
    return model_avar(_model_terms(layout, params), tau, fs, checked=False)


_COV_CACHE: OrderedDict[tuple, np.ndarray] = OrderedDict()


_COV_LOCK = threading.Lock()


def _covariance(model: list[tuple[str, dict[str, float]]], fs: float, m: np.ndarray,
                n_terms: np.ndarray) -> np.ndarray:
    """:func:`imunoise.analysis.misfit.avar_covariance`, remembered for the last 64 distinct inputs
    (a fit asks for the same model's covariance when it solves, trims, scores and reports)."""
    key = (repr(model), fs, m.tobytes(), n_terms.tobytes())
    with _COV_LOCK:
        hit = _COV_CACHE.get(key)
        if hit is not None:
            _COV_CACHE.move_to_end(key)
            return hit
    cov = avar_covariance(model, fs, m, n_terms)
    cov.setflags(write=False)
    with _COV_LOCK:
        _COV_CACHE[key] = cov
        while len(_COV_CACHE) > 64:
            _COV_CACHE.popitem(last=False)
    return cov


def _log_weights(model: list[tuple[str, dict[str, float]]], fs: float, m: np.ndarray,
                 n_terms: np.ndarray, avar_model: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Whitening matrix, mean bias of ln(avar_hat) and the covariance of the AVAR estimates."""
    cov = _covariance(model, fs, m, n_terms)
    var = np.clip(np.diag(cov), 1e-300, None)
    nu = np.clip(2.0 * avar_model**2 / var, 1.0, 1e12)
    sd = np.sqrt(var)
    corr = cov / np.outer(sd, sd)
    log_sd = np.sqrt(special.polygamma(1, nu / 2.0))
    bias = special.digamma(nu / 2.0) - np.log(nu / 2.0)
    cov_log = corr * np.outer(log_sd, log_sd)
    w, v = np.linalg.eigh(cov_log)
    w = np.maximum(w, 1e-6 * w.max())
    whiten = (v / np.sqrt(w)).T
    return whiten, bias, cov


def _default_nu(curve: CurveLike) -> np.ndarray:
    edf = getattr(curve, "edf", None)
    if edf is not None and len(edf) == len(curve.tau_s) and np.all(np.isfinite(edf)):
        return np.maximum(np.asarray(edf, dtype=np.float64), 1.0)
    m = np.asarray(curve.m, dtype=np.float64)
    return np.maximum(1.5 * np.asarray(curve.n_terms, dtype=np.float64) / m, 1.0)


def _fixed_keys(names: list[str], fixed: dict[str | int, dict[str, float]], fs: float
                ) -> dict[tuple[int, str], float]:
    out: dict[tuple[int, str], float] = {}
    for key, params in fixed.items():
        if isinstance(key, int):
            if not 0 <= key < len(names):
                raise TermError(f"fixed parameters for model index {key}: no such term")
            idx = key
        else:
            if key not in names:
                raise TermError(f"fixed parameters given for {key!r}, which is not in the "
                                f"model ({', '.join(names)})")
            idx = names.index(key)
        term = get_term(names[idx])
        for pname, value in params.items():
            p = term.param(pname)
            hi = p.upper(fs)
            # a closed lower bound (a resonance's Q = 0.5) is a value a fit can return, so a
            # fitted model given back with every parameter held must be accepted
            above_lo = p.lo < value if p.lo_open else p.lo <= value
            if not (math.isfinite(value) and above_lo and value <= hi):
                raise TermError(f"{term.name}.{pname} = {value:g} outside its physical range "
                                f"{'(' if p.lo_open else '['}{p.lo:g}, {hi:g}]")
            out[(idx, pname)] = float(value)
    return out


def _jacobian(fun: Any, theta: np.ndarray, step: float = 1e-5) -> np.ndarray:
    f0 = fun(theta)
    jac = np.empty((f0.size, theta.size))
    for k in range(theta.size):
        th = theta.copy()
        th[k] += step
        jac[:, k] = (fun(th) - f0) / step
    return jac


def _match_start(names: list[str], start: list[tuple[str, dict[str, float]]]
                 ) -> list[dict[str, float]]:
    """Starting parameters for ``names`` from a previous model; new terms start small."""
    pool = [(n, dict(p)) for n, p in start]
    out: list[dict[str, float]] = []
    for n in names:
        hit = next((k for k, (pn, _) in enumerate(pool) if pn == n), None)
        if hit is not None:
            out.append(pool.pop(hit)[1])
        else:
            out.append(dict(get_term(n).small_default))
    return out
