"""Replicates: several recordings of one unit described by one model.

Each run is fitted alone (:func:`imunoise.analysis.fit.fit_series`). The shape parameters of
the model (a Markov correlation time, a resonance's centre frequency and quality factor, a
line's frequency, a filter's cutoff or taps: every :attr:`Param.is_scale` parameter) belong to
the unit, so they are tested for homogeneity across runs: in the log of the parameter, where the
fit's 95 % intervals are roughly symmetric, each run's estimate is weighed by its own interval
(the half on the side of the pooled value, the intervals being asymmetric) and

    Q = sum_r ((ln p_r - ln p_pooled) / s_r)^2,   Q ~ chi2(R - 1) when the runs agree.

A shape whose Q passes the family-wise test (Bonferroni over every parameter tested) is held at
its pooled value and every run refitted with it held (the tied refit): the amplitudes (white
level, bias instability, random walk, sigma, line amplitude ...) stay per run, with their
intervals, and are tested the same way across runs (on each run's own fit, whose intervals
carry the shapes' uncertainty). A parameter that fails the test is *named*
with its per-run values and Q: a finding about the unit (the sensor changed between runs, or
the intervals are too narrow), not an error; a shape that differs stays free in each run's
refit.

Optionally each run is also diagnosed alone, the loop of ``imunoise diagnose`` applied to it as
to a file of its own (the top significant suggestion applied, a term or a cut of that run's
record, up to ``rounds`` times: :func:`loop_terms`), and the term set that most runs choose is
the one fitted to the unit.
"""

from __future__ import annotations

import collections
import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imunoise.analysis import distributions as dist
from imunoise.analysis.fit import FitResult, fit_series
from imunoise.analysis.jobs import JobMap, serial_map
from imunoise.analysis.terms import TermError, get_term, parse_model

Z95 = 1.959963984540054
"""Two-sided 95 % normal quantile: the fit's intervals are 95 % intervals."""

DEFAULT_ALPHA = 0.05
"""Family-wise probability that runs of one unharmed unit get any parameter named."""


@dataclass
class Run:
    """One recording of the unit: rate samples (SI units) and what the fit needs of them."""

    label: str
    values: np.ndarray
    fs_hz: float
    segment_starts: np.ndarray | None = None
    temperature: np.ndarray | None = None
    """Temperature (degC) at each sample, needed only by a model holding ``temperature``."""
    diagnose_kwargs: dict[str, Any] = field(default_factory=dict)
    """Extra arguments of :func:`imunoise.analysis.diagnosis.diagnose` (temperature record,
    t0_s, units, sensor_filter) for the per-run loop."""


@dataclass
class Estimate:
    """One parameter of one run: value and 95 % interval (SI units), and where it was
    measured: ``"allan"`` (the fit of the Allan curve) or ``"psd"`` (a resonance's peak in
    the run's spectrum). ``unresolved``: an amplitude whose interval reaches zero, an upper
    bound and no estimate (:meth:`imunoise.analysis.terms.base.Term.resolved`)."""

    value: float
    ci95: tuple[float, float]
    source: str = "allan"
    unresolved: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"value": _num(self.value), "ci95": [_num(self.ci95[0]), _num(self.ci95[1])],
                "source": self.source, "unresolved": self.unresolved}


