"""One channel's live analysis state: streaming Allan and PSD, the current model, its fits
and diagnosis. Pure data and computation: no threads, no processes, no clock.

The numbers are those of the batch tools on the same samples: the Allan curve is
:class:`imunoise.analysis.streaming_allan.StreamingAllan` on the octave grid of ``imunoise fit``
(exact up to ``m0``, strided beyond), the model is fitted by :func:`imunoise.analysis.fit.fit_allan`
and the diagnosis is :func:`imunoise.analysis.diagnosis.diagnose`.

The costly work comes in three steps so that the live runtime (:mod:`imunoise.live.channel`) can run
it wherever it likes, holding its locks only for the first and the last: ``plan_*`` takes
what a job needs from the state (a :class:`FitJob` or :class:`DiagnosisJob`, plain data and a
plain function, so that it can run in a worker process), the caller runs ``job.fn(*job.args)``,
and ``finish_*`` publishes the result unless the model changed meanwhile. Times (``now``,
``wall_s``) are given by the caller. Routine refits start from the previous result and use
linearised intervals; a full fit (cold start, profile-likelihood intervals: exactly what
``imunoise fit`` does) runs at a slower cadence, on request and at the end of a replay. A
model change refits at once.

Samples are fed by :meth:`ChannelState.update`; blocks are routed to channels by the live
runtime, so this module imports nothing from ``daq``.
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imunoise.analysis.allan import AllanCurve
from imunoise.analysis.default_model import DEFAULT_MODEL
from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.fit import FitResult, find_line, fit_allan
from imunoise.analysis.psd import StreamingPsd
from imunoise.analysis.streaming_allan import StreamingAllan
from imunoise.analysis.terms import get_term, labels, parse_model, term_name, term_names
from imunoise.core.series import channel_units
from imunoise.core.units import CI95

# ``temperature`` needs the whole temperature record regressed out of the rate series first,
# which a bounded-memory stream does not keep.
VALID_TERMS: tuple[str, ...] = term_names(live=True)
OCTAVE_GRID = (1 << np.arange(41)).astype(np.int64)  # the averaging factors of ``imunoise fit``
FULL_INTERVALS = "profile"
QUICK_INTERVALS = "jacobian"


@dataclass
class ErrorPoint:
    """One entry of the error history."""

    revision: int
    model: list[str]
    chi2_per_dof: float
    time_s: float
    n_samples: int
    psd_deviance_per_bin: float | None = None
    """The PSD part (Whittle deviance per bin of the streaming PSD under the fit), or None
    when none was computed for this entry (no PSD estimate yet)."""


def check_terms(terms: Iterable[str]) -> None:
    """Raise ``ValueError`` naming the valid terms when one is unknown or not live (the model
    grammar of :func:`imunoise.analysis.terms.parse_model`; ``TermError`` is a ``ValueError``)."""
    spec = parse_model(list(terms))
    for name in spec.names:
        if not get_term(name).live:
            needs = get_term(name).needs_record
            what = "the record's other channels" if needs == "channels" \
                else f"the whole {needs} record"
            raise ValueError(f"the {name} term needs {what} and is fitted by 'imunoise fit "
                             f"FILE --model ...,{name}'; valid live terms: "
                             f"{', '.join(VALID_TERMS)}")


def _lifted(params: Sequence[tuple[str, dict[str, float]]], curve: AllanCurve,
            floor: float = 1e-3, level: float = 1e-2) -> list[tuple[str, dict[str, float]]]:
    """A warm start in which no term is negligible.

    A term the previous data did not need sits at the bottom of its range, where the
    likelihood is flat in its log-parameter and a solver started there stays. A term whose
    Allan variance stays below ``floor`` of the measured one at every tau is raised to
    ``level`` of it where it is most prominent, so new data can claim it (the fit lowers it
    again if they do not)."""
    tau = np.asarray(curve.tau_s, dtype=np.float64)
    measured = np.asarray(curve.dev, dtype=np.float64) ** 2
    ok = measured > 0
    out: list[tuple[str, dict[str, float]]] = []
    for name, p in params:
        p = dict(p)
        term = get_term(name)
        amp = term.amplitude if term.role != "regressor" else None
        if amp is not None and ok.any():
            ratio = float(np.max(get_term(name).avar(tau[ok], curve.fs_hz, **p) / measured[ok]))
            if ratio < floor:
                p[amp] *= math.sqrt(level / max(ratio, 1e-300))
        out.append((name, p))
    return out


def _ordered(terms: Iterable[str]) -> list[str]:
    """The model's entries (``name`` or ``name:P=V``, the grammar of
    :func:`imunoise.analysis.terms.parse_model`) in vocabulary order, repeated terms kept in
    order."""
    entries = parse_model(list(terms)).entries
    rank = {n: k for k, n in enumerate(VALID_TERMS)}
    return [e.text() for e in sorted(entries, key=lambda e: rank.get(e.name, len(rank)))]


def _names(model: Iterable[str]) -> list[str]:
    """Term names of a live model's entries."""
    return parse_model(list(model)).names


