"""One channel of the live analysis, safe to share between threads.

:class:`LiveChannel` wraps the pure :class:`imunoise.analysis.channel_state.ChannelState`: it holds
the
locks (HTTP threads read and change the model while the analysis thread feeds samples and
runs the scheduled jobs), reads the clocks, and runs the costly jobs through a runner (in the
calling thread, or in a worker process off the interpreter lock). The state's lock is held
only to plan a job and to publish its result, never while it runs; a second lock keeps one
fit or model change of the channel at a time.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any, Protocol

import numpy as np

from imunoise.analysis.allan import AllanCurve
from imunoise.analysis.channel_state import (
    DEFAULT_MODEL,
    ChannelSnapshot,
    ChannelState,
    FitJob,
    ModelChangeResult,
)
from imunoise.analysis.fit import FitResult
from imunoise.analysis.model_error import streaming_psd_part
from imunoise.analysis.terms import TermError


def timed(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``fn(*args)`` and the CPU seconds of the thread that ran it."""
    t0 = time.thread_time()
    out = fn(*args)
    return out, time.thread_time() - t0


class Runner(Protocol):
    """Runs a job function, returns ``(result, CPU seconds)``."""

    def __call__(self, fn: Callable[..., Any], *args: Any) -> tuple[Any, float]: ...


def run_inline(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """Run a job in the calling thread."""
    return timed(fn, *args)


_FIT_ERRORS = (ValueError, TermError, np.linalg.LinAlgError)


class LiveChannel:
    """Live analysis of one channel (see the module docstring).

    Args:
        channel, fs_hz, units, model: as :class:`imunoise.analysis.channel_state.ChannelState`.
        runner: runs the fits and the diagnosis (:func:`run_inline`, or a
            :class:`imunoise.live.scheduler.WorkerProcess` to keep them off the interpreter lock).
        **state_kwargs: the cadences and sizes of :class:`ChannelState`.
    """

    def __init__(self, channel: str, fs_hz: float, units: str | None = None,
                 model: Sequence[str] = DEFAULT_MODEL, runner: Runner = run_inline,
                 **state_kwargs: Any) -> None:
        self._state = ChannelState(channel, fs_hz, units=units, model=model, **state_kwargs)
        self._lock = threading.RLock()
        self._fit_lock = threading.Lock()  # one fit or model change of this channel at a time
        self.runner = runner
        self.job_cpu_s = 0.0  # CPU seconds of this channel's jobs, wherever they ran
        self.last_job_t = -math.inf  # when the scheduler last ran a job of this channel

    @property
    def channel(self) -> str:
        return self._state.channel

    @property
    def fs_hz(self) -> float:
        return self._state.fs_hz

    @property
    def units(self) -> str:
        return self._state.units

    @property
    def n_samples(self) -> int:
        with self._lock:
            return self._state.n_samples

    @property
    def n_segments(self) -> int:
        with self._lock:
            return self._state.n_segments

    @property
    def revision(self) -> int:
        """Bumps whenever published results change."""
        with self._lock:
            return self._state.revision

    @property
    def fitted(self) -> bool:
        with self._lock:
            return self._state.fitted

    @property
    def model(self) -> list[str]:
        with self._lock:
            return self._state.model

    # --- feeding -------------------------------------------------------------------------
    def update(self, values: np.ndarray, new_segment: bool = False) -> None:
        """Add samples (SI units); see :meth:`ChannelState.update`."""
        with self._lock:
            self._state.update(values, new_segment)

    def curve(self) -> AllanCurve:
        """The Allan curve of everything fed so far."""
        with self._lock:
            return self._state.curve()

    # --- jobs ----------------------------------------------------------------------------
    def _run(self, fn: Callable[..., Any], *args: Any) -> Any:
        out, cpu = self.runner(fn, *args)
        with self._lock:
            self.job_cpu_s += cpu
        return out

    def _fit(self, job: FitJob) -> FitResult:
        return job.cached if job.fn is None else self._run(job.fn, *job.args)

    def set_model(self, terms: Sequence[str]) -> ModelChangeResult:
        """Replace the model and refit now. Raises ``ValueError`` for an unknown term, an
        empty model or a model the data cannot fit."""
        with self._fit_lock:
            with self._lock:
                change = self._state.plan_model_change(terms)
            fit = None
            if change.job is not None:
                try:
                    fit = self._fit(change.job)
                except _FIT_ERRORS as exc:
                    raise ValueError(f"{self.channel}: cannot fit {'+'.join(change.model)}: "
                                     f"{exc}") from None
            wall = time.time()
            part = None if fit is None else self._psd_part(fit, wall, model_changes=True)
            with self._lock:
                return self._state.finish_model_change(change, fit, wall, part)

    def add_term(self, term: str) -> ModelChangeResult:
        with self._lock:
            model = self._state.with_term(term)
        return self.set_model(model)

    def remove_term(self, term: str) -> ModelChangeResult:
        with self._lock:
            model = self._state.without_term(term)
        return self.set_model(model)

    def refit(self, full: bool = False, now: float | None = None) -> bool:
        """Refit the current model (``full``: cold start and profile intervals, as
        ``imunoise fit``). Returns whether results changed."""
        now = time.monotonic() if now is None else now
        with self._fit_lock:
            with self._lock:
                job = self._state.plan_refit(full, now)
            if job is None:
                return False
            try:
                fit = self._fit(job)
            except _FIT_ERRORS:
                return False
            wall = time.time()
            part = self._psd_part(fit, wall)
            with self._lock:
                return self._state.finish_refit(job, fit, wall, part)

    def _psd_part(self, fit: FitResult, wall_s: float, model_changes: bool = False
                  ) -> float | None:
        """The fit's PSD part (Whittle deviance per bin of the streaming PSD) when its error-
        history entry is a new one, else None (the entry keeps the interval's)."""
        with self._lock:
            if not self._state.history_entry_due(wall_s, model_changes):
                return None
            est = self._state.psd_estimate()
            fs = self._state.fs_hz
        if est is None:
            return None
        try:
            _, part = self._run(streaming_psd_part, fit.params, est, fs)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError):
            return None
        value = part.get("deviance_per_bin")
        return None if value is None else float(value)

    def diagnose(self, now: float | None = None) -> bool:
        """Diagnose the current model on the recent samples. Returns whether suggestions
        were published."""
        now = time.monotonic() if now is None else now
        with self._lock:
            job = self._state.plan_diagnosis(now)
        try:
            result = self._run(job.fn, *job.args)
        except (ValueError, np.linalg.LinAlgError) as exc:
            with self._lock:
                self._state.fail_diagnosis(job, str(exc))
            return False
        with self._lock:
            return self._state.finish_diagnosis(job, result)

    def due(self, now: float) -> tuple[float, str] | None:
        """The most overdue job: ``(since when, kind)`` (see :meth:`ChannelState.due`)."""
        with self._lock:
            return self._state.due(now)

    def run(self, kind: str, now: float | None = None) -> bool:
        """Run one job of :meth:`due`'s kinds."""
        self.last_job_t = time.monotonic() if now is None else now
        if kind == "diagnose":
            return self.diagnose(now)
        return self.refit(full=(kind == "full"), now=now)

    # --- what the views show -------------------------------------------------------------
    def snapshot(self) -> ChannelSnapshot:
        """The published results, taken under the lock."""
        with self._lock:
            return self._state.snapshot()

    def psd_estimate(self) -> Any:
        """The streaming PSD estimate, or None before one full segment."""
        with self._lock:
            return self._state.psd_estimate()