@dataclass
class Homogeneity:
    """The test of one parameter across runs.

    Attributes:
        term, index, param: the parameter (``index`` is the term's place in the model).
        kind: ``"shape"`` or ``"amplitude"``.
        pooled: the weighted mean of the runs' estimates (geometric: weighed in log space).
        ci95: its 95 % interval, widened by ``sqrt(Q / dof)`` when that exceeds 1 (the spread
            between runs is then larger than each run's own interval says).
        q: the chi-square statistic; dof: runs tested minus one; p_value: ``P(chi2(dof) > q)``.
        runs: labels of the runs tested (runs whose interval is undefined or reaches zero are
            left out of the test).
        differs: the test rejects at the family-wise level.
    """

    term: str
    index: int
    param: str
    kind: str
    pooled: float
    ci95: tuple[float, float]
    q: float
    dof: int
    p_value: float
    runs: list[str]
    differs: bool = False

    def to_dict(self) -> dict[str, Any]:
        return {"term": self.term, "index": self.index, "param": self.param,
                "kind": self.kind, "value": _num(self.pooled),
                "ci95": [_num(self.ci95[0]), _num(self.ci95[1])], "q": _num(self.q),
                "dof": self.dof, "p_value": _num(self.p_value), "runs": list(self.runs),
                "differs": bool(self.differs)}


@dataclass
class ReplicateResult:
    """The unit's model across its runs.

    Attributes:
        runs: run labels, in input order.
        term_set: the model fitted to every run (term names in model order).
        per_run_terms: the term set each run alone chose by the diagnosis loop (empty when the
            loop was not run).
        common_terms: the most common of those and how many runs chose it.
        free_fits: each run's own fit of ``term_set``, its resonances' f0 and Q (where the
            user did not hold them) from its spectrum, with the spectrum's intervals.
        tied_fits: each run's refit with the shapes that agree held at their pooled values.
        shared: the homogeneity test of every shape parameter.
        amplitudes: the homogeneity test of every amplitude parameter (on the runs' own fits).
        per_run: per run, ``{"term#i.param": Estimate}`` of the tied refit.
        alpha: family-wise level of the tests.
    """

    runs: list[str]
    term_set: list[str]
    per_run_terms: list[list[str]]
    common_terms: tuple[list[str], int] | None
    free_fits: list[FitResult]
    tied_fits: list[FitResult]
    shared: list[Homogeneity]
    amplitudes: list[Homogeneity]
    per_run: list[dict[str, Estimate]]
    alpha: float
    order: list[list[int]] = field(default_factory=list)
    """Per run, the term index in that run's fits of each model position (repeated terms are
    matched across runs by their shape, not by the order the fit left them in)."""
    curve_fits: list[FitResult] = field(default_factory=list)
    """Each run's fit of the Allan curve alone, before its resonances' shapes are taken from
    its spectrum: the amplitudes are compared there."""
    curve_order: list[list[int]] = field(default_factory=list)
    """:attr:`order` of :attr:`curve_fits`."""
    spectral: list[dict[int, dict[str, float]]] = field(default_factory=list)
    """Per run, the resonance shapes taken from its spectrum, by term index of its fits."""
    error_parts: list[dict[str, Any]] = field(default_factory=list)
    """Per run, the error parts beside the Allan one of its own fit (:attr:`free_fits`):
    ``{"psd", "holdout", "time_domain"}`` as :func:`imunoise.analysis.model_error.error_parts`
    gives them (plain numbers)."""

    @property
    def differ(self) -> list[Homogeneity]:
        """The parameters that differ between runs beyond their intervals."""
        return [h for h in self.shared + self.amplitudes if h.differs]

    def per_run_values(self, h: Homogeneity) -> list[Estimate | None]:
        """Each run's own estimate of the tested parameter (what the test compared)."""
        if h.kind == "amplitude" and self.curve_fits:
            return [_estimate(f, o[h.index], h.param)
                    for f, o in zip(self.curve_fits, self.curve_order, strict=True)]
        out = []
        for r, (f, o) in enumerate(zip(self.free_fits, self.order, strict=True)):
            e = _estimate(f, o[h.index], h.param)
            if e is not None and self.spectral and h.param in self.spectral[r].get(o[h.index], {}):
                e.source = "psd"
            out.append(e)
        return out

    def tied_values(self, h: Homogeneity) -> list[Estimate | None]:
        """Each run's estimate in the refit with the agreeing shapes held."""
        return [_estimate(f, o[h.index], h.param) for f, o in zip(self.tied_fits, self.order,
                                                                   strict=True)]

    def to_dict(self) -> dict[str, Any]:
        """The ``replicates`` JSON block."""
        def differ_entry(h: Homogeneity) -> dict[str, Any]:
            d = h.to_dict()
            d["per_run"] = [None if e is None else e.to_dict() for e in self.per_run_values(h)]
            return d

        common = None
        if self.common_terms is not None:
            common = {"terms": list(self.common_terms[0]), "runs": self.common_terms[1]}
        return {
            "runs": [{"label": lab, "chi2_per_dof": _num(free.chi2_per_dof),
                      "chi2_per_dof_tied": _num(tied.chi2_per_dof),
                      "error": self.error_parts[i] if self.error_parts else None,
                      "loop_terms": list(self.per_run_terms[i]) if self.per_run_terms else None}
                     for i, (lab, free, tied) in enumerate(zip(self.runs, self.free_fits,
                                                               self.tied_fits, strict=True))],
            "term_set": list(self.term_set),
            "common_term_set": common,
            "shared": [h.to_dict() for h in self.shared],
            "per_run": [{k: e.to_dict() for k, e in run.items()} for run in self.per_run],
            "amplitudes": [h.to_dict() for h in self.amplitudes],
            "differ": [differ_entry(h) for h in self.differ],
            "alpha": self.alpha,
        }


