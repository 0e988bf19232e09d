"""Rolling analysis of live data: streaming Allan and PSD, the current model, refits, diagnosis.

The numbers are those of the batch tools on the same samples: the Allan curve is
:class:`analysis.streaming_allan.StreamingAllan` on the octave grid of ``imunoise fit``
(exact up to ``m0``, strided beyond), the model is fitted by :func:`analysis.fit.fit_allan`
and the diagnosis is :func:`analysis.diagnosis.diagnose`.

:class:`ChannelAnalyzer` is one channel's state: it takes the channel's samples, and its
fits and diagnoses run when the scheduler of the live runtime
(:class:`live.scheduler.RollingAnalyzer`, which keeps one per channel) asks, through the
runner it was given (in the calling thread by default). Routine refits start from the
previous result and use
linearised intervals; a full fit (cold start, profile-likelihood intervals: exactly what
``imunoise fit`` does) runs at a slower cadence, on request and at the end of a replay.
A model change refits at once.

Blocks are taken structurally (anything with ``stream``, ``channels``, ``fs_hz`` and
``gap_before`` attributes, e.g. ``core.blocks.SampleBlock``), so this module imports nothing from
``daq``.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from analysis.allan import AllanCurve
from analysis.diagnosis import diagnose
from analysis.fit import FitResult, find_line, fit_allan
from analysis.psd import StreamingPsd
from analysis.streaming_allan import StreamingAllan
from analysis.terms import TermError, get_term, parse_model, term_names
from analysis.terms import model_psd as _terms_psd
from core.series import channel_units
from core.units import CI95
from core.units import param_units as _param_units

DEFAULT_MODEL: tuple[str, ...] = ("white", "bias_instability", "random_walk")
# ``temperature`` needs the whole temperature record regressed out of the rate series first,
# which a bounded-memory stream does not keep.
VALID_TERMS: tuple[str, ...] = term_names(live=True)
OCTAVE_GRID = (1 << np.arange(41)).astype(np.int64)  # the averaging factors of ``imunoise fit``
FULL_INTERVALS = "profile"
QUICK_INTERVALS = "jacobian"


class BlockLike(Protocol):
    """What :meth:`RollingAnalyzer.update` needs from a block of samples."""

    stream: str
    channels: dict[str, np.ndarray]
    fs_hz: float
    gap_before: int


def model_psd(f_hz: np.ndarray, params: Sequence[tuple[str, dict[str, float]]],
              fs_hz: float) -> np.ndarray:
    """One-sided model PSD ((channel units)^2/Hz) of fitted terms ``[(term, params)]``.

    Sinusoids are spectral lines and add nothing to the continuous spectrum drawn here.
    """
    f = np.asarray(f_hz, dtype=np.float64)
    return _terms_psd(params, f, fs_hz, continuous_only=True).reshape(f.shape)


@dataclass
class ErrorPoint:
    """One entry of the error history."""

    revision: int
    model: list[str]
    chi2_per_dof: float
    time_s: float
    n_samples: int


@dataclass
class JobStats:
    """CPU and wall time of the analysis jobs of one channel (seconds)."""

    fits: int = 0
    full_fits: int = 0
    diagnoses: int = 0
    last_fit_cpu_s: float = 0.0
    last_full_cpu_s: float = 0.0
    last_diagnosis_cpu_s: float = 0.0
    last_fit_wall_s: float = 0.0


def _error(fit: FitResult | None) -> dict[str, float | None]:
    if fit is None:
        return {"chi2_per_dof": None, "max_abs_z": None}
    return {"chi2_per_dof": _num(fit.chi2_per_dof), "max_abs_z": _num(fit.max_abs_z)}


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _finite(x: Iterable[float]) -> list[float | None]:
    """A JSON-safe list: non-finite numbers become ``None``."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(list(x), dtype=float)]


def check_terms(terms: Iterable[str]) -> None:
    """Raise ``ValueError`` naming the valid terms when one is unknown or not live (the model
    grammar of :func:`analysis.terms.parse_model`; ``TermError`` is a ``ValueError``)."""
    spec = parse_model(list(terms))
    for name in spec.names:
        if not get_term(name).live:
            raise ValueError(f"the {name} term needs the whole {get_term(name).needs_record} "
                             f"record and is fitted by 'imunoise fit FILE --model "
                             f"...,{name}'; valid live terms: {', '.join(VALID_TERMS)}")


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
    :func:`analysis.terms.parse_model`) in vocabulary order, repeated terms kept in order."""
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
    ``line_samples``) or warm."""
    line = find_line(line_samples, curve.fs_hz) if line_samples is not None else None
    if start is None:
        return fit_allan(curve, model, line=line, intervals=intervals)
    return fit_allan(curve, model, start=start, intervals=intervals)


