"""Starting values: a linear solve for the linear terms, grids for the shape parameters, and
the starts taken from a smaller model's solution.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from typing import Any

import numpy as np
from scipy import optimize

from imunoise.analysis.fit.problem import _Problem, _theta_of
from imunoise.analysis.terms import (
    Entry,
    ModelSpec,
    get_term,
    model_avar,
)
from imunoise.analysis.terms.output_filter import OutputFilter

Line = tuple[float, float]
"""A spectral line: frequency (Hz) and amplitude (the series' units)."""

Lines = tuple[Line, ...]
"""Spectral lines, strongest first."""


def as_lines(line: Line | Sequence[Line] | None) -> Lines:
    """One line or several (strongest first) as a tuple of lines."""
    if line is None:
        return ()
    items: list[Any] = list(line)
    if len(items) == 2 and all(np.ndim(v) == 0 for v in items):
        return ((float(items[0]), float(items[1])),)
    return tuple((float(f), float(a)) for f, a in items)


def _line_of(names: Sequence[str], index: int, lines: Lines,
             held: Collection[tuple[int, str]]) -> Line | None:
    """The spectral line that starts term ``index``: the k-th line term with a free frequency
    (in model order) starts at the k-th line, none where the spectrum shows fewer (its grid
    then), so two line terms never start on one line and share it; any other shaped term (a
    resonance's grid) at the strongest."""
    if get_term(names[index]).role != "line":
        return lines[0] if lines else None
    rank = sum(1 for i in range(index)
               if get_term(names[i]).role == "line" and (i, "f") not in held)
    return lines[rank] if rank < len(lines) else None


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
                  nu: np.ndarray, duration_s: float, lines: Lines,
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
        line = _line_of(names, i, lines, fixed)
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
        if isinstance(term, OutputFilter):
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
            line = _line_of(names, owner, lines, fixed)
            amp = term.start_amplitude(amp if c > 0 else 0.0, line) or amp
        start[owner] = {term.amplitude: amp, **shapes.get(owner, {})}
    return start


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


def _cold_starts(prob: _Problem, lines: Lines) -> list[list[dict[str, float]]]:
    """Starting points without a previous fit: the linear solve weighted by each estimate's
    degrees of freedom, the same with every tau weighted alike (it follows the long taus the
    first neglects) and each near-zero linear term raised."""
    names, lay = prob.names, prob.layout
    if all(p is not None for _, p in prob.spec):
        return [[dict(p or {}) for _, p in prob.spec]]
    out = []
    for nu in (prob.nu0, np.full_like(prob.nu0, 2.0)):
        first = _start_values(names, prob.tau, prob.avar, prob.fs, nu, prob.duration, lines,
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


def _prefix(parsed: ModelSpec, prob: _Problem) -> tuple[ModelSpec, int] | None:
    """The model without its last term that has free parameters, and that term's index."""
    free = {i for i, _ in prob.layout.keys}
    if len(free) < 2 or any(e.start is not None for e in parsed.entries):
        return None
    last = max(free)
    return ModelSpec(tuple(e for i, e in enumerate(parsed.entries) if i != last)), last


def _residual_starts(prob: _Problem, params: list[dict[str, float]], last: int,
                     lines: Lines, keep: int = 2) -> list[np.ndarray]:
    """Starts for a shaped term (a Markov time constant, a resonance, a line) added to a
    solved smaller model: each shape of its grid (``Term.start_shapes``) is scored by one
    weighted NNLS solve of every amplitude with the other terms' shapes at the smaller
    model's solution; the ``keep`` best start from that solve.

    At zero amplitude a log-parameter has no gradient, and the cold starts place the term's
    shape before the other terms are solved (a Markov term then takes a resonance's bump at
    the shortest taus, or a random walk keeps what the Markov term should take, and the
    solver stays in that valley). An output filter has its own grid
    (:func:`_filter_starts`)."""
    names = prob.names
    term = get_term(names[last])
    if isinstance(term, OutputFilter):
        return _filter_starts(prob, params, last, keep)
    if term.linear or term.role == "regressor" or not term.shape_params:
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
    line = _line_of(names, last, lines, prob.layout.fixed)
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


def _inner_filter_starts(prob: _Problem, params: list[dict[str, float]]
                         ) -> list[np.ndarray]:
    """Cold starts for each output filter with free parameters that is not the model's last
    term: its :meth:`~OutputFilter.cold_grid` scored as :func:`_filter_starts` scores an
    appended filter's grid, from the cold start ``params``. A filter fitted together with
    the terms after it otherwise starts from one guess, and a solve that starts there can
    stop in a valley of the filter's parameter that a term after it holds open."""
    out: list[np.ndarray] = []
    last = len(prob.names) - 1
    for i, name in enumerate(prob.names):
        term = get_term(name)
        if isinstance(term, OutputFilter) and i != last:
            out += _filter_starts(prob, params, i, grid=term.cold_grid(prob.fs))
    return out


def _filter_starts(prob: _Problem, params: list[dict[str, float]], last: int,
                   keep: int = 2, grid: list[dict[str, float]] | None = None
                   ) -> list[np.ndarray]:
    """Starts for an output filter appended to a solved smaller model: each candidate of
    its grid (``OutputFilter.start_grid``) is scored by one weighted NNLS solve of every noise
    amplitude, each noise term's curve taken through the other filters and the candidate; the
    ``keep`` best start from that solve. A filter acts on every noise term at once, so the
    amplitudes move with it: a model that misses elsewhere has a chi2 with several valleys
    in the filter's parameter, and a single start ends in any of them. ``grid``: candidates
    other than the filter's start grid (the filter at index ``last`` need not be the model's
    last term then)."""
    names = prob.names
    term = get_term(names[last])
    assert isinstance(term, OutputFilter)
    held = {k: v for (i, k), v in prob.layout.fixed.items() if i == last}
    if grid is None:
        grid = term.start_grid(prob.fs)
    if not grid or held:
        return []
    others = [(n, p) for j, (n, p) in enumerate(zip(names, params, strict=True))
              if j != last and get_term(n).kind == "filter"]
    owners = [j for j, n in enumerate(names) if j != last and
              get_term(n).role != "regressor" and get_term(n).kind != "filter"]
    if not owners:
        return []
    w = np.sqrt(prob.nu0 / 2.0)
    scored: list[tuple[float, dict[str, float], np.ndarray]] = []
    for cand in grid:
        filters = others + [(names[last], cand)]
        cols = []
        for j in owners:
            owner = get_term(names[j])
            unit = {**params[j], owner.amplitude: 1.0}
            cols.append(model_avar([(names[j], unit)] + filters, prob.tau, prob.fs,
                                   checked=False))
        coef, rnorm = _nnls_weighted(np.stack(cols, axis=1), prob.avar, w)
        scored.append((rnorm, cand, coef))
    scored.sort(key=lambda x: x[0])
    out = []
    for _, cand, coef in scored[:keep]:
        trial = [dict(p) for p in params]
        for j, c in zip(owners, coef, strict=True):
            amp = get_term(names[j]).amplitude
            trial[j][amp] = math.sqrt(max(float(c), 1e-6 * trial[j][amp] ** 2, 1e-300))
        trial[last] = {**trial[last], **cand}
        out.append(_theta_of(prob, trial))
    return out