def _num(v: float) -> float | None:
    return float(v) if v is not None and np.isfinite(v) else None


def _estimate(fit: FitResult, index: int, param: str) -> Estimate | None:
    t = fit.terms[index]
    if param not in t.params:
        return None
    ci = t.ci95.get(param, (math.nan, math.nan))
    interval = (float(ci[0]), float(ci[1]))
    return Estimate(float(t.params[param]), interval,
                    unresolved=not get_term(t.term).resolved(param, interval))


def _log_sd(e: Estimate, towards: float) -> float:
    """Standard deviation of ``ln value`` from the side of the 95 % interval facing
    ``towards`` (a log value); nan when that side is undefined or reaches zero."""
    lo, hi = e.ci95
    x = math.log(e.value)
    if towards >= x:
        return (math.log(hi) - x) / Z95 if hi > e.value else math.nan
    return (x - math.log(lo)) / Z95 if 0.0 < lo < e.value else math.nan


def homogeneity(estimates: list[Estimate | None], labels: list[str]
                ) -> tuple[float, tuple[float, float], float, int, float, list[str]]:
    """Test that the runs' estimates of one positive parameter agree.

    Returns ``(pooled, ci95, q, dof, p_value, runs_tested)``; ``q`` is the chi-square of the
    log estimates against their weighted mean, each weighed by its interval's half facing the
    mean (iterated: the side depends on the mean). Runs without a usable interval are left
    out; with fewer than two left the test has no degree of freedom (``q = 0``, ``p = 1``).
    """
    usable = [(lab, e) for lab, e in zip(labels, estimates, strict=True)
              if e is not None and e.value > 0 and np.isfinite(e.value)
              and e.ci95[0] > 0 and np.isfinite(e.ci95[1]) and e.ci95[1] > e.ci95[0]]
    if not usable:
        return math.nan, (math.nan, math.nan), 0.0, 0, 1.0, []
    x = np.array([math.log(e.value) for _, e in usable])
    sd = np.array([(math.log(e.ci95[1]) - math.log(e.ci95[0])) / (2 * Z95) for _, e in usable])
    sd = np.maximum(sd, 1e-12)
    mean = float(np.sum(x / sd**2) / np.sum(1 / sd**2))
    for _ in range(5):
        side = np.array([_log_sd(e, mean) for _, e in usable])
        side = np.where(np.isfinite(side) & (side > 0), side, sd)
        side = np.maximum(side, 1e-12)
        new = float(np.sum(x / side**2) / np.sum(1 / side**2))
        if abs(new - mean) < 1e-12:
            break
        mean = new
    sd = side
    w = 1.0 / sd**2
    q = float(np.sum(w * (x - mean) ** 2))
    dof = len(usable) - 1
    se = 1.0 / math.sqrt(float(np.sum(w)))
    if dof > 0:
        se *= math.sqrt(max(1.0, q / dof))  # Birge ratio: the spread between runs counts
    p = float(dist.chi2.sf(q, dof)) if dof > 0 else 1.0
    return (math.exp(mean), (math.exp(mean - Z95 * se), math.exp(mean + Z95 * se)), q, dof, p,
            [lab for lab, _ in usable])