def _job_fit_new_model(curve: AllanCurve, model: list[str], start: Any,
                       hints: dict[str, dict[str, float]],
                       line_samples: np.ndarray | None) -> FitResult:
    """A changed model: the cold start of ``imunoise fit`` and a warm start from the previous
    model's parameters (``start``; a new term from ``hints`` or the spectral line); the one
    with the smaller misfit wins (a nested model must not fit worse)."""
    line = find_line(line_samples, curve.fs_hz) if line_samples is not None else None
    best = fit_allan(curve, model, line=line, intervals=QUICK_INTERVALS)
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
    return warm if warm.misfit.chi2 < best.misfit.chi2 else best


def _job_diagnose(values: np.ndarray, fs_hz: float, model: list[str], starts: np.ndarray,
                  units: str) -> tuple[list[dict], list[dict]]:
    """``analysis.diagnosis.diagnose``: suggestions and the significant findings that are not
    a term (outliers, gaps, a changing noise level), as JSON-ready dicts."""
    # the live service cannot cut its stream: no warm-up or step remedies
    result = diagnose(values, fs_hz, model, segment_starts=starts, units=units,
                      transients=False)
    findings = [f.to_dict() for f in result.findings if f.significant and f.term is None]
    return ([s.to_dict() for s in result.suggestions],
            [{k: f[k] for k in ("kind", "p_value", "why", "range")} for f in findings])


