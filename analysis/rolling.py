"""Rolling analysis of live data: streaming Allan and PSD, the current model, refits, diagnosis.

:class:`RollingAnalyzer` takes blocks of samples and keeps one :class:`ChannelAnalyzer` per
channel. Feeding (``update``) only runs the streaming estimators, which are
vectorised and cheap; refits and diagnosis run in :meth:`ChannelAnalyzer.refresh`, which the
caller invokes from its own thread at a bounded cadence, so acquisition never waits on a fit.

Blocks are taken structurally (anything with ``stream``, ``channels``, ``fs_hz`` and
``gap_before`` attributes, e.g. ``daq.blocks.SampleBlock``), so this module imports nothing from
``daq``.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from analysis.live_estimators import AllanCurveData, OctaveAllan
from analysis.live_fit import ORDER, TERMS, LiveFit, fit_model, rank_missing_terms
from analysis.psd import StreamingPsd
from analysis.series import channel_units
from analysis.terms import get_term
from analysis.units import param_units as _param_units

DEFAULT_MODEL: tuple[str, ...] = ("white", "bias_instability", "random_walk")
VALID_TERMS: tuple[str, ...] = tuple(ORDER)
# Octave Allan points needed before missing terms are ranked (a shaped term has two parameters).
MIN_TAUS_FOR_DIAGNOSIS = 8


class BlockLike(Protocol):
    """What :meth:`RollingAnalyzer.update` needs from a block of samples."""

    stream: str
    channels: dict[str, np.ndarray]
    fs_hz: float
    gap_before: int


def model_psd(f_hz: np.ndarray, params: dict[str, dict[str, float]], fs_hz: float) -> np.ndarray:
    """One-sided model PSD ((channel units)^2/Hz) of the fitted terms at ``f_hz``.

    Sinusoids are spectral lines and add nothing to the continuous spectrum drawn here.
    """
    f = np.asarray(f_hz, dtype=np.float64)
    out = np.zeros_like(f)
    for name, p in params.items():
        if name != "sinusoid":
            out += get_term(name).psd(f, fs_hz, **p)
    return out


@dataclass
class ErrorPoint:
    """One entry of the error history."""

    revision: int
    model: list[str]
    chi2_per_dof: float
    time_s: float
    n_samples: int


def _error(fit: LiveFit | None) -> dict[str, float | None]:
    if fit is None:
        return {"chi2_per_dof": None, "max_abs_z": None}
    return {"chi2_per_dof": fit.chi2_per_dof, "max_abs_z": fit.max_abs_z}


def _finite(x: Iterable[float]) -> list[float | None]:
    """A JSON-safe list: non-finite numbers become ``None``."""
    return [float(v) if math.isfinite(v) else None for v in np.asarray(list(x), dtype=float)]


class ChannelAnalyzer:
    """Live analysis of one channel.

    Args:
        channel: channel name (``gyro_x`` ...).
        fs_hz: sampling rate in Hz.
        units: SI units of the values (derived from the name when omitted).
        model: initial model (term names).
        refit_interval_s: least wall-clock time between two refits.
        diagnosis_interval_s: least wall-clock time between two diagnoses.
        history_interval_s: least time between two error-history entries of one model
            revision (a model change always adds one).
        history_len: error history entries kept (bounded memory; 2000 entries at 10 s cover
            5.5 h, older ones are dropped).
        nperseg: PSD segment length in samples at every level of the decimation cascade.
    """

    def __init__(self, channel: str, fs_hz: float, units: str | None = None,
                 model: Sequence[str] = DEFAULT_MODEL, refit_interval_s: float = 2.0,
                 diagnosis_interval_s: float = 10.0, history_interval_s: float = 10.0,
                 history_len: int = 2000,
                 nperseg: int = 256) -> None:
        check_terms(model)
        self.channel = channel
        self.fs_hz = float(fs_hz)
        self.units = units if units is not None else channel_units(channel)
        self.refit_interval_s = refit_interval_s
        self.diagnosis_interval_s = diagnosis_interval_s
        self.history_interval_s = history_interval_s
        self._allan = OctaveAllan(self.fs_hz)
        self._psd = StreamingPsd(self.fs_hz, nperseg=nperseg)
        self._lock = threading.RLock()
        self._model = [t for t in ORDER if t in model]
        self._model_revision = 0
        self.n_samples = 0
        self.n_segments = 0
        self._gap_pending = False
        self._new_since_fit = 0
        self._fit: LiveFit | None = None
        self._curve: AllanCurveData | None = None
        self._suggestions: list[dict] = []
        self._diag_revision = -1
        self._last_fit_t = -math.inf
        self._last_diag_t = -math.inf
        self._history: deque[ErrorPoint] = deque(maxlen=history_len)
        self.revision = 0  # bumps whenever published results change

    # --- feeding (acquisition-side, cheap) -------------------------------------------------
    def update(self, values: np.ndarray, new_segment: bool = False) -> None:
        """Add samples (SI units). ``new_segment``: they do not follow the previous ones."""
        v = np.asarray(values, dtype=np.float64).ravel()
        finite = np.isfinite(v)
        if finite.all():
            runs = [v]
            leading_gap = trailing_gap = False
        else:  # non-finite samples are a gap: analyse the finite runs as separate segments
            edges = np.flatnonzero(np.diff(np.concatenate(([0], finite.view(np.int8), [0]))))
            runs = [v[a:b] for a, b in zip(edges[0::2], edges[1::2], strict=True)]
            leading_gap, trailing_gap = not finite[0], not finite[-1]
        with self._lock:
            self._gap_pending |= new_segment or leading_gap
            for k, run in enumerate(runs):
                if self._gap_pending or k > 0 or self.n_segments == 0:
                    self._allan.new_segment()
                    self._psd.new_segment()
                    self.n_segments += 1
                    self._gap_pending = False
                self._allan.update(run)
                self._psd.update(run)
                self.n_samples += int(run.size)
                self._new_since_fit += int(run.size)
            self._gap_pending |= trailing_gap

    # --- model ---------------------------------------------------------------------------
    @property
    def model(self) -> list[str]:
        with self._lock:
            return list(self._model)

    def set_model(self, terms: Sequence[str]) -> dict[str, Any]:
        """Replace the model and refit now. Returns the error before and after."""
        check_terms(terms)
        if not terms:
            raise ValueError("the model needs at least one term")
        with self._lock:
            before = _error(self._fit)
            old = list(self._model)
            self._model = [t for t in ORDER if t in terms]
            if self._model != old:
                self._model_revision += 1
        self.refresh(force=True)
        with self._lock:
            return {"channel": self.channel, "model": list(self._model),
                    "model_revision": self._model_revision,
                    "error_before": before, "error_after": _error(self._fit)}

    def add_term(self, term: str) -> dict[str, Any]:
        check_terms([term])
        return self.set_model(self.model + [term])

    def remove_term(self, term: str) -> dict[str, Any]:
        check_terms([term])
        model = self.model
        if term not in model:
            raise ValueError(f"term {term!r} is not in the model; model: {', '.join(model)}")
        return self.set_model([t for t in model if t != term])

    # --- refit and diagnosis (off the acquisition path) ----------------------------------
    def refresh(self, force: bool = False, now: float | None = None) -> bool:
        """Refit (and diagnose) when due. Returns whether results changed."""
        now = time.monotonic() if now is None else now
        with self._lock:
            due = force or (self._new_since_fit > 0 and
                            now - self._last_fit_t >= self.refit_interval_s)
            if not due:
                return False
            curve = self._allan.curve()
            model = list(self._model)
            revision = self._model_revision
            n_samples = self.n_samples
            self._new_since_fit = 0
            self._last_fit_t = now
        if curve.tau_s.size < 3:
            return False
        fit = fit_model(curve.tau_s, curve.avar, curve.edf, model, self.fs_hz)
        diagnose = force or revision != self._diag_revision or \
            now - self._last_diag_t >= self.diagnosis_interval_s
        suggestions = None
        if curve.tau_s.size < MIN_TAUS_FOR_DIAGNOSIS:
            suggestions = []
        elif diagnose:
            suggestions = rank_missing_terms(curve.tau_s, curve.avar, curve.edf, model,
                                             self.fs_hz, base=fit)
        with self._lock:
            if revision != self._model_revision:
                return False  # the model changed meanwhile; the next refresh publishes
            self._fit = fit
            self._curve = curve
            if suggestions is not None:
                self._suggestions = suggestions
                self._diag_revision = revision
                self._last_diag_t = now
            last = self._history[-1] if self._history else None
            if last is None or last.revision != revision or \
                    time.time() - last.time_s >= self.history_interval_s:
                self._history.append(ErrorPoint(revision, model, fit.chi2_per_dof,
                                                 time.time(), n_samples))
            self.revision += 1
        return True

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
            }
            if fit is None:
                out["model"] = [{"term": t, "params": {}, "ci95": {}} for t in model]
                return out
            for term in fit.model:
                entry: dict[str, Any] = {"term": term, "params": {}, "ci95": {}, "units": {},
                                         "conventional": {}}
                for name, value in fit.params[term].items():
                    pu = _param_units(name, self.channel)
                    ci = fit.ci95[term].get(name)
                    entry["params"][name] = value
                    entry["units"][name] = pu.si
                    if ci:
                        entry["ci95"][name] = ci
                    entry["conventional"][name] = {
                        "value": value * pu.factor, "units": pu.conventional,
                        "ci95": [c * pu.factor for c in ci] if ci else None}
                out["model"].append(entry)
            out["error"] = {"chi2_per_dof": fit.chi2_per_dof, "max_abs_z": fit.max_abs_z}
            out["failures"] = fit.failures
            return out

    def allan(self) -> dict[str, Any]:
        """Allan deviation with its band, the model, each term's curve and the z residuals."""
        with self._lock:
            curve, fit = self._curve, self._fit
            if curve is None:
                curve = self._allan.curve()
                fit = None
            out: dict[str, Any] = {
                "channel": self.channel, "units": self.units,
                "tau_s": _finite(curve.tau_s), "adev": _finite(curve.dev),
                "ci_low": _finite(curve.ci_low), "ci_high": _finite(curve.ci_high),
                "model": list(self._model), "model_adev": None, "terms": {}, "z": None,
                "failures": [], "error": None,
            }
            if fit is not None and len(fit.model_avar) == len(curve.tau_s):
                out["model_adev"] = _finite(np.sqrt(fit.model_avar))
                out["terms"] = {t: _finite(np.sqrt(a)) for t, a in fit.term_avar.items()}
                out["z"] = _finite(fit.z)
                out["failures"] = fit.failures
                out["error"] = {"chi2_per_dof": fit.chi2_per_dof, "max_abs_z": fit.max_abs_z}
                out["model"] = list(fit.model)
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
        """The latest ranking of missing terms, best first (``note`` says why it is empty)."""
        with self._lock:
            n_taus = self._curve.tau_s.size if self._curve is not None else 0
            if n_taus < MIN_TAUS_FOR_DIAGNOSIS:
                note = (f"waiting for data: the diagnosis needs {MIN_TAUS_FOR_DIAGNOSIS} octaves "
                        f"of averaging time, the data so far give {n_taus}")
            elif len(self._model) == len(ORDER):
                note = "every term is already in the model"
            else:
                note = ""
            return {"channel": self.channel, "model": list(self._model), "note": note,
                    "model_revision": self._model_revision,
                    "error": ({"chi2_per_dof": self._fit.chi2_per_dof,
                               "max_abs_z": self._fit.max_abs_z} if self._fit else None),
                    "suggestions": [dict(s) for s in self._suggestions
                                    if s["term"] not in self._model]}

    def history(self) -> list[dict[str, Any]]:
        """Error history: (model revision, model, chi2 per dof, wall time, samples)."""
        with self._lock:
            return [{"revision": p.revision, "model": p.model, "chi2_per_dof": p.chi2_per_dof,
                     "time_s": p.time_s, "n_samples": p.n_samples} for p in self._history]