# --- jobs: plain functions of plain data, so they can run in a worker process ----------------

def _job_fit(curve: AllanCurve, model: list[str], start: Any, line_samples: np.ndarray | None,
             intervals: str) -> FitResult:
    """``fit_allan`` cold (``start`` None, a sinusoid starting from the strongest line of
    ``line_samples``) or warm; repeated terms in shape order, as ``imunoise fit`` lists
    them (:meth:`FitResult.in_canonical_order`)."""
    line = find_line(line_samples, curve.fs_hz) if line_samples is not None else None
    fit = (fit_allan(curve, model, line=line, intervals=intervals) if start is None
           else fit_allan(curve, model, start=start, intervals=intervals))
    return fit.in_canonical_order()


def _job_fit_new_model(curve: AllanCurve, model: list[str], start: Any,
                       hints: dict[str, dict[str, float]],
                       line_samples: np.ndarray | None) -> FitResult:
    """A changed model: the cold start of ``imunoise fit`` and a warm start from the previous
    model's parameters (``start``; a new term from ``hints`` or the spectral line); the one
    with the smaller misfit wins (a nested model must not fit worse); repeated terms in shape
    order."""
    line = find_line(line_samples, curve.fs_hz) if line_samples is not None else None
    best = fit_allan(curve, model, line=line, intervals=QUICK_INTERVALS).in_canonical_order()
    if start is None:
        return best
    start = list(start)
    have = {t for t, _ in start}
    for term in _names(model):
        if term in have:
            continue
        if term in hints:
            start.append((term, hints[term]))
        elif term == "sinusoid" and line is not None and line[1] > 0:
            start.append((term, {"A": line[1], "f": line[0]}))
    try:
        warm = fit_allan(curve, model, start=start, line=line, intervals=QUICK_INTERVALS)
    except (ValueError, np.linalg.LinAlgError):
        return best
    return warm.in_canonical_order() if warm.misfit.chi2 < best.misfit.chi2 else best


def _job_diagnose(values: np.ndarray, fs_hz: float, model: list[str], starts: np.ndarray,
                  units: str) -> tuple[list[dict], list[dict]]:
    """``imunoise.analysis.diagnosis.diagnose``: suggestions and the significant findings that are
    not
    a term (outliers, gaps, a changing noise level), as JSON-ready dicts."""
    # the live service cannot cut its stream: no warm-up or step remedies; nor does it pay
    # for the hold-out part's fits on the halves of every recent window
    result = diagnose(values, fs_hz, model, segment_starts=starts, units=units,
                      transients=False, holdout=False)
    findings = [f.to_dict() for f in result.findings if f.significant and f.term is None]
    return ([s.to_dict() for s in result.suggestions],
            [{k: f[k] for k in ("kind", "p_value", "why", "range")} for f in findings])


