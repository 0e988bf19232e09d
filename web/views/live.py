"""The API's views of a live channel (``/coefficients``, ``/allan``, ``/psd``, ``/diagnosis``,
``/model``), built from one :class:`imunoise.analysis.channel_state.ChannelSnapshot` with the parts
of
the command line's documents (:mod:`imunoise.pipeline.documents`)."""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Sequence
from typing import Any

import numpy as np

from imunoise.analysis.channel_state import ChannelSnapshot, ModelChangeResult
from imunoise.analysis.fit import FitResult
from imunoise.analysis.terms import model_psd as terms_model_psd
from imunoise.core.units import param_units
from imunoise.live.channel import LiveChannel
from imunoise.pipeline.documents import error_json, floats, model_json, number, z_on_curve


def model_psd(f_hz: np.ndarray, params: Sequence[tuple[str, dict[str, float]]],
              fs_hz: float) -> np.ndarray:
    """One-sided model PSD ((channel units)^2/Hz) of fitted terms ``[(term, params)]``.

    Sinusoids are spectral lines and add nothing to the continuous spectrum drawn here.
    """
    f = np.asarray(f_hz, dtype=np.float64)
    return terms_model_psd(params, f, fs_hz, continuous_only=True).reshape(f.shape)


# --- coefficients ---------------------------------------------------------------------------

_PLANS: OrderedDict[tuple[int, str, float], tuple[FitResult, dict]] = OrderedDict()
_PLANS_LOCK = threading.Lock()


def _plans(fit: FitResult, targets: str, fs_hz: float) -> dict:
    """The recording plans of a fit's targeted, resolved parameters: ``{(label, param):
    Plan}`` (computed once per fit; the cache holds the fit, so its id stays its own)."""
    from imunoise.analysis.planning import parse_targets, plan

    key = (id(fit), targets, fs_hz)
    with _PLANS_LOCK:
        hit = _PLANS.get(key)
    if hit is not None:
        return hit[1]
    spec = [(t.term, dict(t.params)) for t in fit.terms]
    resolved = [(lab, p) for t, lab in zip(fit.terms, fit.labels, strict=True)
                for p in t.params if t.ci95.get(p, (0.0, 0.0))[0] > 0]
    try:
        wanted = [tg for tg in parse_targets(targets, spec) if (tg.label, tg.param) in resolved]
        plans = {(p.target.label, p.target.param): p for p in plan(spec, fs_hz, wanted)}
    except ValueError:
        plans = {}
    with _PLANS_LOCK:
        _PLANS[key] = (fit, plans)
        while len(_PLANS) > 64:
            _PLANS.popitem(last=False)
    return plans


def _add_time_to_target(out: dict[str, Any], fit: FitResult, targets: str,
                        fs_hz: float) -> None:
    """Per targeted parameter: the target and the further recording time (s) until the
    95 % interval reaches it, from the plan for the fitted model (None when the parameter is
    not resolved yet or the target is out of reach)."""
    plans = _plans(fit, targets, fs_hz)
    recorded = out["duration_s"]
    for entry in out["model"]:
        label = entry["term"]  # name#K for a repeated term
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


def coefficients_view(s: ChannelSnapshot) -> dict[str, Any]:
    """Current coefficients with SI and conventional units and 95 % intervals."""
    fit = s.fit
    out: dict[str, Any] = {
        "channel": s.channel, "units": s.units, "fs_hz": s.fs_hz,
        "n_samples": s.n_samples, "duration_s": s.n_samples / s.fs_hz,
        "segments": s.n_segments, "model_revision": s.model_revision,
        "model": [], "error": None, "failures": [],
        "intervals": s.fit_intervals or None,
        "fitted_samples": s.fit_n if fit is not None else 0,
        "fitted_at": s.fit_wall_s,
    }
    if fit is None:
        out["model"] = [{"term": t, "params": {}, "ci95": {}} for t in s.model]
        return out
    for entry, t in zip(model_json(fit), fit.terms, strict=True):
        entry["units"], entry["conventional"] = {}, {}
        for name, value in t.params.items():
            pu = param_units(name, s.channel)
            ci = entry["ci95"].get(name)
            entry["units"][name] = pu.si
            entry["conventional"][name] = {
                "value": number(value * pu.factor), "units": pu.conventional,
                "ci95": [number(c * pu.factor) for c in t.ci95[name]] if ci else None}
        entry["relative_halfwidth"] = {
            k: ((hi - lo) / (2 * v) if v > 0 and lo > 0 else None)
            for k, v in t.params.items() for lo, hi in [t.ci95.get(k, (0.0, 0.0))]}
        out["model"].append(entry)
    out["error"] = error_json(fit)
    out["failures"] = fit.failures
    if s.targets:
        _add_time_to_target(out, fit, s.targets, s.fs_hz)
    return out