def check_terms(terms: Iterable[str]) -> None:
    """Raise ``ValueError`` naming the valid terms when one is unknown."""
    bad = [t for t in terms if t not in TERMS]
    if bad:
        raise ValueError(f"unknown term {', '.join(map(repr, bad))}; valid terms: "
                         f"{', '.join(VALID_TERMS)}")


class RollingAnalyzer:
    """One :class:`ChannelAnalyzer` per analysable channel of the blocks fed.

    Channels named ``gyro_*`` and ``accel_*`` are analysed; a channel name already taken by
    another stream is keyed ``STREAM:NAME``.
    """

    def __init__(self, model: Sequence[str] = DEFAULT_MODEL, **analyzer_kwargs: Any) -> None:
        check_terms(model)
        self._model = list(model)
        self._kwargs = analyzer_kwargs
        self._lock = threading.Lock()
        self._analyzers: dict[str, ChannelAnalyzer] = {}
        self._keys: dict[tuple[str, str], str] = {}

    def update(self, block: BlockLike) -> None:
        """Route a block's channels to their analyzers (new segment after a gap)."""
        gap = getattr(block, "gap_before", 0) != 0
        for name, values in block.channels.items():
            if channel_units(name) not in ("rad/s", "m/s^2"):
                continue
            analyzer = self._analyzer(block.stream, name, block.fs_hz)
            analyzer.update(values, new_segment=gap)

    def _analyzer(self, stream: str, name: str, fs_hz: float) -> ChannelAnalyzer:
        key = self._keys.get((stream, name))
        if key is not None:
            return self._analyzers[key]
        with self._lock:
            key = name if name not in self._analyzers else f"{stream}:{name}"
            self._analyzers[key] = ChannelAnalyzer(key, fs_hz, units=channel_units(name),
                                                   model=self._model, **self._kwargs)
            self._keys[(stream, name)] = key
            return self._analyzers[key]

    @property
    def channels(self) -> list[str]:
        with self._lock:
            return list(self._analyzers)

    def get(self, channel: str) -> ChannelAnalyzer:
        """The analyzer of ``channel``; ``KeyError`` naming the valid channels otherwise."""
        with self._lock:
            if channel not in self._analyzers:
                valid = ", ".join(self._analyzers) or "(none yet)"
                raise KeyError(f"unknown channel {channel!r}; valid channels: {valid}")
            return self._analyzers[channel]

    def refresh(self, force: bool = False) -> bool:
        """Refit every channel that is due. Returns whether anything changed."""
        with self._lock:
            analyzers = list(self._analyzers.values())
        changed = False
        for a in analyzers:
            changed |= a.refresh(force=force)
        return changed

    @property
    def revision(self) -> int:
        with self._lock:
            return sum(a.revision for a in self._analyzers.values())