class RecentSamples:
    """The most recent ``capacity`` samples with their gap-free segment starts (bounded)."""

    def __init__(self, capacity: int) -> None:
        self.capacity = int(capacity)
        self._chunks: deque[tuple[bool, np.ndarray]] = deque()  # (starts a segment, values)
        self._n = 0

    def append(self, values: np.ndarray, new_segment: bool) -> None:
        if values.size == 0:
            return
        if values.size >= self.capacity:
            self._chunks.clear()
            self._n = 0
            values = values[-self.capacity:]
            new_segment = True  # its beginning is not the segment's, but nothing precedes it
        self._chunks.append((new_segment or not self._chunks, values.copy()))
        self._n += values.size
        while self._n > self.capacity:
            starts, first = self._chunks[0]
            excess = self._n - self.capacity
            if first.size <= excess:
                self._chunks.popleft()
                self._n -= first.size
                if self._chunks:
                    self._chunks[0] = (True, self._chunks[0][1])
            else:
                self._chunks[0] = (True, first[excess:])
                self._n -= excess

    def series(self) -> tuple[np.ndarray, np.ndarray]:
        """``(values, segment_starts)`` of the window."""
        if not self._chunks:
            return np.zeros(0), np.zeros(1, dtype=np.int64)
        values = np.concatenate([c for _, c in self._chunks])
        sizes = np.array([c.size for _, c in self._chunks])
        offsets = np.concatenate(([0], np.cumsum(sizes)[:-1]))
        starts = offsets[[s for s, _ in self._chunks]]
        return values, np.asarray(starts, dtype=np.int64)

    def longest_segment(self) -> np.ndarray:
        values, starts = self.series()
        bounds = np.append(starts, values.size)
        k = int(np.argmax(np.diff(bounds)))
        return values[bounds[k]:bounds[k + 1]]

    def __len__(self) -> int:
        return self._n


@dataclass
class FitJob:
    """A fit to run: ``fn(*args)`` returns the :class:`FitResult` (``fn`` is None when
    ``cached`` already is the result: the same model was fitted to the same samples)."""

    kind: str  # "fit" (warm, linearised), "full" (cold, profile) or "model" (a changed model)
    model: list[str]
    revision: int  # the model revision it was planned for
    n: int  # samples behind ``curve``
    curve: AllanCurve
    intervals: str
    fn: Callable[..., FitResult] | None = None
    args: tuple = ()
    cached: FitResult | None = None


@dataclass
class ModelChange:
    """A model change: the new model, the fit it was made from and the refit to run (None
    when the model is unchanged or the data cannot fit it yet)."""

    model: list[str]
    before: FitResult | None
    job: FitJob | None
    unchanged: bool = False


@dataclass(frozen=True)
class ModelChangeResult:
    """What a model change did: the model, its revision and the fits before and after."""

    channel: str
    model: list[str]
    model_revision: int
    before: FitResult | None
    after: FitResult | None


@dataclass
class DiagnosisJob:
    """A diagnosis to run: ``fn(*args)`` returns ``(suggestions, findings)``."""

    revision: int
    n: int  # samples fed when it was planned
    covered: int  # samples it looks at (the recent window)
    fn: Callable[..., tuple[list[dict], list[dict]]]
    args: tuple = ()


@dataclass(frozen=True)
class ChannelSnapshot:
    """Everything the views of one channel show, taken at one instant (the fit and the curve
    it was fitted to belong together)."""

    channel: str
    units: str
    fs_hz: float
    n_samples: int
    n_segments: int
    model: tuple[str, ...]
    model_revision: int
    fit: FitResult | None
    fit_curve: AllanCurve | None
    fit_intervals: str
    fit_n: int
    fit_wall_s: float | None
    suggestions: tuple[dict, ...]
    findings: tuple[dict, ...]
    diagnosis_note: str
    diagnosis_revision: int
    history: tuple[ErrorPoint, ...] = field(default_factory=tuple)
    targets: str | None = None