def coefficients(channel: LiveChannel) -> dict[str, Any]:
    """``/coefficients`` of one channel, its error with the PSD part beside the Allan's."""
    s = channel.snapshot()
    out = coefficients_view(s)
    if out["error"] is not None and s.fit is not None:
        out["error"].update(_live_parts(channel.psd_estimate(), s)[1])
    return out


def error_with_parts(fit: FitResult | None, est: Any, fs_hz: float) -> dict[str, Any] | None:
    """A fit's error (:func:`error_json`) with the PSD part against the streaming estimate
    ``est`` beside the Allan's, and the hold-out and time-domain parts with the reason the
    live service leaves them to ``imunoise fit``; None without a fit."""
    if fit is None:
        return None
    out: dict[str, Any] = dict(error_json(fit))
    out.update(_parts_of(est, fit, fs_hz)[1])
    return out


_LIVE_WHY = "not computed by the live service: imunoise fit on the recording reports it"


def _live_parts(est: Any, s: ChannelSnapshot) -> tuple[np.ndarray | None, dict[str, Any]]:
    """The estimator's expected PSD under the snapshot's fit (or None) and the error's PSD,
    hold-out and time-domain parts for the live views."""
    return _parts_of(est, s.fit, s.fs_hz)


def _parts_of(est: Any, fit: FitResult | None, fs_hz: float
              ) -> tuple[np.ndarray | None, dict[str, Any]]:
    """:func:`_live_parts` of any fit of the channel (the one before a model change too)."""
    from imunoise.analysis.model_error import plain, streaming_psd_part

    parts: dict[str, Any] = {
        "psd": {"deviance_per_bin": None, "bins": 0, "outside_95": None,
                "reason": "no PSD estimate yet"},
        "holdout": {"chi2_per_dof": None, "parts": 2, "reason": _LIVE_WHY},
        "time_domain": {"statistic": None, "p": None, "reason": _LIVE_WHY}}
    if est is None or fit is None:
        return None, parts
    expected, part = streaming_psd_part(fit.params, est, fs_hz)
    parts["psd"] = plain(part)
    return expected, parts


# --- curves ---------------------------------------------------------------------------------

def allan(channel: LiveChannel) -> dict[str, Any]:
    """Allan deviation with its band, the model, each term's curve and the z residuals.

    Once a fit exists this is the curve it was fitted to (at most one refit old), so the
    band, the model and the z residuals belong together; before, the live curve."""
    s = channel.snapshot()
    fit, curve = s.fit, s.fit_curve
    if fit is None or curve is None:
        fit, curve = None, channel.curve()
    keep = curve.dev > 0  # a constant signal has no log-scale value
    tau = np.asarray(curve.tau_s)[keep]
    out: dict[str, Any] = {
        "channel": s.channel, "units": s.units,
        "tau_s": floats(tau), "adev": floats(curve.dev[keep]),
        "ci_low": floats(curve.ci_low[keep]), "ci_high": floats(curve.ci_high[keep]),
        "model": list(s.model), "model_adev": None, "terms": {}, "z": None,
        "failures": [], "error": None,
    }
    upper = None
    if fit is not None:
        model_adev = np.sqrt(fit.model_avar(tau))
        out["model_adev"] = floats(model_adev)
        out["terms"] = {k: floats(np.sqrt(v)) for k, v in fit.term_avar_at(tau).items()}
        out["z"] = floats(z_on_curve(fit, curve)[keep])
        out["failures"] = fit.failures
        out["error"] = error_json(fit)
        out["model"] = [t.term for t in fit.terms]
        # the bound covers the measured band and the fitted model (as analyze does)
        upper = np.fmax(curve.ci_high[keep], model_adev)
    duration = float(curve.n_terms[0] + 2 * curve.m[0]) / curve.fs_hz if len(curve.m) else None
    out["overbound"] = _overbound(tau, upper, curve.fs_hz, duration) if upper is not None \
        else None
    return out


def _overbound(tau: np.ndarray, upper: np.ndarray, fs_hz: float,
               duration_s: float | None) -> dict[str, Any] | None:
    """The over-bounding model of the live curve (:mod:`imunoise.analysis.overbound`)."""
    from imunoise.analysis.overbound import overbound

    try:
        ob = overbound(tau, upper, fs_hz, duration_s=duration_s)
    except ValueError:
        return None
    return {"model_adev": floats(ob.model_adev), "N": ob.N, "K": ob.K,
            "markov": [{"sigma": s, "T_s": t} for s, t in ob.markov],
            "median_excess": float(np.median(ob.excess)), "max_excess": float(ob.excess.max())}


