"""Per-channel extras of ``analyze``: the discrete model, its simulated check, term curves.

``extend_channel`` adds to a channel's ``fit`` document (docs/json.md keys):

- ``discrete_model`` (always): the filter-ready model at the sample period
  (:mod:`imunoise.analysis.discrete`), its bias-instability approximation fitted over the measured
  tau
  range;
- with ``full=True`` (the HTML report): ``discrete_check``, ``terms_adev``, ``model_psd`` and,
  from :func:`complete_document`, the diagnosis ``suggestions`` and the record's facts.

``discrete_check`` simulates the discrete model for as many samples as the channel has (at most
``MAX_CHECK_SAMPLES``), computes its overlapping Allan deviation on the measured tau grid and
counts the averaging times where it agrees with the measurement. Two independent estimates of
the same curve differ by more than either's own interval: a point agrees when the log-ratio of
simulated to measured deviation lies within sqrt(2) times the measured 95 % half-width (in log),
so on a correct model about 95 % of the points agree.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from imunoise.analysis.default_model import DEFAULT_MODEL
from imunoise.analysis.discrete import DiscreteModel, discretize, simulate
from imunoise.analysis.terms import term_name

MAX_CHECK_SAMPLES = 1 << 23  # 8.4 M samples: 67 MB per array, about two seconds to simulate


def _model_tuples(doc: Mapping) -> list[tuple[str, dict[str, float]]]:
    # a document's ``term`` is a label (``resonance#2`` for a second resonance)
    return [(term_name(str(t["term"])), {k: float(v) for k, v in (t.get("params") or {}).items()})
            for t in doc.get("model") or []]


def discrete_for_channel(doc: Mapping) -> DiscreteModel | None:
    """The discrete model of a fitted channel document, or None without a model."""
    model = _model_tuples(doc)
    fs = doc.get("fs_hz")
    if not model or not fs:
        return None
    tau = np.asarray((doc.get("allan") or {}).get("tau_s") or [], dtype=np.float64)
    tau_range = (float(tau.min()), float(tau.max())) if tau.size >= 2 else None
    from imunoise.analysis.terms import get_term

    bias_instability = get_term("bias_instability")

    def flicker(t: np.ndarray, B: float) -> np.ndarray:
        return bias_instability.avar(t, float(fs), B=B)

    return discretize(model, float(fs), str(doc.get("units", "")), tau_range_s=tau_range,
                      flicker_avar=flicker)


def discrete_check(dm: DiscreteModel, doc: Mapping, seed: int = 0) -> dict | None:
    """Allan deviation of a simulation of ``dm`` on the measured grid, and the agreement."""
    from imunoise.analysis.allan import oadev

    al = doc.get("allan") or {}
    tau = np.asarray(al.get("tau_s") or [], dtype=np.float64)
    adev = np.asarray(al.get("adev") or [], dtype=np.float64)
    lo = np.asarray(al.get("ci_low") or [], dtype=np.float64)
    hi = np.asarray(al.get("ci_high") or [], dtype=np.float64)
    n = int(min(int(doc.get("n_samples") or 0), MAX_CHECK_SAMPLES))
    if tau.size == 0 or n < 4 or not (adev.size == lo.size == hi.size == tau.size):
        return None
    fs = dm.fs_hz
    m = np.unique(np.rint(tau * fs).astype(np.int64))
    m = m[(m >= 1) & (2 * m < n)]
    if m.size == 0:
        return None
    y = simulate(dm, n, seed)
    curve = oadev(y, fs, m=m, ci=None)  # only the deviation is used: no intervals
    sim_tau = np.asarray(curve.tau_s, dtype=np.float64)
    sim_dev = np.asarray(curve.dev, dtype=np.float64)
    # agreement at the measured taus that the simulation also has
    idx = np.searchsorted(sim_tau, tau)
    idx = np.clip(idx, 0, sim_tau.size - 1)
    same = np.isclose(sim_tau[idx], tau, rtol=1e-9)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.log(sim_dev[idx] / adev)
        half_lo = np.log(adev / lo)
        half_hi = np.log(hi / adev)
    ok = same & np.isfinite(r) & np.isfinite(half_lo) & np.isfinite(half_hi)
    agree = ok & (r >= -np.sqrt(2.0) * half_lo) & (r <= np.sqrt(2.0) * half_hi)
    exact = np.sqrt(dm.avar(tau))
    inside_exact = (exact >= lo) & (exact <= hi)
    return {
        "tau_s": sim_tau.tolist(), "adev": sim_dev.tolist(), "n_samples": n, "seed": seed,
        "inside": int(agree.sum()), "total": int(ok.sum()),
        "exact_adev": exact.tolist(), "exact_inside": int(inside_exact.sum()),
        "exact_total": int(tau.size),
    }


def term_curves(doc: Mapping) -> dict[str, list[float]]:
    """Each fitted term's own Allan deviation on the measured tau grid."""
    from imunoise.analysis.terms import get_term

    tau = np.asarray((doc.get("allan") or {}).get("tau_s") or [], dtype=np.float64)
    fs = float(doc.get("fs_hz") or 0.0)
    out: dict[str, list[float]] = {}
    if tau.size == 0 or fs <= 0:
        return out
    for term, params in _model_tuples(doc):
        if term == "temperature":
            continue  # its Allan curve depends on the temperature record, not on tau alone
        avar = get_term(term).avar(tau, fs, **params)
        label = term if term not in out else f"{term} ({sum(k.startswith(term) for k in out)})"
        out[label] = np.sqrt(np.maximum(avar, 0.0)).tolist()
    return out