def _order(fit: FitResult, names: list[str]) -> list[int]:
    """The run's term index of each model position: the instances of a repeated term (two
    resonances, two Markov terms) sorted by their first shape parameter, so that position k
    means the same physical term in every run whatever order the fit left them in."""
    order = list(range(len(names)))
    for name in set(names):
        at = [i for i, n in enumerate(names) if n == name]
        shape = next((p.name for p in get_term(name).params if p.is_scale), None)
        if len(at) < 2 or shape is None:
            continue
        ranked = sorted(at, key=lambda i: fit.terms[i].params.get(shape, math.inf))
        for pos, idx in zip(at, ranked, strict=True):
            order[pos] = idx
    return order


def _kinds(names: list[str]) -> list[tuple[int, str, str]]:
    """``(term index, parameter, "shape" | "amplitude")`` of every parameter of the model but
    a regressor's (a temperature coefficient is signed, and not a noise property)."""
    out = []
    for i, n in enumerate(names):
        term = get_term(n)
        if term.role == "regressor":
            continue
        for p in term.params:
            out.append((i, p.name, "shape" if p.is_scale else "amplitude"))
    return out


def _by_index(fixed: dict[str | int, dict[str, float]] | None, names: list[str]
              ) -> dict[int, dict[str, float]]:
    """``fixed`` (keyed by model index or first term name) keyed by model index."""
    out: dict[int, dict[str, float]] = {}
    for key, pars in (fixed or {}).items():
        out.setdefault(key if isinstance(key, int) else names.index(key), {}).update(pars)
    return out


def _held(fixed: dict[str | int, dict[str, float]] | None, names: list[str], index: int,
          param: str) -> bool:
    """Whether ``fixed`` (keyed by model index or first term name) holds this parameter."""
    for key, pars in (fixed or {}).items():
        idx = key if isinstance(key, int) else (names.index(key) if key in names else -1)
        if idx == index and param in pars:
            return True
    return False


def loop_terms(run: Run, model: str, rounds: int, alpha: float = DEFAULT_ALPHA) -> list[str]:
    """The term set one run alone reaches by the loop of ``imunoise diagnose`` on its file:
    each round the top significant suggestion is applied, up to ``rounds`` times; a term as
    the next round's model, a cut (a warm-up's ``--skip``, a bias step's ``--split``) as a cut
    of this run's record for the rounds that follow.

    Every round is the single-file diagnosis, the transient tests included: their cuts are
    among the candidates the family-wise level counts and a cut judged first is applied
    before any term, so without them a term can be significant here that the loop on the
    file holds back (ADIS16405 run 1 gyro_x: a 0.0015 Hz sinusoid at p 0.052 beside a
    bias-step cut, significant without the cut in the family). The cuts stay in the loop;
    the unit's fits use each record as given."""
    from imunoise.analysis.diagnosis import diagnose
    from imunoise.core.series import ChannelSeries

    kwargs = dict(run.diagnose_kwargs)
    t0 = float(kwargs.pop("t0_s", 0.0))
    units = str(kwargs.pop("units", "rad/s"))
    origin = float(kwargs.pop("time_origin_s", 0.0))
    series = ChannelSeries("x", units, run.fs_hz, np.asarray(run.values, dtype=np.float64),
                           np.zeros(1, dtype=np.int64) if run.segment_starts is None
                           else np.asarray(run.segment_starts, dtype=np.int64), t0)
    spec = model
    for _ in range(rounds):
        diag = diagnose(series.values, run.fs_hz, spec, segment_starts=series.segment_starts,
                        t0_s=series.t0_s, units=units, alpha=alpha, time_origin_s=origin,
                        **kwargs)
        top = next((s for s in diag.suggestions if s.significant), None)
        if top is None:
            break
        cut = _cut_of(top.apply.get("args") or [])
        if cut is None:
            spec = top.apply.get("model") or f"{spec},{top.term}"
            continue
        skip_s, split_s = cut
        try:
            series = series.windowed(skip_s, split_s)
        except ValueError:
            break  # a cut that leaves nothing: the loop on the file would stop there too
        origin += skip_s
    return parse_model(spec).names


