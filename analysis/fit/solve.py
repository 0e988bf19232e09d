"""The weighted least-squares solve on ln(avar), the choice among its starts, setting failing
shortest taus aside, and :func:`fit_allan`.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from typing import Any, cast

import numpy as np
from scipy import optimize

from imunoise.analysis.blas import one_blas_thread
from imunoise.analysis.fit.intervals import _intervals
from imunoise.analysis.fit.layout import (
    _avar_of,
    _AvarModel,
    _covariance,
    _Layout,
    _log_weights,
    _LogResidual,
    _match_start,
    _model_terms,
    _unpack,
)
from imunoise.analysis.fit.problem import _chi2, _Point, _Problem, _problem, _theta_of
from imunoise.analysis.fit.result import CurveLike, FitResult, ModelLike, TermFit, _term_avar
from imunoise.analysis.fit.starts import (
    Line,
    Lines,
    _cold_starts,
    _folded,
    _inner_filter_starts,
    _prefix,
    _residual_starts,
    as_lines,
)
from imunoise.analysis.jobs import JobMap, serial_map
from imunoise.analysis.misfit import failure_threshold, failures, misfit
from imunoise.analysis.terms import (
    ModelSpec,
    TermError,
    get_term,
    parse_model,
)
from imunoise.analysis.terms.output_filter import OutputFilter

_LOSS = "soft_l1"


_MAX_SHORT_TRIM = 4


_F_SCALE = 3.0


_CHI2_TIE = 0.05  # chi2 differences below this are the solver's tolerance


_WHOLE_WINS = 0.5


def _solve(layout: _Layout, theta0: np.ndarray, y: np.ndarray, tau: np.ndarray,
           m: np.ndarray, n_terms: np.ndarray, fs: float, max_nfev: int) -> np.ndarray:
    """GLS on ln(avar): whitening from the model at the current point, solved, refreshed once.
    A start outside the bounds (a Markov T shorter than the two sample periods it may take) is
    moved onto them."""
    theta = np.clip(theta0, layout.lo, layout.hi)
    avar = _AvarModel(layout, tau, fs)
    for _ in range(2):
        params = _unpack(layout, theta)
        whiten, bias, _ = _log_weights(_model_terms(layout, params), fs, m, n_terms,
                                       avar.value(theta))
        resid = _LogResidual(avar, y, whiten, bias)
        sol = optimize.least_squares(resid, theta, jac=resid.jac, bounds=(layout.lo, layout.hi),
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


@one_blas_thread
def fit_allan(curve: CurveLike, model: ModelLike, *, start: Any = None,
              line: Line | Sequence[Line] | None = None, temperature: TermFit | None = None,
              fixed: dict[str | int, dict[str, float]] | None = None,
              family_rate: float = 0.10, max_nfev: int = 200,
              intervals: str = "profile", memo: dict | None = None,
              job_map: JobMap = serial_map,
              profile_terms: Collection[int] | None = None) -> FitResult:
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
        line: ``(f_hz, amplitude)`` of the strongest spectral line, the start of a sinusoid,
            or several such lines, strongest first: the model's line terms with a free
            frequency start one at each, in model order; other shaped terms start at the first.
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
        job_map: runs the parameters' profile intervals (:mod:`imunoise.analysis.jobs`);
            the result is the same whichever runs them.
        profile_terms: with ``"jacobian"``, the terms (model indices) whose weakly
            determined parameters (an amplitude near zero, a log-scale standard error above
            0.5) still get their profile interval; the weakly determined parameters of the
            other terms get none, ``(nan, nan)``, rather than a linearised interval that
            could not be trusted. Default: every term. The diagnosis's candidate refits
            report the appended term's intervals only, so they profile that term and the
            white noise alone.

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
                                    _chi2(prob, theta)), intervals, temperature, job_map,
                       profile_terms)
    memo = {} if memo is None else memo
    _hold(memo, curve)
    folded = _folded(parsed, prob)
    # no key for a model with starting values: its solution depends on them
    lines = as_lines(line)
    key = _memo_key(curve, folded, lines) if start is None else None
    hit = memo.get(key) if key is not None else None
    if hit is not None:
        point = hit[1]
    else:
        point = _best_point(prob, curve, folded, start, lines, memo)
        if key is not None:
            memo[key] = (prob, point)
    return _result(prob, point, intervals, temperature, job_map, profile_terms)


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
    the whole curve's chi2 it is kept, as before.

    A model with an output filter term is never trimmed: its filter states what the shortest
    taus should be, so a tau below it is a misfit the whole curve reports. Trimmed, the other
    terms follow the remaining taus instead: ADIS16405 run 2 accel_y's second half, predicted
    by the first half's model with the 10 Hz resonance's f0 and Q left free, set its two
    shortest taus aside and moved the resonance from 10.2 to 11.9 Hz, raising the whole
    curve's chi2 from 71 to 133."""
    lay, tau, m, n_terms = prob.layout, prob.tau, prob.m, prob.n_terms
    used = np.ones(len(tau), dtype=bool)
    if any(get_term(n).kind == "filter" for n in prob.names):
        return _Point(theta, used, _chi2(prob, theta))
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