def psd(channel: LiveChannel, max_points: int = 400) -> dict[str, Any]:
    """Log-frequency PSD (thinned to ``max_points``) with its band and the model PSD."""
    s = channel.snapshot()
    est = channel.psd_estimate()
    out: dict[str, Any] = {"channel": s.channel, "units": f"({s.units})^2/Hz",
                           "f_hz": [], "psd": [], "ci_low": [], "ci_high": [], "dof": [],
                           "model_psd": None}
    if est is None:
        return out
    idx = np.unique(np.geomspace(1, est.f_hz.size, max_points).astype(int) - 1)
    f = est.f_hz[idx]
    out.update(f_hz=floats(f), psd=floats(est.psd[idx]), ci_low=floats(est.ci_low[idx]),
               ci_high=floats(est.ci_high[idx]), dof=floats(est.dof[idx]))
    if s.fit is not None:
        from imunoise.analysis.psd_model import psd_z

        expected, _ = _live_parts(est, s)
        if expected is not None:
            out["model_psd"] = floats(expected[idx])
            out["z"] = floats(psd_z(est.psd, est.dof, expected)[idx])
        else:
            out["model_psd"] = floats(model_psd(f, s.fit.params, s.fs_hz))
    return out


# --- the model ------------------------------------------------------------------------------

def diagnosis_view(s: ChannelSnapshot) -> dict[str, Any]:
    """The latest diagnosis of the current model, best first (``note`` says why it is empty
    or what it rests on)."""
    suggestions: list[dict] = []
    if s.fit is None:
        note = "waiting for data: no fit yet"
    elif s.diagnosis_revision != s.model_revision:
        note = "waiting for the diagnosis of the current model"
    else:
        note = s.diagnosis_note
        suggestions = [dict(x) for x in s.suggestions if x["term"] not in s.model]
        if not suggestions and not note:
            note = "every term is already in the model"
    return {"channel": s.channel, "model": list(s.model), "note": note,
            "model_revision": s.model_revision,
            "error": error_json(s.fit) if s.fit is not None else None,
            "suggestions": suggestions, "findings": [dict(f) for f in s.findings]}


def diagnosis(channel: LiveChannel) -> dict[str, Any]:
    """``/diagnosis`` of one channel, its error with every part (:func:`error_with_parts`)."""
    s = channel.snapshot()
    out = diagnosis_view(s)
    out["error"] = error_with_parts(s.fit, channel.psd_estimate(), s.fs_hz)
    return out


def model(channel: LiveChannel, valid_terms: Sequence[str]) -> dict[str, Any]:
    """``GET /model`` of one channel: the model, its revision, the terms that may be added,
    the error with every part (:func:`error_with_parts`) and the error history."""
    s = channel.snapshot()
    d = diagnosis_view(s)
    return {"channel": s.channel, "model": d["model"], "model_revision": d["model_revision"],
            "valid_terms": list(valid_terms),
            "error": error_with_parts(s.fit, channel.psd_estimate(), s.fs_hz),
            "history": history_view(s)}


def history_view(s: ChannelSnapshot) -> list[dict[str, Any]]:
    """Error history: (model revision, model, chi2 per dof, PSD part, wall time, samples)."""
    return [{"revision": p.revision, "model": p.model, "chi2_per_dof": number(p.chi2_per_dof),
             "psd_deviance_per_bin": number(p.psd_deviance_per_bin),
             "time_s": p.time_s, "n_samples": p.n_samples} for p in s.history]


def history(channel: LiveChannel) -> list[dict[str, Any]]:
    return history_view(channel.snapshot())


def model_change(result: ModelChangeResult, channel: LiveChannel | None = None
                 ) -> dict[str, Any]:
    """The reply to a model change: the model, its revision, the error before and after;
    given the ``channel``, each error with every part, both PSD parts against the same
    streaming estimate (:func:`error_with_parts`)."""
    if channel is None:
        before, after = error_json(result.before), error_json(result.after)
    else:
        est, fs_hz = channel.psd_estimate(), channel.snapshot().fs_hz
        before = error_with_parts(result.before, est, fs_hz) or error_json(None)
        after = error_with_parts(result.after, est, fs_hz) or error_json(None)
    return {"channel": result.channel, "model": list(result.model),
            "model_revision": result.model_revision,
            "error_before": before, "error_after": after}
