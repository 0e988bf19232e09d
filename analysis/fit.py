"""Composite noise-model fit to a measured Allan curve, with honest intervals and misfit.

The model's Allan variance is the sum of its terms' (:mod:`imunoise.analysis.terms`). The fit works
on
``ln(avar)`` at every tau of the curve:

1. Starting values without hand-picked tau windows: the linear terms (white, quantization,
   bias instability, random walk, ramp) are linear in their squared parameters, so a
   non-negative least-squares solve on the relative residuals, weighted by each estimate's
   degrees of freedom, gives them all at once. Each Gauss-Markov term adds a grid search over
   its correlation time T (the amplitude stays linear); a sinusoid starts from the strongest
   spectral line when the caller supplies one (see :func:`find_line`), else from a grid in f.
2. Generalised least squares on ``ln(avar)`` with parameters in log form (positivity): the
   residuals are whitened with the covariance of the log estimates across taus computed from
   the model itself (:func:`imunoise.analysis.misfit.avar_covariance`), corrected for the
   chi-square law
   of each estimate (mean ``psi(nu/2) - ln(nu/2)``, variance ``psi'(nu/2)``). The covariance is
   computed for the starting model, the fit solved, and the covariance recomputed for the
   result.
3. 95 % intervals from the whitened Jacobian (``(J^T J)^-1`` in log-parameter space,
   so intervals are asymmetric and positive); the misfit (chi2 per degree of freedom, z per
   tau, failing tau ranges) from :func:`imunoise.analysis.misfit.misfit`.

``temperature`` is not part of the Allan fit: :func:`regress_temperature` removes it from the
series first (see :func:`fit_series`).
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
from scipy import ndimage, optimize, signal, special

from imunoise.analysis.blas import one_blas_thread
from imunoise.analysis.misfit import Misfit, avar_covariance, failure_threshold, failures, misfit
from imunoise.analysis.profile import profile_bounds
from imunoise.analysis.terms import (
    Entry,
    ModelSpec,
    TermError,
    get_term,
    labels,
    model_avar,
    parse_model,
)

_Z95 = 1.959963984540054
_LOSS = "soft_l1"
_MAX_SHORT_TRIM = 4
_F_SCALE = 3.0
_CHI2_TIE = 0.05  # chi2 differences below this are the solver's tolerance
_WHOLE_WINS = 0.5


class CurveLike(Protocol):
    """What the fit needs from an Allan curve (``imunoise.analysis.allan.AllanCurve`` provides
    it; read-only, as its frozen dataclass)."""

    @property
    def fs_hz(self) -> float: ...
    @property
    def tau_s(self) -> np.ndarray: ...
    @property
    def m(self) -> np.ndarray: ...
    @property
    def dev(self) -> np.ndarray: ...
    @property
    def n_terms(self) -> np.ndarray: ...


ModelLike = Sequence[str] | Sequence[tuple[str, dict[str, float]]] | str | ModelSpec


@dataclass
class TermFit:
    """One fitted term: parameters (SI) and their 95 % intervals."""

    term: str
    params: dict[str, float]
    ci95: dict[str, tuple[float, float]]

    def to_dict(self) -> dict[str, Any]:
        return {"term": self.term, "params": dict(self.params),
                "ci95": {k: [float(a), float(b)] for k, (a, b) in self.ci95.items()}}


@dataclass
class FitResult:
    """A fitted model and how well it explains the measured Allan curve.

    Attributes:
        terms: fitted terms in model order (``temperature`` included when fitted upstream).
        fs_hz: sampling rate, Hz.
        tau_s, m, n_terms: the curve's averaging times (s), factors, number of differences.
        avar_measured: measured Allan variance (units^2).
        avar_fit: model Allan variance at ``tau_s``.
        term_avar: per-term model Allan variance at ``tau_s`` (for plotting).
        misfit: z per tau, chi2 and the rest (:class:`imunoise.analysis.misfit.Misfit`).
        failures: ``failures`` entries of the JSON documents (docs/json.md).
        param_cov: covariance of the log-parameters (order of :attr:`free_params`).
        free_params: ``(term index, parameter name)`` of each fitted parameter.
    """

    terms: list[TermFit]
    fs_hz: float
    tau_s: np.ndarray
    m: np.ndarray
    n_terms: np.ndarray
    avar_measured: np.ndarray
    avar_fit: np.ndarray
    term_avar: list[np.ndarray]
    misfit: Misfit
    failures: list[dict]
    param_cov: np.ndarray
    free_params: list[tuple[int, str]] = field(default_factory=list)
    used: np.ndarray | None = None
    """Taus the parameters rest on (failing shortest taus are set aside)."""

    @property
    def params(self) -> list[tuple[str, dict[str, float]]]:
        """The model as ``[(term, params)]``, usable as a starting point of a refit."""
        return [(t.term, dict(t.params)) for t in self.terms]

    @property
    def ci95(self) -> list[dict[str, tuple[float, float]]]:
        return [t.ci95 for t in self.terms]

    @property
    def chi2_per_dof(self) -> float:
        return self.misfit.chi2_per_dof

    @property
    def z(self) -> np.ndarray:
        return self.misfit.z

    @property
    def max_abs_z(self) -> float:
        return self.misfit.max_abs_z

    def model_avar(self, tau_s: np.ndarray | float) -> np.ndarray:
        """Model Allan variance at any ``tau_s`` (the fitted noise terms; temperature, removed
        upstream, contributes nothing)."""
        tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
        return model_avar([(t.term, t.params) for t in self.terms
                           if get_term(t.term).role != "regressor"], tau, self.fs_hz)

    def term_avar_at(self, tau_s: np.ndarray | float) -> dict[str, np.ndarray]:
        """Per-term Allan variance at ``tau_s`` keyed ``term`` (``term#2`` for repeats)."""
        tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
        return {key: _term_avar(t.term, t.params, tau, self.fs_hz)
                for key, t in zip(labels([t.term for t in self.terms]), self.terms,
                                  strict=True)}

    def allan_dict(self, ci_low: np.ndarray | None = None, ci_high: np.ndarray | None = None
                   ) -> dict[str, list[float]]:
        """The JSON ``allan`` block (docs/json.md; deviations, not variances)."""
        adev = np.sqrt(self.avar_measured)
        return {"tau_s": self.tau_s.tolist(), "adev": adev.tolist(),
                "ci_low": (ci_low if ci_low is not None else adev).tolist(),
                "ci_high": (ci_high if ci_high is not None else adev).tolist(),
                "model_adev": np.sqrt(self.avar_fit).tolist(),
                "z": self.misfit.z.tolist()}


def _term_avar(name: str, params: dict[str, float], tau: np.ndarray, fs: float) -> np.ndarray:
    term = get_term(name)
    if term.role == "regressor":
        return np.zeros_like(tau)
    return term.avar(tau, fs, **params)


# --- starting values ------------------------------------------------------------------------

def _linear_shape(name: str, tau: np.ndarray, fs: float) -> np.ndarray:
    return get_term(name).unit_avar(tau, fs, {})


def _nnls_weighted(design: np.ndarray, avar: np.ndarray, w: np.ndarray
                   ) -> tuple[np.ndarray, float]:
    a = design / avar[:, None] * w[:, None]
    b = w.copy()
    scale = np.max(np.abs(a), axis=0)
    scale[scale == 0] = 1.0
    coef, rnorm = optimize.nnls(a / scale, b, maxiter=50 * a.shape[1])
    return coef / scale, float(rnorm)


def _start_values(names: list[str], tau: np.ndarray, avar: np.ndarray, fs: float,
                  nu: np.ndarray, duration_s: float, line: tuple[float, float] | None,
                  fixed: dict[tuple[int, str], float] | None = None) -> list[dict[str, float]]:
    """Starting parameters: the linear terms' squared amplitudes by one weighted NNLS solve;
    each nonlinear term (in model order) by a grid search over its shape parameters
    (``Term.start_shapes``, a fixed value taking the grid's place) with its amplitude
    linear."""
    fixed = fixed or {}
    w = np.sqrt(nu / 2.0)
    columns: list[np.ndarray] = []
    owners: list[int] = []
    for i, n in enumerate(names):
        term = get_term(n)
        if term.linear and term.role != "regressor":
            columns.append(_linear_shape(n, tau, fs))
            owners.append(i)
    shapes: dict[int, dict[str, float]] = {}
    base = np.stack(columns, axis=1) if columns else np.zeros((len(tau), 0))

    def solve(extra_cols: list[np.ndarray]) -> tuple[np.ndarray, float]:
        d = np.concatenate([base] + [c[:, None] for c in extra_cols], axis=1)
        if d.shape[1] == 0:
            return np.zeros(0), float(np.sum(w * w))
        return _nnls_weighted(d, avar, w)

    extra_cols: list[np.ndarray] = []
    extra_owner: list[int] = []
    for i, n in enumerate(names):
        term = get_term(n)
        if term.linear or term.role == "regressor" or term.kind == "filter":
            continue
        held = {k: fixed[(i, k)] for k in term.shape_params if (i, k) in fixed}
        candidates = [{**c, **held} for c in term.start_shapes(fs, duration_s, line)]
        if held and len(held) == len(term.shape_params):
            candidates = [held]
        best = None
        for cand in candidates:
            col = term.unit_avar(tau, fs, cand)
            _, r = solve(extra_cols + [col]) if len(candidates) > 1 else (None, 0.0)
            if best is None or r < best[0]:
                best = (r, cand, col)
        if best is None:  # no start shape fits a record this short: a bad input, not a bug
            raise ValueError(f"{n}: no starting shape for a record of {duration_s:.3g} s")
        extra_cols.append(best[2])
        extra_owner.append(i)
        shapes[i] = {k: float(v) for k, v in best[1].items()}
    coef, _ = solve(extra_cols)
    start: list[dict[str, float]] = [dict() for _ in names]
    for i, n in enumerate(names):
        term = get_term(n)
        if term.kind == "filter":
            start[i] = {**term.start_params(fs),
                        **{k: fixed[(i, k)] for k in term.param_names if (i, k) in fixed}}
    all_owners = owners + extra_owner
    all_cols = list(base.T) + extra_cols
    for c, owner, col in zip(coef, all_owners, all_cols, strict=True):
        # a term the data do not need starts small but positive (log parameters)
        floor = 1e-4 * float(np.min(avar / np.maximum(col, 1e-300)))
        c2 = max(float(c), floor)
        term = get_term(names[owner])
        amp = math.sqrt(c2)
        if not term.linear:
            amp = term.start_amplitude(amp if c > 0 else 0.0, line) or amp
        start[owner] = {term.amplitude: amp, **shapes.get(owner, {})}
    return start


# --- the fit --------------------------------------------------------------------------------

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


def _solve(layout: _Layout, theta0: np.ndarray, y: np.ndarray, tau: np.ndarray,
           m: np.ndarray, n_terms: np.ndarray, fs: float, max_nfev: int) -> np.ndarray:
    """GLS on ln(avar): whitening from the model at the current point, solved, refreshed once.
    A start outside the bounds (a Markov T shorter than the two sample periods it may take) is
    moved onto them."""
    theta = np.clip(theta0, layout.lo, layout.hi)
    for _ in range(2):
        params = _unpack(layout, theta)
        whiten, bias, _ = _log_weights(_model_terms(layout, params), fs, m, n_terms,
                                       _avar_of(layout, params, tau, fs))

        def resid(th: np.ndarray, whiten: np.ndarray = whiten, bias: np.ndarray = bias
                  ) -> np.ndarray:
            mod = _avar_of(layout, _unpack(layout, th), tau, fs)
            return whiten @ (y - np.log(np.maximum(mod, 1e-300)) - bias)

        sol = optimize.least_squares(resid, theta, bounds=(layout.lo, layout.hi),
                                     method="trf", max_nfev=max_nfev, loss=_LOSS,
                                     f_scale=_F_SCALE)
        moved = float(np.max(np.abs(sol.x - theta))) if theta.size else 0.0
        theta = sol.x
        if moved < 0.02:
            break
    return theta


def _neg2_loglik(layout: _Layout, theta: np.ndarray, y: np.ndarray, tau: np.ndarray,
                 m: np.ndarray, n_terms: np.ndarray, fs: float) -> float:
    """-2 log-likelihood of ln(avar) under the model at ``theta`` (Gaussian approximation with
    the model's own covariance), to choose among local optima."""
    params = _unpack(layout, theta)
    avar_model = _avar_of(layout, params, tau, fs)
    whiten, bias, _ = _log_weights(_model_terms(layout, params), fs, m, n_terms, avar_model)
    r = whiten @ (y - np.log(np.maximum(avar_model, 1e-300)) - bias)
    logdet = -2.0 * float(np.sum(np.log(np.abs(np.linalg.eigvalsh(whiten @ whiten.T)))) / 2.0)
    return float(r @ r) + logdet


def _bumped_starts(names: list[str], start: list[dict[str, float]], tau: np.ndarray,
                   avar: np.ndarray, fs: float) -> list[list[dict[str, float]]]:
    """Extra starting points: each linear term that the linear solve left near zero is raised
    to a third of the measured AVAR where its shape is most prominent. Correlated terms (rate
    random walk and ramp, flicker and a Markov bias) otherwise let one term swallow the other
    and the fit settle in the wrong valley."""
    out: list[list[dict[str, float]]] = []
    for i, n in enumerate(names):
        term = get_term(n)
        if not term.linear or term.role == "regressor":
            continue
        key = term.amplitude
        shape = _linear_shape(n, tau, fs)
        level = float(np.max(shape / avar))  # 1/c at which the term alone reaches the data
        c_now = start[i][key] ** 2
        if c_now * level < 0.05:
            bumped = [dict(p) for p in start]
            bumped[i][key] = math.sqrt(0.3 / level)
            out.append(bumped)
    return out


@one_blas_thread
def fit_allan(curve: CurveLike, model: ModelLike, *, start: Any = None,
              line: tuple[float, float] | None = None, temperature: TermFit | None = None,
              fixed: dict[str | int, dict[str, float]] | None = None,
              family_rate: float = 0.10, max_nfev: int = 200,
              intervals: str = "profile", memo: dict | None = None) -> FitResult:
    """Fit a sum of noise terms to a measured overlapping Allan curve.

    Args:
        curve: the measured curve (``imunoise.analysis.allan.AllanCurve`` or any object with
        ``fs_hz``,
            ``tau_s``, ``m``, ``dev``, ``n_terms``; ``edf`` is used for starting values when
            present).
        model: term names (``"white,random_walk"`` or a list) or ``[(term, params)]``; given
            parameters are starting values.
        start: a previous :class:`FitResult` or ``[(term, params)]`` to start from (a cheap
            refit: the starting-value search is skipped).
        line: ``(f_hz, amplitude)`` of the strongest spectral line, the start of a sinusoid.
        temperature: the fitted temperature coefficient (from :func:`regress_temperature`),
            carried into the result when the model holds ``temperature``.
        fixed: parameters held at known values, keyed by term name (its first occurrence)
            or model index, e.g. ``{"gauss_markov": {"T": 100.0}}``; their interval is the
            value itself.
        family_rate: probability that a correct model reports any failure (sets the |z|
            threshold).
        max_nfev: cap on model evaluations of the least-squares solver.
        memo: a dict shared by fits of one curve (the diagnosis's candidates): the solutions
            of the nested models each fit starts from are computed once.
        intervals: ``"profile"`` (profile likelihood: the other parameters re-fitted while
            one is moved until chi2 rises by 3.84; honest for weakly determined terms, about
            0.1-0.5 s) or ``"jacobian"`` (linearised, log-parameter space; for quick refits).

    Solutions: the fit is solved from several starts (the linear solve, each near-zero linear
    term raised, the linear solve with every tau weighted alike and, unless ``start`` is given,
    the solution of the model without its last term with that term at zero and at its own
    start) and the one with the smallest reported misfit ``chi2`` wins (the first of those
    within 0.05 of it, the solver's tolerance). The model without its last term is itself
    fitted this way, so appending a term to a model (the diagnosis's ``apply.model``) never
    raises ``chi2`` by more than that tolerance.

    Raises:
        TermError: unknown term, or a model with no term to fit.
        ValueError: a curve with fewer taus than free parameters, or non-positive values.
    """
    parsed = parse_model(model)
    prob = _problem(curve, parsed, fixed, family_rate, max_nfev)
    if prob.n_free == 0:
        # every parameter given: the model is evaluated as it stands, nothing fitted
        theta = np.zeros(0)
        return _result(prob, _Point(theta, np.ones(len(prob.tau), dtype=bool),
                                    _chi2(prob, theta)), intervals, temperature)
    memo = {} if memo is None else memo
    _hold(memo, curve)
    folded = _folded(parsed, prob)
    key = _memo_key(curve, folded, line)
    hit = memo.get(key) if start is None else None
    if hit is not None:
        point = hit[1]
    else:
        point = _best_point(prob, curve, folded, start, line, memo)
        if start is None:
            memo[key] = (prob, point)
    return _result(prob, point, intervals, temperature)


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


def _solve_all(prob: _Problem, theta0: np.ndarray) -> _Point:
    """Solve from ``theta0`` on every tau."""
    lay = prob.layout
    theta = _solve(lay, theta0, prob.y, prob.tau, prob.m, prob.n_terms, prob.fs, prob.max_nfev)
    return _Point(theta, np.ones(len(prob.tau), dtype=bool), _chi2(prob, theta))


def _trim(prob: _Problem, theta: np.ndarray) -> _Point:
    """While the shortest tau still used lies below the model's band, set it aside and refit.

    A sensor's anti-aliasing and decimation filters make the shortest taus fall below any sum
    of the terms; they are reported as failures without dragging the parameters. A refit that
    leaves a tau set aside above the model by more than the failure threshold (no filter lifts
    a tau) and raises chi2 over the whole curve is undone and trimming stops there: without its
    shortest tau a term can take over another's part (a Markov term the white noise's), and the
    choice hung on a z a hair either side of the threshold, so the same curve's fit moved by a
    factor of two with the rounding of the machine's linear algebra. Where such a refit lowers
    the whole curve's chi2 it is kept, as before."""
    lay, tau, m, n_terms = prob.layout, prob.tau, prob.m, prob.n_terms
    used = np.ones(len(tau), dtype=bool)
    threshold = failure_threshold(len(tau), prob.family_rate)

    def z_of(th: np.ndarray, mask: np.ndarray) -> np.ndarray:
        params = _unpack(lay, th)
        avar_fit = _avar_of(lay, params, tau, prob.fs)
        cov = _covariance(_model_terms(lay, params), prob.fs, m[mask], n_terms[mask])
        return misfit(prob.avar[mask], avar_fit[mask], cov, prob.n_free,
                      prob.family_rate).z

    for first in range(min(_MAX_SHORT_TRIM, len(tau))):
        if len(tau) - first - 1 < prob.n_free + 3:
            break
        if z_of(theta, used)[0] >= -threshold:
            break  # a filter pulls the shortest taus below the model, never above it
        trial_used = used.copy()
        trial_used[first] = False
        trial = _solve(lay, theta, prob.y[trial_used], tau[trial_used], m[trial_used],
                       n_terms[trial_used], prob.fs, prob.max_nfev)
        if np.any(z_of(trial, ~trial_used) > threshold) and \
                _chi2(prob, trial) > _chi2(prob, theta):
            break
        theta, used = trial, trial_used
    return _Point(theta, used, _chi2(prob, theta))


def _cold_starts(prob: _Problem, line: tuple[float, float] | None
                 ) -> list[list[dict[str, float]]]:
    """Starting points without a previous fit: the linear solve weighted by each estimate's
    degrees of freedom, the same with every tau weighted alike (it follows the long taus the
    first neglects) and each near-zero linear term raised."""
    names, lay = prob.names, prob.layout
    if all(p is not None for _, p in prob.spec):
        return [[dict(p or {}) for _, p in prob.spec]]
    out = []
    for nu in (prob.nu0, np.full_like(prob.nu0, 2.0)):
        first = _start_values(names, prob.tau, prob.avar, prob.fs, nu, prob.duration, line,
                              lay.fixed)
        for i, (_, p) in enumerate(prob.spec):
            if p is not None:
                first[i].update(p)
        out.append(first)
    out += _bumped_starts(names, out[0], prob.tau, prob.avar, prob.fs)
    return out


def _folded(parsed: ModelSpec, prob: _Problem) -> ModelSpec:
    """``parsed`` with every held parameter (also those given by keyword) in its entry."""
    fixed = {i: {k: v for (j, k), v in prob.layout.fixed.items() if j == i}
             for i in range(len(parsed.entries))}
    return ModelSpec(tuple(Entry(e.name, fixed[i], e.start)
                           for i, e in enumerate(parsed.entries)))


def _hold(memo: dict, obj: Any) -> None:
    """Keep ``obj`` alive as long as ``memo``: the memo's keys name curves and series by
    ``id()``, and an object's id is reused once it is freed, so a key of a temporary curve
    would hand its solutions to a later one."""
    memo.setdefault(("held", id(obj)), obj)


def _memo_key(curve: CurveLike, spec: ModelSpec, line: tuple[float, float] | None
              ) -> tuple | None:
    if any(e.start is not None for e in spec.entries):
        return None
    uses_line = any(get_term(n).role == "line" for n in spec.names)
    return (id(curve), spec.text(), line if uses_line else None)


def _prefix(parsed: ModelSpec, prob: _Problem) -> tuple[ModelSpec, int] | None:
    """The model without its last term that has free parameters, and that term's index."""
    free = {i for i, _ in prob.layout.keys}
    if len(free) < 2 or any(e.start is not None for e in parsed.entries):
        return None
    last = max(free)
    return ModelSpec(tuple(e for i, e in enumerate(parsed.entries) if i != last)), last


def _nested_starts(prob: _Problem, curve: CurveLike, parsed: ModelSpec,
                   line: tuple[float, float] | None, memo: dict, cold: list[dict[str, float]]
                   ) -> tuple[list[np.ndarray], _Point | None]:
    """The start from the solution of the model without its last term, with that term at zero
    (also returned unsolved: its chi2 is the smaller model's)."""
    pre = _prefix(parsed, prob)
    if pre is None:
        return [], None
    sub_spec, last = pre
    sub = _memo_point(curve, sub_spec, line, prob, memo)
    if sub is None:
        return [], None
    sub_prob, sub_point = sub
    sub_params = _unpack(sub_prob.layout, sub_point.theta)
    params = sub_params[:last] + [dict(cold[last])] + sub_params[last:]
    term = get_term(prob.names[last])
    params[last] = {**params[last], term.amplitude: 1e-300}
    at_zero = _theta_of(prob, params)
    exact = _Point(at_zero, sub_point.used.copy(), _chi2(prob, at_zero))
    return [at_zero] + _residual_starts(prob, params, last, line), exact


def _residual_starts(prob: _Problem, params: list[dict[str, float]], last: int,
                     line: tuple[float, float] | None, keep: int = 2) -> list[np.ndarray]:
    """Starts for a shaped term (a Markov time constant, a resonance, a line) added to a
    solved smaller model: each shape of its grid (``Term.start_shapes``) is scored by one
    weighted NNLS solve of every amplitude with the other terms' shapes at the smaller
    model's solution; the ``keep`` best start from that solve.

    At zero amplitude a log-parameter has no gradient, and the cold starts place the term's
    shape before the other terms are solved (a Markov term then takes a resonance's bump at
    the shortest taus, or a random walk keeps what the Markov term should take, and the
    solver stays in that valley)."""
    names = prob.names
    term = get_term(names[last])
    if term.linear or term.role == "regressor" or term.kind == "filter" or \
            not term.shape_params:
        return []
    held = {k: v for (i, k), v in prob.layout.fixed.items() if i == last}
    if len(held) >= len(term.shape_params):
        return []
    filters = [(n, p) for n, p in zip(names, params, strict=True)
               if get_term(n).kind == "filter"]

    def column(name: str, shape: dict[str, float]) -> np.ndarray:
        unit = {**shape, get_term(name).amplitude: 1.0}
        return model_avar([(name, unit)] + filters, prob.tau, prob.fs, checked=False)

    owners = [j for j, n in enumerate(names) if j != last and
              get_term(n).role != "regressor" and get_term(n).kind != "filter"]
    cols = [column(names[j], params[j]) for j in owners]
    w = np.sqrt(prob.nu0 / 2.0)
    scored: list[tuple[float, dict[str, float], np.ndarray]] = []
    for cand in term.start_shapes(prob.fs, prob.duration, line):
        cand = {**cand, **held}
        design = np.stack(cols + [column(names[last], cand)], axis=1)
        coef, rnorm = _nnls_weighted(design, prob.avar, w)
        if coef[-1] > 0:
            scored.append((rnorm, cand, coef))
    scored.sort(key=lambda x: x[0])
    out = []
    for _, cand, coef in scored[:keep]:
        trial = [dict(p) for p in params]
        for j, c in zip(owners, coef[:-1], strict=True):
            amp = get_term(names[j]).amplitude
            trial[j][amp] = math.sqrt(max(float(c), 1e-6 * trial[j][amp] ** 2, 1e-300))
        trial[last] = {**trial[last], **cand, term.amplitude: math.sqrt(float(coef[-1]))}
        out.append(_theta_of(prob, trial))
    return out


def _memo_point(curve: CurveLike, spec: ModelSpec, line: tuple[float, float] | None,
                prob: _Problem, memo: dict) -> tuple[_Problem, _Point] | None:
    key = _memo_key(curve, spec, line)
    if key not in memo:
        try:
            sub_prob = _problem(curve, spec, None, prob.family_rate, prob.max_nfev)
            memo[key] = (sub_prob, _best_point(sub_prob, curve, spec, None, line, memo))
        except (ValueError, np.linalg.LinAlgError):
            memo[key] = None
    return memo[key]


def _best_point(prob: _Problem, curve: CurveLike, parsed: ModelSpec, start: Any,
                line: tuple[float, float] | None, memo: dict) -> _Point:
    """The candidate with the smallest reported chi2 (the first of equals)."""
    if start is not None:
        start_params = start.params if isinstance(start, FitResult) else list(start)
        thetas = [_theta_of(prob, _match_start(prob.names, start_params))]
        exact = None
    else:
        cold = _cold_starts(prob, line)
        thetas = [_theta_of(prob, c) for c in cold]
        nested, exact = _nested_starts(prob, curve, parsed, line, memo, cold[0])
        thetas += nested
    distinct: list[np.ndarray] = []
    for theta0 in thetas:  # a start within 10 % of an earlier one adds nothing
        if all(np.max(np.abs(theta0 - d)) > 0.1 for d in distinct):
            distinct.append(theta0)
    points = [_solve_all(prob, theta0) for theta0 in distinct]
    # chi2 differences below the solver's tolerance do not count: the first start among the
    # near-best wins (the order of the starts is fixed, so equal curves give equal models)
    low = min(p.chi2 for p in points)
    whole = next(p for p in points if p.chi2 <= low + _CHI2_TIE)
    best = _trim(prob, whole.theta)
    # the smaller model's solution itself when every solve does worse: adding a term never
    # raises chi2 (by more than the solver's tolerance). Setting the shortest taus aside costs
    # chi2 (the parameters then rest on the taus the model can follow); when the new term's
    # solution on the whole curve has less than half the smaller model's chi2, the term
    # explains most of the misfit and that solution is kept instead
    if exact is not None and exact.chi2 < best.chi2 - _CHI2_TIE:
        best = whole if whole.chi2 < _WHOLE_WINS * exact.chi2 else exact
    assert best is not None
    return best


def _result(prob: _Problem, point: _Point, intervals: str, temperature: TermFit | None
            ) -> FitResult:
    names, layout, fs, tau = prob.names, prob.layout, prob.fs, prob.tau
    m, n_terms, avar, theta, used = prob.m, prob.n_terms, prob.avar, point.theta, point.used
    params = _unpack(layout, theta)
    model_final = _model_terms(layout, params)
    avar_fit = _avar_of(layout, params, tau, fs)
    cov = _covariance(model_final, fs, m, n_terms)
    mf = misfit(avar, avar_fit, cov, prob.n_free, prob.family_rate)
    ci, param_cov = _intervals(prob, point, model_final, avar_fit, intervals)
    terms_out: list[TermFit] = []
    for i, n in enumerate(names):
        if get_term(n).role == "regressor":
            if temperature is None:
                raise TermError("the temperature term needs a temperature record: fit the "
                                "series with fit_series(..., temperature=...)")
            terms_out.append(temperature)
        else:
            terms_out.append(TermFit(n, params[i], ci[i]))
    term_avar = [_term_avar(t.term, t.params, tau, fs) for t in terms_out]
    return FitResult(terms=terms_out, fs_hz=fs, tau_s=tau, m=m.astype(np.int64),
                     n_terms=n_terms.astype(np.int64), avar_measured=avar, avar_fit=avar_fit,
                     term_avar=term_avar, misfit=mf,
                     failures=failures(tau, mf.z, mf.threshold), param_cov=param_cov,
                     free_params=list(layout.keys), used=used)


def _intervals(prob: _Problem, point: _Point, model_final: list, avar_fit: np.ndarray,
               intervals: str) -> tuple[list[dict[str, tuple[float, float]]], np.ndarray]:
    """95 % intervals: linearised in log-parameter space, or by profile likelihood."""
    layout, fs, used, theta = prob.layout, prob.fs, point.used, point.theta
    if prob.n_free == 0:
        return ([{k: (float(v), float(v)) for (i, k), v in layout.fixed.items() if i == j}
                 for j in range(len(prob.names))], np.zeros((0, 0)))
    whiten, bias, _ = _log_weights(model_final, fs, prob.m[used], prob.n_terms[used],
                                   avar_fit[used])
    y_used, tau_used = prob.y[used], prob.tau[used]

    def resid_final(th: np.ndarray) -> np.ndarray:
        mod = _avar_of(layout, _unpack(layout, th), tau_used, fs)
        return whiten @ (y_used - np.log(np.maximum(mod, 1e-300)) - bias)

    jac = _jacobian(resid_final, theta)
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
    base = None
    if intervals == "profile" or np.any(weak):
        full = optimize.least_squares(resid_final, theta, bounds=(layout.lo, layout.hi),
                                      method="trf", max_nfev=60)
        base = min(2.0 * float(full.cost), float(np.sum(resid_final(theta) ** 2)))
    for idx, ((i, k), th, s) in enumerate(zip(layout.keys, theta, sd, strict=True)):
        if intervals == "profile" or weak[idx]:
            lo, hi = _profile_interval(resid_final, theta, idx, layout, s, base)
        else:
            lo, hi = th - _Z95 * s, th + _Z95 * s
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


def _profile_interval(resid: Any, theta: np.ndarray, idx: int, layout: _Layout, sd: float,
                      base: float) -> tuple[float, float]:
    """95 % profile-likelihood interval of log-parameter ``idx`` (whitening held fixed;
    ``base`` is the minimum of the plain sum of squares)."""
    others = [j for j in range(theta.size) if j != idx]

    def excess(v: float, guess: np.ndarray) -> tuple[float, np.ndarray]:
        th = theta.copy()
        th[idx] = v
        if not others:
            return float(np.sum(resid(th) ** 2)) - base, guess

        def sub(x: np.ndarray) -> np.ndarray:
            th2 = th.copy()
            th2[others] = x
            return resid(th2)

        lo_b, hi_b = layout.lo[others], layout.hi[others]
        x0 = np.clip(guess, lo_b + 1e-9, hi_b - 1e-9)
        sol = optimize.least_squares(sub, x0, bounds=(lo_b, hi_b), method="trf", max_nfev=40)
        return 2.0 * float(sol.cost) - base, sol.x

    step = max(2.0 * _Z95 * sd, 0.05) if np.isfinite(sd) and sd > 0 else 1.0
    return profile_bounds(excess, float(theta[idx]), float(layout.lo[idx]),
                          float(layout.hi[idx]), step, _CHI2_95_1DOF, theta[others],
                          bisections=5, width=_PROFILE_WIDTH)


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


# --- helpers on the series ------------------------------------------------------------------

def find_line(values: np.ndarray, fs_hz: float, min_snr: float = 10.0
              ) -> tuple[float, float] | None:
    """Frequency (Hz) and amplitude (units) of the strongest spectral line, or None.

    Welch spectrum (Hann, up to 2^15 samples per segment); the line is the bin standing
    furthest above the running median of its neighbourhood (by at least ``min_snr``); its
    power is the excess summed over the main lobe (``A = sqrt(2 P)``)."""
    x = np.asarray(values, dtype=np.float64)
    if x.size < 64:
        return None
    nper = int(min(1 << 15, 1 << int(math.log2(x.size))))
    f, p = signal.welch(x - x.mean(), fs=fs_hz, nperseg=nper)
    if p.size < 16:
        return None
    floor = np.maximum(ndimage.median_filter(p, size=31, mode="nearest"), 1e-300)
    ratio = p / floor
    ratio[:4] = 0.0  # the lowest bins carry drift, not lines
    ratio[-4:] = 0.0  # nor does the edge at the Nyquist frequency
    k = int(np.argmax(ratio))
    if ratio[k] < min_snr:
        return None
    lo, hi = max(k - 3, 0), min(k + 4, p.size)
    df = f[1] - f[0]
    power = float(np.sum(p[lo:hi] - floor[lo:hi]) * df)
    weights = p[lo:hi] - floor[lo:hi]
    f_line = float(np.sum(f[lo:hi] * weights) / np.sum(weights))
    return f_line, math.sqrt(max(2.0 * power, 0.0))


def regress_temperature(rate: np.ndarray, temperature: np.ndarray, blocks: int = 10
                        ) -> tuple[TermFit, np.ndarray]:
    """Least-squares regression of the rate on temperature (with offset).

    Returns the ``temperature`` term (coef in rate units per degC, 95 % interval) and the
    corrected rate ``rate - coef (temperature - mean temperature)``. The interval comes from
    refitting the coefficient on ``blocks`` contiguous blocks (Student t on their spread),
    which stays honest when the residual noise is coloured, as it is for inertial sensors.
    """
    y = np.asarray(rate, dtype=np.float64)
    t = np.asarray(temperature, dtype=np.float64)
    if y.shape != t.shape:
        raise ValueError(f"temperature record has {t.size} samples, rate {y.size}")
    if not np.all(np.isfinite(t)):
        raise ValueError("temperature record holds non-finite values")
    tc = t - t.mean()
    sxx = float(tc @ tc)
    if sxx <= 0:
        raise ValueError("temperature is constant: its coefficient cannot be estimated")
    coef = float(tc @ (y - y.mean()) / sxx)
    per_block = []
    for yb, tb in zip(np.array_split(y, blocks), np.array_split(t, blocks), strict=True):
        tbc = tb - tb.mean()
        s = float(tbc @ tbc)
        if s > 0:
            per_block.append(float(tbc @ (yb - yb.mean()) / s))
    if len(per_block) >= 3:
        from scipy import stats
        half = float(stats.t.ppf(0.975, len(per_block) - 1) * np.std(per_block, ddof=1)
                     / math.sqrt(len(per_block)))
    else:
        half = math.inf
    term = TermFit("temperature", {"coef": coef}, {"coef": (coef - half, coef + half)})
    return term, y - coef * tc


def series_line(values: np.ndarray, fs_hz: float, segment_starts: np.ndarray | None = None
                ) -> tuple[float, float] | None:
    """The strongest spectral line of the longest gap-free segment (:func:`find_line`): the
    start of a line term in :func:`fit_series`."""
    x = np.asarray(values, dtype=np.float64)
    bounds = np.append(segment_starts if segment_starts is not None else [0], x.size)
    k = int(np.argmax(np.diff(bounds)))
    return find_line(x[bounds[k]:bounds[k + 1]], fs_hz)


def fit_series(values: np.ndarray, fs_hz: float, model: ModelLike, *,
               segment_starts: np.ndarray | None = None,
               temperature: np.ndarray | None = None,
               fixed: dict[str | int, dict[str, float]] | None = None,
               ci: float = 0.95, start: Any = None, memo: dict | None = None,
               intervals: str = "profile") -> tuple[FitResult, Any]:
    """Fit ``model`` to a rate series: Allan curve (octave taus, computed once), spectral line
    for a sinusoid, temperature regression, then :func:`fit_allan`.

    Args:
        values: rate samples in SI units, all segments concatenated.
        fs_hz: sampling rate, Hz.
        model: a model specification (:func:`imunoise.analysis.terms.parse_model`).
        segment_starts: gap-free segment starts (``ChannelSeries.segment_starts``).
        temperature: temperature in degC at each sample (required with ``temperature``).
        fixed: parameters held at known values (see :func:`fit_allan`).
        ci: confidence level of the curve's ``ci_low``/``ci_high``.
        start: starting point of a refit (see :func:`fit_allan`).
        memo: a dict shared by fits of one series (the diagnosis's candidates): its Allan
            curves, spectral line and nested solutions are computed once. A fit with a memo
            gives exactly the numbers of one without.
        intervals: see :func:`fit_allan` (intervals never change the parameters or chi2).

    Returns:
        ``(FitResult, AllanCurve)``; the curve is that of the temperature-corrected series
        when the model holds ``temperature``.
    """
    from imunoise.analysis.allan import oadev

    memo = {} if memo is None else memo
    _hold(memo, values)
    spec = parse_model(model)
    names = spec.names
    x = np.asarray(values, dtype=np.float64)
    temp_term = None
    regressed = any(get_term(n).role == "regressor" for n in names)
    if regressed:
        if temperature is None:
            raise TermError("the temperature term needs a temperature record, and this "
                            "record has none")
        key = ("temperature", id(values), ci)
        if key not in memo:
            memo[key] = regress_temperature(x, np.asarray(temperature, dtype=np.float64))
        temp_term, x = memo[key]
    key = ("curve", id(values), regressed, ci)
    if key not in memo:
        memo[key] = oadev(x, fs_hz, m="octave", segment_starts=segment_starts, ci=ci)
    curve = memo[key]
    line = None
    if any(get_term(n).role == "line" for n in names):
        key = ("line", id(values), regressed)
        if key not in memo:
            memo[key] = series_line(x, fs_hz, segment_starts)
        line = memo[key]
    result = fit_allan(curve, spec, start=start, line=line, temperature=temp_term, fixed=fixed,
                       memo=memo, intervals=intervals)
    return result, curve