def model_psd(doc: Mapping) -> dict[str, list[float]] | None:
    """The fitted model's one-sided PSD on the measured frequency grid."""
    from imunoise.analysis.terms import model_psd as psd_of

    f = np.asarray((doc.get("psd") or {}).get("f_hz") or [], dtype=np.float64)
    fs = float(doc.get("fs_hz") or 0.0)
    model = [(t, p) for t, p in _model_tuples(doc) if t != "temperature"]
    if f.size == 0 or fs <= 0 or not model:
        return None
    return {"f_hz": f.tolist(), "psd": np.asarray(psd_of(model, f, fs)).tolist()}


def overbound_for_channel(doc: Mapping, markov: bool = True,
                          band_hz: tuple[float, float] | None = None) -> dict | None:
    """The over-bounding model of a channel document (:mod:`imunoise.analysis.overbound`): on or
    above
    the measured Allan deviation's upper 95 % bound at every tau (and the PSD's in
    ``band_hz``), or None without a curve."""
    from imunoise.analysis.overbound import overbound

    al = doc.get("allan") or {}
    fs = float(doc.get("fs_hz") or 0.0)
    tau = np.asarray(al.get("tau_s") or [], dtype=np.float64)
    hi = np.asarray([np.nan if v is None else v for v in al.get("ci_high") or []],
                    dtype=np.float64)
    if fs <= 0 or tau.size == 0 or hi.size != tau.size:
        return None
    # where the fitted model lies above the measurement's band, bound the model too: a filter
    # built on the fit must not be safer than the bound
    fitted = np.asarray([np.nan if v is None else v for v in al.get("model_adev") or []],
                        dtype=np.float64)
    if fitted.size == hi.size:
        hi = np.fmax(hi, fitted)
    psd = doc.get("psd") or {}
    upper = None
    if band_hz is not None and psd.get("f_hz"):
        upper = (np.asarray(psd["f_hz"], dtype=np.float64),
                 np.asarray([np.nan if v is None else v for v in psd["ci_high"]],
                            dtype=np.float64))
    try:
        ob = overbound(tau, hi, fs, duration_s=float(doc.get("duration_s") or 0.0) or None,
                       markov=markov, psd=upper, band_hz=band_hz if upper is not None else None)
    except ValueError as exc:
        return {"error": str(exc)}
    return ob.to_dict()


