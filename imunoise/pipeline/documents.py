"""JSON documents of the command line (``analyze``, ``fit``, ``diagnose``) and the parts that
the live views (:mod:`imunoise.web.views.live`) share with them.

Every number is a plain float; a value that is not finite becomes ``null`` so the output is
strict JSON. Shapes follow docs/json.md and docs/schemas/: a channel document carries
``channel, units, fs_hz, n_samples, duration_s, model, error, failures, allan`` and, for
``analyze``, ``psd``.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from imunoise.analysis.terms import get_term
from imunoise.core.record import Record
from imunoise.core.series import ChannelSeries

if TYPE_CHECKING:
    from imunoise.analysis.fit import FitResult
    from imunoise.analysis.psd import PsdEstimate


class AllanLike(Protocol):
    """The parts of an Allan curve (``imunoise.analysis.allan.AllanCurve``) that the JSON shows
    (read-only: the curve is a frozen dataclass)."""

    @property
    def tau_s(self) -> np.ndarray: ...
    @property
    def dev(self) -> np.ndarray: ...
    @property
    def ci_low(self) -> np.ndarray: ...
    @property
    def ci_high(self) -> np.ndarray: ...
    @property
    def edf(self) -> np.ndarray: ...
    @property
    def alpha(self) -> np.ndarray: ...
    @property
    def ci(self) -> float: ...


def floats(values: Iterable[float] | np.ndarray) -> list[float | None]:
    """A list of plain floats, non-finite values as None."""
    arr = np.asarray(values, dtype=np.float64).ravel()
    return [float(v) if np.isfinite(v) else None for v in arr.tolist()]


def number(value: float | None) -> float | None:
    """One plain float, or None when missing or not finite."""
    if value is None:
        return None
    value = float(value)
    return value if np.isfinite(value) else None


NO_ERROR: Mapping[str, None] = {"chi2_per_dof": None, "max_abs_z": None}
"""The ``error`` object of a channel without a model fit."""


def error_json(fit: FitResult | None) -> dict[str, float | None]:
    """The ``error`` object of a fit: chi2 per degree of freedom and the largest |z|."""
    if fit is None:
        return dict(NO_ERROR)
    return {"chi2_per_dof": number(fit.chi2_per_dof), "max_abs_z": number(fit.max_abs_z)}


def model_json(fit: FitResult) -> list[dict[str, Any]]:
    """The JSON ``model`` entries of a fit (parameters in the channel's SI units), each
    with ``unresolved``: the amplitudes whose 95 % interval reaches zero (no estimate, only an
    upper bound). ``term`` is the term's label: its name, ``name#K`` for the K-th of a
    repeated term, as the hold-out part's ``changed`` entries name its parameters and as a
    model specification may write it."""
    return [{"term": label, "params": {k: number(v) for k, v in t.params.items()},
             "ci95": {k: [number(a), number(b)] for k, (a, b) in t.ci95.items()},
             "unresolved": [k for k in t.params
                            if not get_term(t.term).resolved(k, t.ci95.get(k))]}
            for label, t in zip(fit.labels, fit.terms, strict=True)]


def z_on_curve(fit: FitResult, curve: AllanLike) -> np.ndarray:
    """The fit's z at each tau of the curve (NaN where the fit had no estimate)."""
    z_map = dict(zip(np.round(fit.tau_s, 12), fit.z, strict=True))
    return np.array([z_map.get(round(float(t), 12), np.nan) for t in curve.tau_s])


def fit_fields(fit: FitResult, curve: AllanLike) -> dict[str, Any]:
    """The fit's part of a channel document: model, error, failures, model_adev, z."""
    return {"model": model_json(fit), "error": error_json(fit), "failures": fit.failures,
            "model_adev": np.sqrt(fit.model_avar(curve.tau_s)), "z": z_on_curve(fit, curve)}


def allan_json(curve: AllanLike | None, model_adev: Sequence[float] | np.ndarray = (),
               z: Sequence[float] | np.ndarray = ()) -> dict[str, Any]:
    """The ``allan`` object: measured deviation with its interval, model curve and z-scores.

    The arrays run parallel to ``tau_s``: without a model, ``model_adev`` and ``z`` hold null
    at every tau."""
    if curve is not None:
        n_tau = len(np.asarray(curve.tau_s))
        if len(model_adev) == 0:
            model_adev = np.full(n_tau, np.nan)
        if len(z) == 0:
            z = np.full(n_tau, np.nan)
    if curve is None:
        return {"tau_s": [], "adev": [], "ci_low": [], "ci_high": [], "model_adev": floats(
            model_adev), "z": floats(z), "edf": [], "alpha": [], "ci": None}
    return {
        "tau_s": floats(curve.tau_s),
        "adev": floats(curve.dev),
        "ci_low": floats(curve.ci_low),
        "ci_high": floats(curve.ci_high),
        "model_adev": floats(model_adev),
        "z": floats(z),
        "edf": floats(curve.edf),
        "alpha": [int(a) for a in np.asarray(curve.alpha).ravel()],
        "ci": number(curve.ci),
    }


def psd_json(est: PsdEstimate | None) -> dict[str, Any]:
    """The ``psd`` object: one-sided PSD (units^2/Hz) with its interval, dof and method."""
    if est is None:
        return {"f_hz": [], "psd": [], "ci_low": [], "ci_high": [], "dof": [], "method": [],
                "ci": None}
    return {
        "f_hz": floats(est.f_hz),
        "psd": floats(est.psd),
        "ci_low": floats(est.ci_low),
        "ci_high": floats(est.ci_high),
        "dof": floats(est.dof),
        "method": [str(m) for m in est.method],
        "ci": number(est.ci),
    }


def channel_json(
    series: ChannelSeries,
    allan: AllanLike | None,
    *,
    model: Sequence[Mapping[str, Any]] = (),
    error: Mapping[str, Any] | None = None,
    failures: Sequence[Mapping[str, Any]] = (),
    model_adev: Sequence[float] | np.ndarray = (),
    z: Sequence[float] | np.ndarray = (),
    psd: PsdEstimate | None = None,
    include_psd: bool = False,
    warnings: Sequence[str] = (),
    channel: str | None = None,
) -> dict[str, Any]:
    """One channel's document (the ``fit`` shape, plus ``psd`` when ``include_psd``).

    ``channel`` is the record's key for the series (default: the series name).
    """
    doc: dict[str, Any] = {
        "channel": channel or series.name,
        "units": series.units,
        "fs_hz": number(series.fs_hz),
        "n_samples": series.n_samples,
        "duration_s": number(series.duration_s),
        "n_segments": int(len(series.segment_starts)),
        "model": [dict(m) for m in model],
        "error": dict(error) if error is not None else dict(NO_ERROR),
        "failures": [dict(f) for f in failures],
        "allan": allan_json(allan, model_adev, z),
    }
    if include_psd or psd is not None:
        doc["psd"] = psd_json(psd)
    if warnings:
        doc["warnings"] = list(warnings)
    return doc


def analyze_json(file: str, channels: Mapping[str, dict[str, Any]],
                 warnings: Sequence[str] = ()) -> dict[str, Any]:
    """The ``analyze`` document: ``{"file", "channels": {key: channel document}, "warnings"}``."""
    return {"file": file, "channels": dict(channels), "warnings": list(warnings)}


def dumps(doc: Mapping[str, Any]) -> str:
    """Strict JSON text (no NaN or Infinity tokens)."""
    return json.dumps(doc, allow_nan=False, separators=(",", ":"))


def analysis_json(path: str, record: Record, results: Sequence[Any]) -> dict[str, Any]:
    """The ``analyze`` JSON document of analysed channels
    (:class:`imunoise.pipeline.channel_analysis.ChannelAnalysis`)."""
    channels = {
        r.key: _with_psd_part(channel_json(r.series, r.allan, psd=r.psd, include_psd=True,
                                           warnings=r.warnings, channel=r.key,
                                           **(fit_fields(r.fit, r.allan) if r.fit else {})), r)
        for r in results
    }
    doc = analyze_json(path, channels, record.warnings)
    stated = dataset_statement(record)
    if stated:
        doc["dataset"] = stated
    for key in ("timing", "motion"):
        if key in record.facts:
            doc[key] = record.facts[key]
    return doc


def _with_psd_part(doc: dict[str, Any], r: Any) -> dict[str, Any]:
    """An ``analyze`` channel document with the default model's PSD part: ``psd.model_psd``,
    ``psd.z`` and ``error.psd``; the hold-out and time-domain parts are left to ``fit`` (they
    cost two fits and a transient search per channel)."""
    from imunoise.analysis.model_error import plain

    if r.fit is None or r.psd is None:
        return doc
    block, parts = analyze_error_parts(r)
    doc["psd"]["model_psd"] = plain(block["model_psd"])
    doc["psd"]["z"] = plain(block["z"])
    doc["error"].update(plain(parts))
    return doc


def analyze_error_parts(r: Any) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(psd block, error parts)`` of an ``analyze`` channel result with a fit and a PSD:
    the default model's PSD part; the hold-out and time-domain parts not computed, with the
    reason."""
    from imunoise.analysis.model_error import psd_parts
    from imunoise.analysis.psd import default_nperseg

    bounds = np.append(r.series.segment_starts, r.series.n_samples)
    nperseg = default_nperseg(int(np.max(np.diff(bounds))))
    block, part = psd_parts(r.fit.params, r.psd, r.series.fs_hz, nperseg)
    why = "not computed by analyze: imunoise fit reports it"
    return block, {"psd": part,
                   "holdout": {"chi2_per_dof": None, "parts": 2, "reason": why},
                   "time_domain": {"statistic": None, "p": None, "reason": why}}


def dataset_statement(record: Record) -> dict[str, Any]:
    """What a dataset's own ``sensor.yaml`` states (EuRoC/ASL layout), to show beside the
    measured values: ``{"sensor_yaml": path, "rate_hz": ..., "gyroscope_noise_density": ...}``."""
    md = record.metadata
    out: dict[str, Any] = {}
    for key, value in md.items():
        if key == "dataset_sensor_yaml":
            out["sensor_yaml"] = value
        elif key.startswith("dataset_"):
            out[key.removeprefix("dataset_")] = float(value)
    return out


def fit_json(record: Record, key: str, result: Any, curve: Any,
             parts: tuple[dict[str, Any] | None, dict[str, Any]] | None = None
             ) -> dict[str, Any]:
    """The ``fit`` JSON document of one channel (with the reader's ``warnings``, if any, and
    the channel's held samples, :func:`imunoise.analysis.evidence.held.warning_text`).

    ``parts`` is ``(psd block, error parts)`` from
    :func:`imunoise.analysis.model_error.error_parts`: the ``psd`` block (measured PSD with
    ``model_psd`` and ``z``) and the ``error``'s ``psd``, ``holdout`` and ``time_domain``."""
    from imunoise.analysis.evidence.held import held_samples, warning_text
    from imunoise.analysis.model_error import plain

    series = record.series(key)
    held = warning_text(held_samples(series.segments(), series.fs_hz, units=series.units))
    doc = channel_json(series, curve, channel=key,
                       warnings=[*record.warnings, *([held] if held else [])],
                       **fit_fields(result, curve))
    for fact in ("timing", "motion"):
        if fact in record.facts:
            doc[fact] = record.facts[fact]
    if parts is not None:
        block, error = parts
        doc["error"].update(plain(error))
        if block is not None:
            doc["psd"] = plain(block)
    return doc


def diagnosis_json(record: Record, key: str, diag: Any) -> dict[str, Any]:
    """``fit``'s JSON document plus ``suggestions`` (best first) and ``evidence``."""
    doc = fit_json(record, key, diag.fit, diag.curve,
                   (getattr(diag, "psd", None), getattr(diag, "error_parts", {}) or {}))
    doc["suggestions"] = finite_or_null([s.to_dict() for s in diag.suggestions])
    doc["evidence"] = finite_or_null([f.to_dict() for f in diag.findings])
    return doc


def finite_or_null(obj: Any) -> Any:
    """``obj`` with every float that is not finite (an unbounded interval of a short record,
    say) as None, through dicts, lists and tuples; JSON has no Infinity."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, np.floating):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: finite_or_null(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v) for v in obj]
    return obj