class ChannelState:
    """Live analysis state of one channel.

    Args:
        channel: channel name (``gyro_x`` ...).
        fs_hz: sampling rate in Hz.
        units: SI units of the values (derived from the name when omitted).
        model: initial model (term names).
        refit_interval_s: least time between two routine refits (warm start, linearised
            intervals) of this channel; the scheduler's CPU budget may space them further.
        full_refit_interval_s: least time between two full fits (cold start, profile
            intervals, as ``imunoise fit``).
        diagnosis_interval_s: least time between two diagnoses.
        history_interval_s: least time between two error-history entries of one model
            revision (a model change always adds one).
        history_len: error history entries kept (bounded memory; 2000 entries at 10 s cover
            5.5 h, older ones are dropped).
        nperseg: PSD segment length in samples at every level of the decimation cascade.
        recent_samples: samples kept for the diagnosis's evidence and a sinusoid's starting
            line (bounded; 2^18 samples is 44 min at 100 Hz, 2 MB).
        m0: largest averaging factor of the Allan curve computed on every start index.
        targets: wanted 95 % half-widths (``K=20%,B=10%``, see :mod:`imunoise.analysis.planning`);
            the coefficients then say how much longer to record for each.
    """

    def __init__(self, channel: str, fs_hz: float, units: str | None = None,
                 model: Sequence[str] = DEFAULT_MODEL, refit_interval_s: float = 2.0,
                 full_refit_interval_s: float = 60.0, diagnosis_interval_s: float = 60.0,
                 history_interval_s: float = 10.0, history_len: int = 2000,
                 nperseg: int = 256, recent_samples: int = 1 << 18, m0: int = 4096,
                 targets: str | None = None) -> None:
        check_terms(model)
        self.targets = targets
        self.channel = channel
        self.fs_hz = float(fs_hz)
        self.units = units if units is not None else channel_units(channel)
        self.refit_interval_s = refit_interval_s
        self.full_refit_interval_s = full_refit_interval_s
        self.diagnosis_interval_s = diagnosis_interval_s
        self.history_interval_s = history_interval_s
        self._allan = StreamingAllan(self.fs_hz, kinds=("oadev",), m0=m0, m_grid=OCTAVE_GRID)
        self._psd = StreamingPsd(self.fs_hz, nperseg=nperseg)
        self._recent = RecentSamples(recent_samples)
        self._model = _ordered(model)
        self._model_revision = 0
        self.n_samples = 0
        self.n_segments = 0
        self._seg_len = 0
        self._closed_segments: dict[int, int] = {}  # length in samples -> how many
        self._gap_pending = False
        self._fit: FitResult | None = None
        self._fit_intervals = ""
        self._fit_n = -1  # samples behind the published fit
        self._fit_wall: float | None = None
        self._curve: AllanCurve | None = None
        self._cache: OrderedDict[tuple[tuple[str, ...], int, str], FitResult] = OrderedDict()
        self._suggestions: list[dict] = []
        self._findings: list[dict] = []
        self._diag_note = ""
        self._diag_revision = -1
        self._diag_n = -1
        self._full_n = -1
        self._last_fit_t = -math.inf
        self._last_full_t = -math.inf
        self._last_diag_t = -math.inf
        self._history: deque[ErrorPoint] = deque(maxlen=history_len)
        self.revision = 0  # bumps whenever published results change

    # --- feeding (cheap, vectorised) -------------------------------------------------------
    def update(self, values: np.ndarray, new_segment: bool = False) -> None:
        """Add samples (SI units). ``new_segment``: they do not follow the previous ones.
        Non-finite samples are a gap: the finite runs around them are separate segments."""
        v = np.asarray(values, dtype=np.float64).ravel()
        finite = np.isfinite(v)
        if finite.all():
            runs = [v]
            leading_gap = trailing_gap = False
        else:
            edges = np.flatnonzero(np.diff(np.concatenate(([0], finite.view(np.int8), [0]))))
            runs = [v[a:b] for a, b in zip(edges[0::2], edges[1::2], strict=True)]
            leading_gap, trailing_gap = not finite[0], not finite[-1]
        self._gap_pending |= new_segment or leading_gap
        for k, run in enumerate(runs):
            starts = self._gap_pending or k > 0 or self.n_segments == 0
            if starts:
                self._close_segment()
                self._allan.new_segment()
                self._psd.new_segment()
                self.n_segments += 1
                self._gap_pending = False
            self._allan.update(run)
            self._psd.update(run)
            self._recent.append(run, starts)
            self.n_samples += int(run.size)
            self._seg_len += int(run.size)
        self._gap_pending |= trailing_gap

    def _close_segment(self) -> None:
        if self._seg_len:
            self._closed_segments[self._seg_len] = self._closed_segments.get(self._seg_len, 0) + 1
        self._seg_len = 0

    def _full_counts(self, m: np.ndarray) -> np.ndarray:
        """Differences of the full overlapping estimate at each m, pooled over segments
        (``n + 1 - 2m`` per segment of ``n`` samples)."""
        lengths = dict(self._closed_segments)
        if self._seg_len:
            lengths[self._seg_len] = lengths.get(self._seg_len, 0) + 1
        total = np.zeros(m.size, dtype=np.int64)
        for n, count in lengths.items():
            total += count * np.maximum(n + 1 - 2 * m, 0)
        return total

    def curve(self) -> AllanCurve:
        """The overlapping Allan curve of everything fed so far (octave taus, 95 % band).

        Beyond ``m0`` the streaming estimate averages every d-th difference; ``n_terms``
        reports the count of the full estimate it stands for, which is what the fit's
        covariance needs (the deviation equals the full one to a small fraction of its
        interval)."""
        c = self._allan.curve("oadev", ci=CI95)
        return dataclasses.replace(c, n_terms=self._full_counts(np.asarray(c.m)))

    def psd_estimate(self) -> Any:
        """The streaming PSD estimate (:class:`imunoise.analysis.psd.PsdEstimate`), or None before
        one full segment."""
        try:
            return self._psd.estimate()
        except ValueError:
            return None

    # --- model ---------------------------------------------------------------------------
    @property
    def model(self) -> list[str]:
        return list(self._model)

    @property
    def model_revision(self) -> int:
        return self._model_revision

    @property
    def fitted(self) -> bool:
        """Whether a fit has been published."""
        return self._fit is not None

    def with_term(self, term: str) -> list[str]:
        """The model with ``term`` added (``ValueError`` when unknown or already there)."""
        check_terms([term])
        name = parse_model([term]).names[0]
        if name in _names(self._model) and not get_term(name).repeatable:
            raise ValueError(f"term {term!r} is already in the model")
        return self._model + [term]

    def without_term(self, term: str) -> list[str]:
        """The model with ``term`` removed: an entry as written, every entry of that name, or
        one occurrence by its label (``resonance#2``, as the ``/coefficients`` rows name it)."""
        check_terms([term_name(term)])
        model = self._model
        names = _names(model)
        marks = labels(names)
        if term not in model and term not in names and term not in marks:
            raise ValueError(f"term {term!r} is not in the model; model: {', '.join(model)}")
        return [t for t, n, k in zip(model, names, marks, strict=True)
                if t != term and n != term and k != term]

    def plan_model_change(self, terms: Sequence[str]) -> ModelChange:
        """The refit a change to ``terms`` needs. Raises ``ValueError`` for an unknown term or
        an empty model."""
        if not terms:
            raise ValueError("the model needs at least one term")
        check_terms(terms)
        new = _ordered(terms)
        if new == self._model:
            return ModelChange(new, self._fit, None, unchanged=True)
        curve, n = self.curve(), self.n_samples
        if not self._enough(curve, new):
            return ModelChange(new, self._fit, None)
        job = FitJob("model", new, self._model_revision, n, curve, QUICK_INTERVALS)
        hit = self._cached(new, QUICK_INTERVALS, n)
        if hit is not None:
            job.cached, job.intervals = hit
            return ModelChange(new, self._fit, job)
        start = None
        hints: dict[str, dict[str, float]] = {}
        previous = self._fit
        if previous is not None:
            names = _names(new)
            start = [(t, p) for t, p in previous.params if t in names]
            hints = {t: h for t in names if (h := self._hint(t)) is not None}
        job.fn = _job_fit_new_model
        job.args = (curve, new, start, hints, self._line_samples(new))
        return ModelChange(new, self._fit, job)

    def finish_model_change(self, change: ModelChange, fit: FitResult | None,
                            wall_s: float, psd_part: float | None = None
                            ) -> ModelChangeResult:
        """Make ``change`` the model, publishing ``fit`` (its job's result) when there is one.
        ``wall_s``: the wall-clock time (Unix seconds) of the history entry; ``psd_part``:
        the fit's PSD part."""
        if not change.unchanged:
            job = change.job
            if fit is not None and job is not None:
                self._remember(fit, change.model, job.n, job.intervals)
            self._model = change.model
            self._model_revision += 1
            if fit is not None and job is not None:
                self._publish(fit, job.curve, job.intervals, job.n, wall_s, psd_part)
            self.revision += 1
        return ModelChangeResult(self.channel, list(self._model), self._model_revision,
                                 change.before, self._fit)

    # --- fits ----------------------------------------------------------------------------
    def _enough(self, curve: AllanCurve, model: Sequence[str]) -> bool:
        spec = parse_model(list(model))
        n_free = sum(len(get_term(e.name).params) - len(e.fixed) for e in spec.entries)
        return int(np.count_nonzero(curve.dev > 0)) > n_free

    def _line_samples(self, model: Sequence[str]) -> np.ndarray | None:
        """The longest recent gap-free stretch, where a sinusoid's line is looked for."""
        if not any(get_term(n).role == "line" for n in _names(model)):
            return None
        return self._recent.longest_segment()

    def _cached(self, model: Sequence[str], intervals: str, n: int
                ) -> tuple[FitResult, str] | None:
        """A fit of ``model`` on exactly the current data (same samples), if one was made,
        with its kind of intervals (a profile fit serves a request for linearised ones)."""
        for kind in (FULL_INTERVALS, intervals):
            hit = self._cache.get((tuple(model), n, kind))
            if hit is not None:
                return hit, kind
        return None

    def _remember(self, fit: FitResult, model: Sequence[str], n: int, intervals: str) -> None:
        self._cache[(tuple(model), n, intervals)] = fit
        while len(self._cache) > 16:
            self._cache.popitem(last=False)

    def _hint(self, term: str) -> dict[str, float] | None:
        """The diagnosis's parameters for ``term``, the start of a warm refit that adds it."""
        for s in self._suggestions:
            if s.get("term") == term and s.get("params") and all(
                    v is not None and math.isfinite(v) and v > 0
                    for v in s["params"].values()):
                return dict(s["params"])
        return None

    def plan_refit(self, full: bool, now: float) -> FitJob | None:
        """The refit of the current model to the current curve (None: too few taus yet).

        Routine refits start from the previous result with linearised intervals; ``full``
        fits start cold with profile-likelihood intervals, as ``imunoise fit`` does. ``now``
        (monotonic seconds) is when it was planned, for :meth:`due`."""
        model = list(self._model)
        previous = self._fit if self._fit is not None and \
            [t.term for t in self._fit.terms] == _names(model) else None
        n = self.n_samples
        intervals = FULL_INTERVALS if full else QUICK_INTERVALS
        hit = self._cached(model, intervals, n)
        self._last_fit_t = now
        if full:
            self._last_full_t = now
        kind = "full" if full else "fit"
        if hit is not None:
            curve = self._curve if self._fit_n == n and self._curve is not None else self.curve()
            return FitJob(kind, model, self._model_revision, n, curve, hit[1], cached=hit[0])
        curve = self.curve()
        if not self._enough(curve, model):
            return None
        cold = full or previous is None
        args = (curve, model, None if cold else _lifted(previous.params, curve),
                self._line_samples(model) if cold else None, intervals)
        return FitJob(kind, model, self._model_revision, n, curve, intervals,
                      fn=_job_fit, args=args)

    def finish_refit(self, job: FitJob, fit: FitResult, wall_s: float,
                     psd_part: float | None = None) -> bool:
        """Publish ``fit`` (``job``'s result) unless the model changed meanwhile (that change
        published its own fit). ``psd_part``: its PSD part, when :meth:`history_entry_due`
        asked for one. Returns whether it was published."""
        if job.revision != self._model_revision:
            return False
        self._remember(fit, job.model, job.n, job.intervals)
        if job.kind == "full":
            self._full_n = job.n
        self._publish(fit, job.curve, job.intervals, job.n, wall_s, psd_part)
        return True

    def history_entry_due(self, wall_s: float, model_changes: bool = False) -> bool:
        """Whether a fit published at ``wall_s`` opens a new error-history entry (rather than
        replacing the latest of its interval): only then is its PSD part worth computing, so
        that costs at most one PSD expectation per history interval and model."""
        last = self._history[-1] if self._history else None
        return (model_changes or last is None or last.revision != self._model_revision
                or wall_s - last.time_s >= self.history_interval_s)

    def _publish(self, fit: FitResult, curve: AllanCurve, intervals: str, n: int,
                 wall_s: float, psd_part: float | None = None) -> None:
        """Make ``fit`` the current result and enter it in the error history. An entry that
        replaces the latest of its interval keeps that entry's PSD part (computed once per
        interval) unless given one."""
        self._fit, self._curve, self._fit_intervals = fit, curve, intervals
        self._fit_n = n
        self._fit_wall = wall_s
        model = [t.term for t in fit.terms]
        last = self._history[-1] if self._history else None
        if psd_part is None and last is not None and last.revision == self._model_revision:
            psd_part = last.psd_deviance_per_bin
        point = ErrorPoint(self._model_revision, model, float(fit.chi2_per_dof), wall_s, n,
                           psd_part)
        if last is None or last.revision != self._model_revision or \
                wall_s - last.time_s >= self.history_interval_s:
            self._history.append(point)
        elif len(self._history) >= 2 and self._history[-2].revision == last.revision:
            self._history[-1] = point  # within one interval: the latest fit stands for it
        else:
            self._history.append(point)  # the first entry of a revision stays as it was
        self.revision += 1

    # --- diagnosis -----------------------------------------------------------------------
    def plan_diagnosis(self, now: float) -> DiagnosisJob:
        """:func:`imunoise.analysis.diagnosis.diagnose` of the recent samples under the current
        model.
        ``now``: monotonic seconds, for :meth:`due`."""
        self._last_diag_t = now
        values, starts = self._recent.series()
        return DiagnosisJob(self._model_revision, self.n_samples, values.size, _job_diagnose,
                            (values, self.fs_hz, list(self._model), starts, self.units))

    def finish_diagnosis(self, job: DiagnosisJob,
                         result: tuple[list[dict], list[dict]]) -> bool:
        """Publish a diagnosis unless the model changed meanwhile."""
        if job.revision != self._model_revision:
            return False
        self._suggestions, self._findings = result
        self._diag_revision = job.revision
        self._diag_n = job.n
        self._diag_note = "" if job.covered >= job.n else \
            f"based on the most recent {job.covered / self.fs_hz:.0f} s of the record"
        self.revision += 1
        return True

    def fail_diagnosis(self, job: DiagnosisJob, reason: str) -> None:
        """A diagnosis that could not run (too few samples ...): publish why."""
        if job.revision != self._model_revision:
            return
        self._suggestions, self._findings = [], []
        self._diag_note = f"waiting for data: {reason}"
        self._diag_revision, self._diag_n = job.revision, job.n
        self.revision += 1

    # --- scheduling ----------------------------------------------------------------------
    def due(self, now: float) -> tuple[float, str] | None:
        """The most overdue job of this channel: ``(since when it is due, kind)``, or None.

        Kinds: ``"full"`` (cold start, profile intervals), ``"fit"`` (warm, linearised),
        ``"diagnose"``. ``now``: monotonic seconds, the clock of the ``plan_*`` calls."""
        n, fitted = self.n_samples, self._fit_n
        jobs: list[tuple[float, str]] = []
        if n > fitted and n > 0:
            jobs.append((self._last_fit_t + self.refit_interval_s, "fit"))
            if n > self._full_n:
                jobs.append((self._last_full_t + self.full_refit_interval_s, "full"))
        if self._fit is not None and \
                (self._diag_revision != self._model_revision or n > self._diag_n):
            wait = 0.0 if self._diag_revision != self._model_revision else \
                self.diagnosis_interval_s
            jobs.append((self._last_diag_t + wait, "diagnose"))
        ready = [j for j in jobs if j[0] <= now]
        if not ready:
            return None
        # a full fit supersedes a routine one that is due at the same time
        kinds = {k for _, k in ready}
        if "full" in kinds and "fit" in kinds:
            ready = [j for j in ready if j[1] != "fit"]
        return min(ready)

    # --- what the views show -------------------------------------------------------------
    def snapshot(self) -> ChannelSnapshot:
        """The published results and the feeding counts, as one consistent record."""
        return ChannelSnapshot(
            channel=self.channel, units=self.units, fs_hz=self.fs_hz,
            n_samples=self.n_samples, n_segments=self.n_segments, model=tuple(self._model),
            model_revision=self._model_revision, fit=self._fit, fit_curve=self._curve,
            fit_intervals=self._fit_intervals, fit_n=self._fit_n, fit_wall_s=self._fit_wall,
            suggestions=tuple(self._suggestions), findings=tuple(self._findings),
            diagnosis_note=self._diag_note, diagnosis_revision=self._diag_revision,
            history=tuple(self._history), targets=self.targets)