def _cut_of(args: list[str]) -> tuple[float, list[float]] | None:
    """``(skip_s, split_s)`` of a suggestion's command-line arguments, or None where they
    hold no cut."""
    skip_s, split_s = 0.0, []
    for flag, value in zip(args[::2], args[1::2], strict=False):
        if flag == "--skip":
            skip_s = float(value)
        elif flag == "--split":
            split_s.append(float(value))
    return (skip_s, split_s) if skip_s > 0.0 or split_s else None


def _loop_job(shared: tuple[str, int, float], run: Run) -> list[str]:
    """:func:`loop_terms` of one run, as a job of a job map."""
    model, rounds, alpha = shared
    with _naming(run):
        return loop_terms(run, model, rounds, alpha)


@contextlib.contextmanager
def _naming(run: Run) -> Iterator[None]:
    """A record that one run's analysis cannot use (too short, no finite curve) raises its
    ValueError with the run's label first: among several runs, the message says which. A
    bad model (:class:`TermError`) is the same for every run and is left as it is."""
    try:
        yield
    except TermError:
        raise
    except ValueError as exc:
        raise ValueError(f"{run.label}: {exc}") from exc


def _at_spectrum_peaks(run: Run, free: FitResult, fixed: dict | None, names: list[str],
                       refit: Any) -> tuple[FitResult, dict[int, dict[str, float]]]:
    """Run ``run``'s fit with the centre frequency and quality factor of each resonance the
    user did not hold taken from the run's own spectrum, as the single-run diagnosis and the
    hold-out part take them (:func:`imunoise.analysis.spectral_pins.pin_resonances`): held
    there in the refit (``refit(held, start)``), with the spectrum's 95 % intervals as their
    intervals. The Allan curve leaves a resonance's f0 loose (ADIS16405 gyro_z: 18.3 Hz from
    the curve of a run whose spectrum peaks at 19.9 Hz). A peak is taken, one resonance at a
    time, only where holding it does not raise the Allan chi2/dof beyond its noise (the
    diagnosis's rule): a broad resonance standing in for a bend can find a narrow peak of
    its own in the spectrum that the curve refuses (run 3: a Q 0.5 hump pinned to a 1.9 Hz
    line took chi2/dof to 3e3). Peaks the spectrum does not resolve keep the curve's values.
    Returns the fit and the shapes held, by term index."""
    from imunoise.analysis.diagnosis.statistics import _rises
    from imunoise.analysis.spectral_pins import Pin, pin_resonances

    user = _by_index(fixed, names)
    held = {(i, p) for i, pars in user.items() for p in pars}
    try:
        pins = pin_resonances(run.values, run.fs_hz, free.params, held, run.segment_starts)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return free, {}
    best = free
    kept: list[Pin] = []
    for pin in pins:
        trial = kept + [pin]
        tie = {k: dict(v) for k, v in user.items()}
        start = best.params
        for q in trial:
            shape = {k: float(q.params[k]) for k in q.ci95}
            tie.setdefault(q.index, {}).update(shape)
            start[q.index][1].update(shape)
        try:
            pinned = refit(tie, start)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            continue
        if _rises(free.chi2_per_dof, pinned.chi2_per_dof, free.misfit.dof):
            continue
        best, kept = pinned, trial
    for pin in kept:
        best.terms[pin.index].ci95.update(
            {k: (float(lo), float(hi)) for k, (lo, hi) in pin.ci95.items()})
    return best, {q.index: {k: float(q.params[k]) for k in q.ci95} for q in kept}