def _hold(memo: dict, obj: Any) -> None:
    """Keep ``obj`` alive as long as ``memo``: the memo's keys name curves and series by
    ``id()``, and an object's id is reused once it is freed, so a key of a temporary curve
    would hand its solutions to a later one."""
    memo.setdefault(("held", id(obj)), obj)


def _memo_key(curve: CurveLike, spec: ModelSpec, lines: Lines) -> tuple | None:
    if any(e.start is not None for e in spec.entries):
        return None
    uses_line = any(get_term(n).role == "line" for n in spec.names)
    return (id(curve), spec.text(), lines if uses_line else None)


def _nested_starts(prob: _Problem, curve: CurveLike, parsed: ModelSpec,
                   lines: Lines, memo: dict, cold: list[dict[str, float]]
                   ) -> tuple[list[np.ndarray], _Point | None]:
    """The start from the solution of the model without its last term, with that term at zero
    (also returned unsolved: its chi2 is the smaller model's)."""
    pre = _prefix(parsed, prob)
    if pre is None:
        return [], None
    sub_spec, last = pre
    sub = _memo_point(curve, sub_spec, lines, prob, memo)
    if sub is None:
        return [], None
    sub_prob, sub_point = sub
    sub_params = _unpack(sub_prob.layout, sub_point.theta)
    params = sub_params[:last] + [dict(cold[last])] + sub_params[last:]
    term = get_term(prob.names[last])
    if isinstance(term, OutputFilter):  # a filter's "zero" is no filtering, not amplitude 0
        params[last] = {**params[last], **term.identity_params(prob.fs)}
    else:
        params[last] = {**params[last], term.amplitude: 1e-300}
    at_zero = _theta_of(prob, params)
    exact = _Point(at_zero, sub_point.used.copy(), _chi2(prob, at_zero))
    return [at_zero] + _residual_starts(prob, params, last, lines), exact


def _memo_point(curve: CurveLike, spec: ModelSpec, lines: Lines,
                prob: _Problem, memo: dict) -> tuple[_Problem, _Point] | None:
    key = _memo_key(curve, spec, lines)
    if key not in memo:
        try:
            sub_prob = _problem(curve, spec, None, prob.family_rate, prob.max_nfev)
            memo[key] = (sub_prob, _best_point(sub_prob, curve, spec, None, lines, memo))
        except (ValueError, np.linalg.LinAlgError):
            memo[key] = None
    return memo[key]


_STUCK_CHI2_PER_DOF = 10.0
"""Reported chi2 (every tau) per degree of freedom (the taus the solution rests on, less its
free parameters) above which a fit also solves its inner filters' grids."""


