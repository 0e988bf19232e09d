"""A model's free parameters as one log-parameter vector (bounds, held values), its Allan
variance, and the covariance of the Allan estimates under it (remembered per model).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy import special

from imunoise.analysis.fit.result import CurveLike
from imunoise.analysis.misfit import avar_covariance
from imunoise.analysis.terms import (
    TermError,
    get_term,
    model_avar,
)
from imunoise.analysis.terms.output_filter import FilteredNoise, OutputFilter


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


_FD_STEP = float(np.sqrt(np.finfo(np.float64).eps))
"""Relative forward-difference step of a shape parameter's derivative (scipy's '2-point')."""


class _AvarModel:
    """A model's Allan variance (units^2) at fixed ``tau`` as a function of the layout's
    log-parameters, and its derivative.

    The derivative is what a fit's solver asks for most often. Differencing the whole model
    costs one full evaluation per parameter; here the model is split into groups that add
    (each additive term alone, and the output filter together with the noise terms it
    filters), and a parameter moves only its own group. An amplitude scales its term's Allan
    variance by its square, so its column is exact (``2 avar_term``; behind a filter, twice
    the term's filtered part); every other column is a forward difference of its group alone,
    and for the shape of a noise term behind the filter (a resonance's f0, a Markov time) of
    that term's filtered part alone, the other terms' parts taken as they were (the same
    numbers as the group's, computed for one term instead of all).
    """

    def __init__(self, layout: _Layout, tau: np.ndarray, fs: float) -> None:
        self.layout, self.tau, self.fs = layout, tau, fs
        terms = [get_term(n) for n in layout.names]
        live = [i for i, t in enumerate(terms) if t.role != "regressor"]
        filters = [i for i in live if terms[i].kind == "filter"]
        # with a filter, it and the noise terms it filters form one group
        through = (filters + [i for i in live if terms[i].role == "noise"
                              and terms[i].kind != "filter"]) if filters else []
        self.groups: list[list[int]] = ([sorted(through)] if through else []) + \
            [[i] for i in live if i not in through]
        group_of = {i: g for g, members in enumerate(self.groups) for i in members}
        self.col_group = [group_of[i] for i, _ in layout.keys]
        self.col_amplitude = [terms[i].kind != "filter" and k == terms[i].amplitude
                              for i, k in layout.keys]
        # the filter group's noise terms, in the order the filter takes them
        self._filtered = sorted(i for i in through if i not in filters)
        self._filter = filters[0] if filters else -1
        self._last: tuple[bytes, list[np.ndarray], FilteredNoise | None] | None = None

    def _group(self, g: int, params: list[dict[str, float]]) -> np.ndarray:
        """Allan variance of group ``g``."""
        names = self.layout.names
        return model_avar([(names[i], params[i]) for i in self.groups[g]], self.tau, self.fs,
                          checked=False)

    def _filtered_noise(self, params: list[dict[str, float]],
                        like: FilteredNoise | None = None, moved: int | None = None
                        ) -> FilteredNoise:
        """The filter group's Allan variance, term by term (see
        :meth:`OutputFilter.filtered_noise`; ``moved`` is a term's index in the layout)."""
        names = self.layout.names
        noise = [(get_term(names[i]), params[i]) for i in self._filtered]
        filt = get_term(names[self._filter])
        assert isinstance(filt, OutputFilter)  # every term of kind "filter" is one
        return filt.filtered_noise(
            noise, self.tau, self.fs, params[self._filter], like=like,
            moved=None if moved is None else self._filtered.index(moved))

    def _parts(self, theta: np.ndarray) -> tuple[list[np.ndarray], FilteredNoise | None]:
        key = theta.tobytes()
        if self._last is not None and self._last[0] == key:
            return self._last[1], self._last[2]
        params = _unpack(self.layout, theta)
        found = None
        parts = []
        for g in range(len(self.groups)):
            if self._filtered and self._filter in self.groups[g]:
                found = self._filtered_noise(params)
                parts.append(found.total)
            else:
                parts.append(self._group(g, params))
        self._last = (key, parts, found)
        return parts, found

    def value(self, theta: np.ndarray) -> np.ndarray:
        """Allan variance at ``theta``."""
        parts = self._parts(theta)[0]
        return np.sum(parts, axis=0) if parts else np.zeros_like(self.tau)

    def derivative(self, theta: np.ndarray) -> np.ndarray:
        """``d avar / d theta_k`` (units^2 per log unit), one column per free parameter."""
        parts, found = self._parts(theta)
        params = _unpack(self.layout, theta)
        out = np.empty((self.tau.size, theta.size))
        for k, (g, amp) in enumerate(zip(self.col_group, self.col_amplitude, strict=True)):
            i, name = self.layout.keys[k]
            # a noise term behind the filter: its filtered part, the others left where they were
            behind = found if found is not None and i in self._filtered else None
            if amp:
                out[:, k] = 2.0 * (parts[g] if behind is None
                                   else behind.parts[self._filtered.index(i)])
                continue
            h = _FD_STEP * max(1.0, abs(float(theta[k])))
            if theta[k] + h > self.layout.hi[k]:
                h = -h  # a parameter at its upper bound is differenced from below
            moved = list(params)
            moved[i] = {**params[i], name: math.exp(float(theta[k]) + h)}
            step = self._group(g, moved) if behind is None \
                else self._filtered_noise(moved, like=behind, moved=i).total
            out[:, k] = (step - parts[g]) / h
        return out


class _LogResidual:
    """Whitened residuals of ln(avar) against a model, ``whiten (y - ln avar - bias)``, and
    their Jacobian (for :func:`scipy.optimize.least_squares`), optionally over a subset of the
    parameters with the others held (``free``: the indices that vary, ``base``: the full
    vector the held ones are taken from)."""

    def __init__(self, model: _AvarModel, y: np.ndarray, whiten: np.ndarray,
                 bias: np.ndarray, base: np.ndarray | None = None,
                 free: list[int] | None = None) -> None:
        self.model, self.target, self.whiten = model, y - bias, whiten
        self.base, self.free = base, free

    def _full(self, x: np.ndarray) -> np.ndarray:
        if self.free is None or self.base is None:
            return x
        th = self.base.copy()
        th[self.free] = x
        return th

    def __call__(self, x: np.ndarray) -> np.ndarray:
        mod = self.model.value(self._full(x))
        return self.whiten @ (self.target - np.log(np.maximum(mod, 1e-300)))

    def jac(self, x: np.ndarray) -> np.ndarray:
        th = self._full(x)
        mod = self.model.value(th)
        d = self.model.derivative(th)
        if self.free is not None:
            d = d[:, self.free]
        # where a wild start makes the model's Allan variance vanish or go negative (a huge
        # flicker level behind a filter) the column is zero, and nothing is divided there
        d = np.divide(d, mod[:, None], out=np.zeros_like(d), where=(mod > 1e-300)[:, None])
        return -(self.whiten @ d)


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