def _common(sets: list[list[str]]) -> tuple[list[str], int]:
    """The most common term set (order-free; a tie goes to the smaller set, then the first)."""
    keys = [tuple(sorted(s)) for s in sets]
    counts = collections.Counter(keys)
    best = min(counts, key=lambda k: (-counts[k], len(k), keys.index(k)))
    first = sets[keys.index(best)]
    return list(first), counts[best]


def fit_replicates(runs: list[Run], model: str, *, fixed: dict | None = None,
                   alpha: float = DEFAULT_ALPHA, rounds: int = 0,
                   intervals: str = "profile", error_parts: bool = True,
                   job_map: JobMap = serial_map) -> ReplicateResult:
    """Fit one model to several runs of one unit with shared shapes and per-run amplitudes.

    Args:
        runs: the recordings (two or more).
        model: the model specification (``"white,random_walk,resonance"``).
        fixed: parameters held in every run (see :func:`imunoise.analysis.fit.fit_allan`).
        alpha: family-wise level of the homogeneity tests (Bonferroni over the parameters).
        rounds: when positive, each run is first diagnosed alone for up to ``rounds`` rounds
            and the most common resulting term set is fitted to the unit.
        intervals: interval method of the fits (``"profile"`` or ``"jacobian"``).
        error_parts: also each run's PSD, hold-out and time-domain parts of its own fit
            (:attr:`ReplicateResult.error_parts`; the hold-out part fits each half of the
            run again).
        job_map: how the runs' loops and their error parts run (one job per run;
            :mod:`imunoise.analysis.jobs`): one after the other by default. The result is
            the same.

    Raises:
        ValueError: fewer than two runs; and as :func:`imunoise.analysis.fit.fit_series`.
    """
    if len(runs) < 2:
        raise ValueError("replicates need at least two runs")
    labels = [r.label for r in runs]
    per_run_terms: list[list[str]] = []
    common = None
    spec = model
    if rounds > 0:
        per_run_terms = job_map(_loop_job, (model, rounds, alpha), runs)
        common = _common(per_run_terms)
        spec = ",".join(common[0]) if common[0] != parse_model(model).names else model
    names = parse_model(spec).names
    memos: list[dict] = [{} for _ in runs]

    def fit(i: int, held: dict | None, start: Any = None) -> FitResult:
        r = runs[i]
        with _naming(r):
            return fit_series(r.values, r.fs_hz, spec, segment_starts=r.segment_starts,
                              temperature=r.temperature, fixed=held, memo=memos[i],
                              intervals=intervals, start=start)[0]

    curve_fits = [fit(i, fixed) for i in range(len(runs))]
    at_peaks = [_at_spectrum_peaks(runs[i], curve_fits[i], fixed, names,
                                   lambda held, start, i=i: fit(i, held, start))
                for i in range(len(runs))]
    free_fits = [f for f, _ in at_peaks]
    parts = job_map(_parts_job, (runs, spec, fixed, free_fits), range(len(runs))) \
        if error_parts else []
    order = [_order(f, names) for f in free_fits]
    curve_order = [_order(f, names) for f in curve_fits]
    params = [(i, p, k) for i, p, k in _kinds(names) if not _held(fixed, names, i, p)]
    level = alpha / max(1, len(params))

    def test(i: int, p: str, kind: str) -> Homogeneity:
        fits, where = (free_fits, order) if kind == "shape" else (curve_fits, curve_order)
        pooled, ci, q, dof, pv, used = homogeneity(
            [_estimate(f, o[i], p) for f, o in zip(fits, where, strict=True)], labels)
        return Homogeneity(names[i], i, p, kind, pooled, ci, q, dof, pv, used,
                           differs=dof > 0 and pv < level)

    # shapes are compared where they are measured best: a resonance's at its spectrum's peak
    shared = [test(i, p, k) for i, p, k in params if k == "shape"]
    tie = _by_index(fixed, names)
    pooled = [h for h in shared if not h.differs and np.isfinite(h.pooled)]

    def tie_of(r: int) -> dict[int, dict[str, float]] | None:
        """Run ``r``'s held parameters: the user's, its own spectrum's resonance shapes, and
        the pooled shapes at its own indices."""
        out = {k: dict(v) for k, v in tie.items()}
        for idx, pars in at_peaks[r][1].items():
            out.setdefault(idx, {}).update(pars)
        for h in pooled:
            out.setdefault(order[r][h.index], {})[h.param] = h.pooled
        return out or None

    def tied(r: int) -> FitResult:
        """Run ``r`` refitted with the shapes held, from its own solution (a cold start can
        stop in a worse minimum than the one next to it)."""
        held = tie_of(r)
        start = free_fits[r].params
        for idx, pars in (held or {}).items():
            start[idx][1].update(pars)
        out = fit(r, held, start)
        for idx, pars in at_peaks[r][1].items():
            # a shape at the run's own spectrum peak keeps the spectrum's interval
            own = free_fits[r].terms[idx]
            out.terms[idx].ci95.update({k: own.ci95[k] for k in pars
                                        if out.terms[idx].params[k] == own.params[k]})
        return out

    tied_fits = [tied(r) for r in range(len(runs))] if pooled or tie else free_fits
    # amplitudes are compared on the runs' fits of the curve alone: their intervals there
    # carry the uncertainty of the shapes, which holding a shape (the spectrum's, or a
    # pooled one) would leave out (and a run whose shape estimate lies off the pooled one
    # moves its amplitude to compensate)
    amplitudes = [test(i, p, k) for i, p, k in params if k == "amplitude"]
    per_run = [_table(f, o, names) for f, o in zip(tied_fits, order, strict=True)]
    return ReplicateResult(labels, names, per_run_terms, common, free_fits, tied_fits, shared,
                           amplitudes, per_run, alpha, order, curve_fits, curve_order,
                           [shapes for _, shapes in at_peaks], parts)


def _parts_job(shared: tuple[list[Run], str, dict | None, list[FitResult]], i: int
               ) -> dict[str, Any]:
    """Run ``i``'s PSD, hold-out and time-domain parts of its own fit (a job of a job map:
    the runs and fits come with the shared context, not through a pipe)."""
    from imunoise.analysis.model_error import error_parts, plain

    runs, spec, fixed, fits = shared
    r = runs[i]
    _, parts = error_parts(r.values, r.fs_hz, spec, fits[i], r.segment_starts, fixed,
                           units=str(r.diagnose_kwargs.get("units", "rad/s")))
    return dict(plain(parts))


def _table(fit: FitResult, order: list[int], names: list[str]) -> dict[str, Estimate]:
    """``{"term#position.param": Estimate}`` of one run's fit, by model position."""
    row: dict[str, Estimate] = {}
    for i, name in enumerate(names):
        for p in fit.terms[order[i]].params:
            e = _estimate(fit, order[i], p)
            if e is not None:
                row[f"{name}#{i}.{p}"] = e
    return row


__all__ = ["Run", "Estimate", "Homogeneity", "ReplicateResult", "fit_replicates",
           "homogeneity", "loop_terms", "DEFAULT_ALPHA"]