def _filter_may_be_stuck(prob: _Problem, best: _Point) -> bool:
    """Whether the best solution from the usual starts may have a filter that is not the
    model's last term stuck short of the minimum: the filter sits on a kink of the chi2 in
    its parameter (:meth:`OutputFilter.kink`), or the model misses its curve by more than
    :data:`_STUCK_CHI2_PER_DOF` (the filter can then sit in the wrong valley of a model one
    term short, from which the nested start of the whole model sets out). Only then are the
    filters' grids (:func:`_inner_filter_starts`) solved too: they cost two solves each."""
    last = len(prob.names) - 1
    inner = [i for i, name in enumerate(prob.names)
             if i != last and isinstance(get_term(name), OutputFilter)
             and any(j == i for j, _ in prob.layout.keys)]
    if not inner:
        return False
    dof = max(int(np.count_nonzero(best.used)) - len(prob.layout.keys), 1)
    if best.chi2 / dof > _STUCK_CHI2_PER_DOF:
        return True
    params = _unpack(prob.layout, best.theta)
    return any(cast(OutputFilter, get_term(prob.names[i])).kink(params[i]) for i in inner)


def _best_point(prob: _Problem, curve: CurveLike, parsed: ModelSpec, start: Any,
                lines: Lines, memo: dict) -> _Point:
    """The candidate with the smallest reported chi2 (the first of equals)."""
    if start is not None:
        start_params = start.params if isinstance(start, FitResult) else list(start)
        thetas = [_theta_of(prob, _match_start(prob.names, start_params))]
        exact = None
    else:
        cold = _cold_starts(prob, lines)
        thetas = [_theta_of(prob, c) for c in cold]
        nested, exact = _nested_starts(prob, curve, parsed, lines, memo, cold[0])
        thetas += nested
    distinct: list[np.ndarray] = []
    for theta0 in thetas:  # a start within 10 % of an earlier one adds nothing
        if all(np.max(np.abs(theta0 - d)) > 0.1 for d in distinct):
            distinct.append(theta0)
    points = [_solve_all(prob, theta0) for theta0 in distinct]
    if start is None and _filter_may_be_stuck(prob, min(points, key=lambda p: p.chi2)):
        # not thinned against the other starts: beside a kink, starts a few per cent apart
        # end on different sides of it
        points += [_solve_all(prob, theta0) for theta0 in _inner_filter_starts(prob, cold[0])]
    # chi2 differences below the solver's tolerance do not count: the first start among the
    # near-best wins (the order of the starts is fixed, so equal curves give equal models)
    low = min(p.chi2 for p in points)
    whole = next(p for p in points if p.chi2 <= low + _CHI2_TIE)
    best = _trim(prob, whole.theta)
    # the smaller model's solution itself when every solve does worse: adding a term never
    # raises chi2 (by more than the solver's tolerance). Setting the shortest taus aside costs
    # chi2 (the parameters then rest on the taus the model can follow); the new term's
    # solution on the whole curve is kept instead when it has less than half the smaller
    # model's chi2 (the term explains most of the misfit), or when the smaller model itself
    # rests on every tau: then both stand on the same taus and the lower chi2 is the better
    # description (a line behind a low-pass whose solution trims the filter's taus)
    if exact is not None and exact.chi2 < best.chi2 - _CHI2_TIE:
        same_taus = bool(np.all(exact.used)) and whole.chi2 < exact.chi2 - _CHI2_TIE
        best = whole if same_taus or whole.chi2 < _WHOLE_WINS * exact.chi2 else exact
    assert best is not None
    return best


def _result(prob: _Problem, point: _Point, intervals: str, temperature: TermFit | None,
            job_map: JobMap = serial_map, profile_terms: Collection[int] | None = None
            ) -> FitResult:
    names, layout, fs, tau = prob.names, prob.layout, prob.fs, prob.tau
    m, n_terms, avar, theta, used = prob.m, prob.n_terms, prob.avar, point.theta, point.used
    params = _unpack(layout, theta)
    model_final = _model_terms(layout, params)
    avar_fit = _avar_of(layout, params, tau, fs)
    cov = _covariance(model_final, fs, m, n_terms)
    mf = misfit(avar, avar_fit, cov, prob.n_free, prob.family_rate)
    ci, param_cov = _intervals(prob, point, model_final, avar_fit, intervals, job_map,
                               profile_terms)
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