def extend_channel(doc: dict, full: bool = False, seed: int = 0,
                   band_hz: tuple[float, float] | None = None) -> dict:
    """Add ``discrete_model`` with its ``overbound`` (and with ``full`` the report's curves)
    to a channel document."""
    dm = discrete_for_channel(doc)
    doc["discrete_model"] = dm.to_dict() if dm is not None else None
    if doc["discrete_model"] is not None:
        doc["discrete_model"]["overbound"] = overbound_for_channel(doc, band_hz=band_hz)
    if full:
        doc["terms_adev"] = term_curves(doc)
        doc["model_psd"] = model_psd(doc)
        doc["discrete_check"] = discrete_check(dm, doc, seed) if dm is not None else None
    return doc


def record_facts(record) -> dict:
    """The record's facts for the report: device, rate, duration, gaps, drops, temperature."""
    md = dict(getattr(record, "metadata", {}) or {})
    series = list((getattr(record, "channels", {}) or {}).values())
    facts: dict = {}
    if md.get("device"):
        facts["device"] = md["device"]
    if series:
        first = series[0]
        facts["fs_hz"] = float(first.fs_hz)
        facts["n_samples"] = int(first.n_samples)
        facts["duration_s"] = float(first.duration_s)
        segments = max(len(s.segment_starts) for s in series)
        facts["segments"] = int(segments)
        facts["gaps"] = int(segments - 1)
    dropped = {k: v for k, v in md.items() if "drop" in k.lower()}
    if dropped:
        facts["dropped"] = ", ".join(f"{v} ({k})" for k, v in dropped.items())
    temp = getattr(record, "temperature", None)
    if temp is not None and int(getattr(temp, "n_samples", 0)) > 0:
        v = np.asarray(temp.values, dtype=np.float64)
        v = v[np.isfinite(v)]
        facts["temperature_range_degC"] = [float(v.min()), float(v.max())] if v.size else None
    else:
        facts["temperature_range_degC"] = None
    facts["metadata"] = {k: v for k, v in md.items() if k not in dropped and k != "device"}
    facts["warnings"] = list(getattr(record, "warnings", []) or [])
    return facts


REPORT_ONLY_KEYS = ("terms_adev", "model_psd", "discrete_check", "suggestions")


def suggestions(record, key: str, model=DEFAULT_MODEL) -> list[dict]:
    """The diagnosis of one channel of ``record`` for ``model``: ranked suggestion documents."""
    from imunoise.analysis.diagnosis import diagnose

    series = record.series(key)
    temp = getattr(record, "temperature", None)
    temperature = None
    if temp is not None and temp.n_samples >= 2:
        temperature = (temp.t0_s + np.arange(temp.n_samples) / temp.fs_hz, temp.values)
    dx = diagnose(series.values, series.fs_hz, list(model),
                  segment_starts=series.segment_starts, t0_s=series.t0_s,
                  temperature=temperature, units=series.units)
    return [s.to_dict() for s in dx.suggestions]


def complete_document(doc: dict, record, full: bool = False, seed: int = 0,
                      band_hz: tuple[float, float] | None = None, diagnose: bool = True) -> dict:
    """Add ``discrete_model`` (and, with ``full``, the report's curves, the diagnosis and the
    record's facts) to a fitted ``analyze`` document; ``band_hz`` is the PSD band the
    over-bounding model must also cover; ``diagnose=False`` leaves the diagnosis out (a record
    analysed without holding its samples)."""
    for key, ch in doc.get("channels", {}).items():
        extend_channel(ch, full=full, seed=seed, band_hz=band_hz)
        if full and ch.get("model") and not diagnose:
            ch.setdefault("warnings", []).append(
                "no diagnosis: the record was analysed without holding its samples (too long); "
                "imunoise diagnose on the channel gives it")
        elif full and ch.get("model"):
            try:
                ch["suggestions"] = suggestions(record, key)
            except ValueError as exc:  # a record too short for a refit with one more term
                ch.setdefault("warnings", []).append(f"no diagnosis: {exc}")
    if full:
        doc["record"] = record_facts(record)
    return doc


def without_report_extras(doc: dict) -> dict:
    """The document as ``analyze --json`` prints it: no report-only curves or facts."""
    out = {k: v for k, v in doc.items() if k != "record"}
    out["channels"] = {k: {kk: vv for kk, vv in ch.items() if kk not in REPORT_ONLY_KEYS}
                       for k, ch in doc.get("channels", {}).items()}
    return out