def _timed(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``fn(*args)`` and the CPU seconds of the thread that ran it."""
    t0 = time.thread_time()
    out = fn(*args)
    return out, time.thread_time() - t0


class Runner(Protocol):
    """Runs a job function, returns ``(result, CPU seconds)``."""

    def __call__(self, fn: Callable[..., Any], *args: Any) -> tuple[Any, float]: ...


def run_inline(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """Run a job in the calling thread."""
    return _timed(fn, *args)


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


class ChannelAnalyzer:
    """Live analysis of one channel.

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
        runner: runs the fits and the diagnosis (:func:`run_inline`, or a
            :class:`WorkerProcess` to keep them off the interpreter lock).
    """

    def __init__(self, channel: str, fs_hz: float, units: str | None = None,
                 model: Sequence[str] = DEFAULT_MODEL, refit_interval_s: float = 2.0,
                 full_refit_interval_s: float = 60.0, diagnosis_interval_s: float = 60.0,
                 history_interval_s: float = 10.0, history_len: int = 2000,
                 nperseg: int = 256, recent_samples: int = 1 << 18, m0: int = 4096,
                 runner: Runner = run_inline, targets: str | None = None) -> None:
        check_terms(model)
        self.targets = targets
        """Wanted 95 % half-widths (``K=20%,B=10%``, see :mod:`analysis.planning`): the
        coefficients then say how much longer to record for each."""
        self._plan_cache: tuple[int, dict] | None = None
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
        self._lock = threading.RLock()
        self._fit_lock = threading.Lock()  # one fit of this channel at a time
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
        self.stats = JobStats()
        self.last_job_t = -math.inf  # when the scheduler last ran a job of this channel
        self.runner = runner
        self.job_cpu_s = 0.0  # CPU seconds of this channel's jobs, wherever they ran
        self.revision = 0  # bumps whenever published results change

    # --- feeding (acquisition-side, cheap) -------------------------------------------------
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
        with self._lock:
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
        with self._lock:
            c = self._allan.curve("oadev", ci=CI95)
            return dataclasses.replace(c, n_terms=self._full_counts(np.asarray(c.m)))

    # --- model ---------------------------------------------------------------------------
    @property
    def model(self) -> list[str]:
        with self._lock:
            return list(self._model)

    def set_model(self, terms: Sequence[str]) -> dict[str, Any]:
        """Replace the model and refit now (``fit_allan``). Returns the error before and after.

        Raises ``ValueError`` for an unknown term, an empty model or data too short to fit."""
        if not terms:
            raise ValueError("the model needs at least one term")
        check_terms(terms)
        new = _ordered(terms)
        with self._fit_lock:
            with self._lock:
                before = _error(self._fit)
                old_fit = self._fit
                if new == self._model:
                    return self._change_reply(before)
                curve, n = self.curve(), self.n_samples
            fit, intervals = None, QUICK_INTERVALS
            if self._enough(curve, new):
                fit, intervals = self._fit_new_model(curve, n, new, old_fit)
            with self._lock:
                self._model = new
                self._model_revision += 1
                if fit is not None:
                    self._publish(fit, curve, intervals, time.monotonic(), n)
                self.revision += 1
                return self._change_reply(before)

    def _change_reply(self, before: dict[str, float | None]) -> dict[str, Any]:
        return {"channel": self.channel, "model": list(self._model),
                "model_revision": self._model_revision,
                "error_before": before, "error_after": _error(self._fit)}

    def add_term(self, term: str) -> dict[str, Any]:
        check_terms([term])
        model = self.model
        name = parse_model([term]).names[0]
        if name in _names(model) and not get_term(name).repeatable:
            raise ValueError(f"term {term!r} is already in the model")
        return self.set_model(model + [term])

    def remove_term(self, term: str) -> dict[str, Any]:
        check_terms([term])
        model = self.model
        if term not in model and term not in _names(model):
            raise ValueError(f"term {term!r} is not in the model; model: {', '.join(model)}")
        return self.set_model([t for t, n in zip(model, _names(model), strict=True)
                               if t != term and n != term])

    # --- fits ----------------------------------------------------------------------------
    def _enough(self, curve: AllanCurve, model: Sequence[str]) -> bool:
        spec = parse_model(list(model))
        n_free = sum(len(get_term(e.name).params) - len(e.fixed) for e in spec.entries)
        return int(np.count_nonzero(curve.dev > 0)) > n_free

    def _line_samples(self, model: Sequence[str]) -> np.ndarray | None:
        """The longest recent gap-free stretch, where a sinusoid's line is looked for."""
        if not any(get_term(n).role == "line" for n in _names(model)):
            return None
        with self._lock:
            return self._recent.longest_segment()

    def _run(self, fn: Callable[..., Any], *args: Any) -> Any:
        out, cpu = self.runner(fn, *args)
        with self._lock:
            self.job_cpu_s += cpu
        return out, cpu

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

    def _fit_new_model(self, curve: AllanCurve, n: int, model: list[str],
                       previous: FitResult | None) -> tuple[FitResult, str]:
        """Fit a changed model (:func:`_job_fit_new_model`), or reuse a fit of the same model
        on the same samples."""
        with self._lock:
            hit = self._cached(model, QUICK_INTERVALS, n)
        if hit is not None:
            return hit
        start = None
        hints: dict[str, dict[str, float]] = {}
        if previous is not None:
            names = _names(model)
            start = [(t, p) for t, p in previous.params if t in names]
            hints = {t: h for t in names if (h := self._hint(t)) is not None}
        try:
            best, cpu = self._run(_job_fit_new_model, curve, model, start, hints,
                                  self._line_samples(model))
        except (ValueError, TermError, np.linalg.LinAlgError) as exc:
            raise ValueError(f"{self.channel}: cannot fit {'+'.join(model)}: {exc}") from None
        self.stats.last_fit_cpu_s = cpu
        self.stats.fits += 1
        with self._lock:
            self._remember(best, model, n, QUICK_INTERVALS)
        return best, QUICK_INTERVALS

    def _hint(self, term: str) -> dict[str, float] | None:
        """The diagnosis's parameters for ``term``, the start of a warm refit that adds it."""
        with self._lock:
            for s in self._suggestions:
                if s.get("term") == term and s.get("params") and all(
                        v is not None and math.isfinite(v) and v > 0
                        for v in s["params"].values()):
                    return dict(s["params"])
        return None

    def refit(self, full: bool = False, now: float | None = None) -> bool:
        """Refit the current model to the current curve. Returns whether results changed.

        Routine refits start from the previous result with linearised intervals; ``full``
        fits start cold with profile-likelihood intervals, as ``imunoise fit`` does."""
        now = time.monotonic() if now is None else now
        with self._fit_lock:
            with self._lock:
                model = list(self._model)
                revision = self._model_revision
                previous = self._fit if self._fit is not None and \
                    [t.term for t in self._fit.terms] == _names(model) else None
                n = self.n_samples
                intervals = FULL_INTERVALS if full else QUICK_INTERVALS
                hit = self._cached(model, intervals, n)
                self._last_fit_t = now
                if full:
                    self._last_full_t = now
                # the curve of exactly these n samples (HTTP threads refit too)
                curve = self._curve if hit is not None and self._fit_n == n else self.curve()
            if hit is not None:
                fit, intervals = hit
            else:
                if not self._enough(curve, model):
                    return False
                cold = full or previous is None
                w0 = time.monotonic()
                try:
                    fit, cpu = self._run(
                        _job_fit, curve, model,
                        None if cold else _lifted(previous.params, curve),
                        self._line_samples(model) if cold else None, intervals)
                except (ValueError, TermError, np.linalg.LinAlgError):
                    return False
                self.stats.last_fit_wall_s = time.monotonic() - w0
                if full:
                    self.stats.full_fits += 1
                    self.stats.last_full_cpu_s = cpu
                else:
                    self.stats.fits += 1
                    self.stats.last_fit_cpu_s = cpu
            with self._lock:
                if revision != self._model_revision:
                    return False  # the model changed meanwhile; that change published its fit
                self._remember(fit, model, n, intervals)
                if full:
                    self._full_n = n
                self._publish(fit, curve, intervals, now, n)
                return True

    def _publish(self, fit: FitResult, curve: AllanCurve, intervals: str, now: float,
                 n: int | None = None) -> None:
        """Make ``fit`` the current result (caller holds the lock)."""
        self._fit, self._curve, self._fit_intervals = fit, curve, intervals
        self._fit_n = self.n_samples if n is None else n
        self._fit_wall = time.time()
        model = [t.term for t in fit.terms]
        last = self._history[-1] if self._history else None
        point = ErrorPoint(self._model_revision, model, float(fit.chi2_per_dof), time.time(),
                           self._fit_n)
        if last is None or last.revision != self._model_revision or \
                time.time() - last.time_s >= self.history_interval_s:
            self._history.append(point)
        elif len(self._history) >= 2 and self._history[-2].revision == last.revision:
            self._history[-1] = point  # within one interval: the latest fit stands for it
        else:
            self._history.append(point)  # the first entry of a revision stays as it was
        self.revision += 1

    def diagnose(self, now: float | None = None) -> bool:
        """Run :func:`analysis.diagnosis.diagnose` on the recent samples and the current
        model. Returns whether suggestions were published."""
        now = time.monotonic() if now is None else now
        with self._lock:
            self._last_diag_t = now
            model = list(self._model)
            revision = self._model_revision
            values, starts = self._recent.series()
            n = self.n_samples
        try:
            (suggestions, findings), cpu = self._run(_job_diagnose, values, self.fs_hz, model,
                                                     starts, self.units)
        except (ValueError, np.linalg.LinAlgError) as exc:
            with self._lock:
                if revision == self._model_revision:
                    self._suggestions, self._findings = [], []
                    self._diag_note = f"waiting for data: {exc}"
                    self._diag_revision, self._diag_n = revision, n
                    self.revision += 1
            return False
        self.stats.last_diagnosis_cpu_s = cpu
        self.stats.diagnoses += 1
        with self._lock:
            if revision != self._model_revision:
                return False
            self._suggestions = suggestions
            self._findings = findings
            self._diag_revision = revision
            self._diag_n = n
            covered = values.size / self.fs_hz
            self._diag_note = "" if values.size >= n else \
                f"based on the most recent {covered:.0f} s of the record"
            self.revision += 1
        return True

    # --- scheduling ----------------------------------------------------------------------
    def due(self, now: float) -> tuple[float, str] | None:
        """The most overdue job of this channel: ``(since when it is due, kind)``, or None.

        Kinds: ``"full"`` (cold start, profile intervals), ``"fit"`` (warm, linearised),
        ``"diagnose"``."""
        with self._lock:
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

    def run(self, kind: str, now: float | None = None) -> bool:
        """Run one job of :meth:`due`'s kinds."""
        self.last_job_t = time.monotonic() if now is None else now
        if kind == "diagnose":
            return self.diagnose(now)
        return self.refit(full=(kind == "full"), now=now)

    @property
    def fitted(self) -> bool:
        """Whether a fit has been published."""
        with self._lock:
            return self._fit is not None

    # --- views (JSON-ready dicts) --------------------------------------------------------
    def coefficients(self) -> dict[str, Any]:
        """Current coefficients with SI and conventional units and 95 % intervals."""
        with self._lock:
            fit, model = self._fit, list(self._model)
            out: dict[str, Any] = {
                "channel": self.channel, "units": self.units, "fs_hz": self.fs_hz,
                "n_samples": self.n_samples, "duration_s": self.n_samples / self.fs_hz,
                "segments": self.n_segments, "model_revision": self._model_revision,
                "model": [], "error": None, "failures": [],
                "intervals": self._fit_intervals or None,
                "fitted_samples": self._fit_n if fit is not None else 0,
                "fitted_at": self._fit_wall,
            }
            if fit is None:
                out["model"] = [{"term": t, "params": {}, "ci95": {}} for t in model]
                return out
            for t in fit.terms:
                entry: dict[str, Any] = {"term": t.term, "params": {}, "ci95": {}, "units": {},
                                         "conventional": {}}
                for name, value in t.params.items():
                    pu = _param_units(name, self.channel)
                    ci = [float(c) for c in t.ci95[name]] if name in t.ci95 else None
                    entry["params"][name] = float(value)
                    entry["units"][name] = pu.si
                    if ci:
                        entry["ci95"][name] = ci
                    entry["conventional"][name] = {
                        "value": value * pu.factor, "units": pu.conventional,
                        "ci95": [c * pu.factor for c in ci] if ci else None}
                out["model"].append(entry)
            out["error"] = _error(fit)
            out["failures"] = fit.failures
        for entry, t in zip(out["model"], fit.terms, strict=True):
            entry["relative_halfwidth"] = {
                k: ((hi - lo) / (2 * v) if v > 0 and lo > 0 else None)
                for k, v in t.params.items() for lo, hi in [t.ci95.get(k, (0.0, 0.0))]}
        if self.targets:
            self._add_time_to_target(out, fit)
        return out

    def _add_time_to_target(self, out: dict[str, Any], fit: FitResult) -> None:
        """Per targeted parameter: the target and the further recording time (s) until the
        95 % interval reaches it, from the plan for the fitted model (computed once per fit;
        None when the parameter is not resolved yet or the target is out of reach)."""
        from analysis.planning import parse_targets, plan
        from analysis.terms import labels

        if self._plan_cache is None or self._plan_cache[0] != id(fit):
            spec = [(t.term, dict(t.params)) for t in fit.terms]
            resolved = [(lab, p) for t, lab in zip(fit.terms, labels([t.term for t in fit.terms]),
                                                   strict=True)
                        for p in t.params if t.ci95.get(p, (0.0, 0.0))[0] > 0]
            try:
                targets = [tg for tg in parse_targets(self.targets, spec)
                           if (tg.label, tg.param) in resolved]
                plans = {(p.target.label, p.target.param): p for p in
                         plan(spec, self.fs_hz, targets)}
            except ValueError:
                plans = {}
            self._plan_cache = (id(fit), plans)
        plans = self._plan_cache[1]
        recorded = out["duration_s"]
        for entry, label in zip(out["model"], labels([e["term"] for e in out["model"]]),
                                strict=True):
            entry["target"], entry["time_to_target_s"] = {}, {}
            for k in entry["params"]:
                p = plans.get((label, k))
                if p is None:
                    continue
                now = entry["relative_halfwidth"].get(k)
                entry["target"][k] = p.target.relative
                entry["time_to_target_s"][k] = (
                    0.0 if now is not None and now <= p.target.relative else
                    None if p.record_s is None else max(0.0, p.record_s - recorded))

    def _z_on_curve(self, fit: FitResult, curve: AllanCurve) -> np.ndarray:
        z_map = dict(zip(np.round(fit.tau_s, 12), fit.z, strict=True))
        return np.array([z_map.get(round(float(t), 12), np.nan) for t in curve.tau_s])

    def allan(self) -> dict[str, Any]:
        """Allan deviation with its band, the model, each term's curve and the z residuals.

        Once a fit exists this is the curve it was fitted to (at most one refit old), so the
        band, the model and the z residuals belong together; before, the live curve."""
        with self._lock:
            curve, fit = self._curve, self._fit
            if curve is None or fit is None:
                curve, fit = self.curve(), None
            keep = curve.dev > 0  # a constant signal has no log-scale value
            tau = np.asarray(curve.tau_s)[keep]
            out: dict[str, Any] = {
                "channel": self.channel, "units": self.units,
                "tau_s": _finite(tau), "adev": _finite(curve.dev[keep]),
                "ci_low": _finite(curve.ci_low[keep]), "ci_high": _finite(curve.ci_high[keep]),
                "model": list(self._model), "model_adev": None, "terms": {}, "z": None,
                "failures": [], "error": None,
            }
            if fit is not None:
                out["model_adev"] = _finite(np.sqrt(fit.model_avar(tau)))
                out["terms"] = {k: _finite(np.sqrt(v))
                                for k, v in fit.term_avar_at(tau).items()}
                out["z"] = _finite(self._z_on_curve(fit, curve)[keep])
                out["failures"] = fit.failures
                out["error"] = _error(fit)
                out["model"] = [t.term for t in fit.terms]
                # the bound covers the measured band and the fitted model (as analyze does)
                upper = np.fmax(curve.ci_high[keep], np.sqrt(fit.model_avar(tau)))
            else:
                upper = None
            duration = float(curve.n_terms[0] + 2 * curve.m[0]) / curve.fs_hz \
                if len(curve.m) else None
        out["overbound"] = (_overbound(tau, upper, curve.fs_hz, duration)
                            if upper is not None else None)
        return out

    def psd(self, max_points: int = 400) -> dict[str, Any]:
        """Log-frequency PSD (thinned to ``max_points``) with its band and the model PSD."""
        with self._lock:
            try:
                est = self._psd.estimate()
            except ValueError:  # not one full segment yet
                est = None
            fit = self._fit
        out: dict[str, Any] = {"channel": self.channel, "units": f"({self.units})^2/Hz",
                               "f_hz": [], "psd": [], "ci_low": [], "ci_high": [], "dof": [],
                               "model_psd": None}
        if est is None:
            return out
        idx = np.unique(np.geomspace(1, est.f_hz.size, max_points).astype(int) - 1)
        f = est.f_hz[idx]
        out.update(f_hz=_finite(f), psd=_finite(est.psd[idx]), ci_low=_finite(est.ci_low[idx]),
                   ci_high=_finite(est.ci_high[idx]), dof=_finite(est.dof[idx]))
        if fit is not None:
            out["model_psd"] = _finite(model_psd(f, fit.params, self.fs_hz))
        return out

    def diagnosis(self) -> dict[str, Any]:
        """The latest diagnosis of the current model, best first (``note`` says why it is
        empty or what it rests on)."""
        with self._lock:
            suggestions: list[dict] = []
            if self._fit is None:
                note = "waiting for data: no fit yet"
            elif self._diag_revision != self._model_revision:
                note = "waiting for the diagnosis of the current model"
            else:
                note = self._diag_note
                suggestions = [dict(s) for s in self._suggestions
                               if s["term"] not in self._model]
                if not suggestions and not note:
                    note = "every term is already in the model"
            return {"channel": self.channel, "model": list(self._model), "note": note,
                    "model_revision": self._model_revision, "error": _error(self._fit)
                    if self._fit is not None else None,
                    "suggestions": suggestions, "findings": list(self._findings)}

    def history(self) -> list[dict[str, Any]]:
        """Error history: (model revision, model, chi2 per dof, wall time, samples)."""
        with self._lock:
            return [{"revision": p.revision, "model": p.model, "chi2_per_dof": p.chi2_per_dof,
                     "time_s": p.time_s, "n_samples": p.n_samples} for p in self._history]


def _overbound(tau: np.ndarray, upper: np.ndarray, fs_hz: float,
               duration_s: float | None) -> dict[str, Any] | None:
    """The over-bounding model of the live curve (:mod:`analysis.overbound`) for ``/allan``."""
    from analysis.overbound import overbound

    try:
        ob = overbound(tau, upper, fs_hz, duration_s=duration_s)
    except ValueError:
        return None
    return {"model_adev": _finite(ob.model_adev), "N": ob.N, "K": ob.K,
            "markov": [{"sigma": s, "T_s": t} for s, t in ob.markov],
            "median_excess": float(np.median(ob.excess)), "max_excess": float(ob.excess.max())}
