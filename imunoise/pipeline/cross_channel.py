"""The cross-channel part of ``analyze`` and ``diagnose`` (docs/environment.md): the coherence
of a record's channels that share one time base, the lines and resonances of the diagnosis
classified as common (environment) or own, and, with ``--subtract-common``, each channel's own
noise analysed beside the raw one."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from imunoise.core.record import TEMPERATURE_KEY, Record
from imunoise.core.series import ChannelSeries

OWN_TAU_S = 1.0
"""Averaging time at which the own white level is read (as the text output reads N)."""


def _signature(s: ChannelSeries) -> tuple:
    return (float(s.fs_hz), int(s.n_samples), tuple(int(v) for v in s.segment_starts),
            round(float(s.t0_s), 6))


def time_base_group(series: dict[str, ChannelSeries], keys: list[str]) -> list[str]:
    """The largest set of ``keys`` whose series share one time base (same rate, samples,
    gap-free segments and start); the temperature is never one of them."""
    groups: dict[tuple, list[str]] = {}
    for k in keys:
        if k != TEMPERATURE_KEY and k in series:
            groups.setdefault(_signature(series[k]), []).append(k)
    return max(groups.values(), key=len, default=[])


def comparison_group(series: dict[str, ChannelSeries], key: str) -> list[str]:
    """The channels ``key`` is compared with (``key`` first): those on its time base, then
    those of other devices, which :func:`coherence_document` brings onto its time base."""
    sig = _signature(series[key])
    same = [k for k, v in series.items() if k != key and _signature(v) == sig]
    return [key] + same + [k for k in series if k != key and k not in same]


def _windowed_group(record: Record, key: str, group: list[str], skip_s: float,
                    split_s: list[float] | tuple[float, ...]) -> dict[str, ChannelSeries]:
    """The series of ``group`` cut by ``--skip``/``--split`` as ``key`` was (``key``'s own
    series is already cut in the record)."""
    return {k: (record.channels[k] if k == key or not (skip_s or split_s)
                else record.channels[k].windowed(skip_s, list(split_s))) for k in group}


def start_channel_coherence(record: Record, key: str, group: list[str], skip_s: float = 0.0,
                            split_s: list[float] | tuple[float, ...] = ()
                            ) -> PendingCoherence | None:
    """The coherence :func:`channel_coherence` needs, started in the background now (None
    without another channel); pass the result to it as ``pending``."""
    if len(group) < 2:
        return None
    series = _windowed_group(record, key, group, skip_s, split_s)
    return PendingCoherence(group, coherence_inputs(record, group, series))


def channel_coherence(record: Record, key: str, diagnosis: Any, group: list[str],
                      skip_s: float = 0.0, split_s: list[float] | tuple[float, ...] = (),
                      pending: PendingCoherence | None = None) -> dict[str, Any] | None:
    """One channel's diagnosis (its suggestions and its spectral-line evidence) judged against
    the other channels of ``group`` (its time base before ``--skip``/``--split``, which cut
    them all alike): its suggestions' ``why`` gets common or own; returns the coherence
    document (None without another channel). ``pending``: the coherence started by
    :func:`start_channel_coherence` with the same arguments."""
    if len(group) < 2:
        return None
    series = _windowed_group(record, key, group, skip_s, split_s)
    doc, _ = coherence_document(record, group, suggestions={key: diagnosis}, only=[key],
                                series=series, pending=pending)
    return doc


def mark_origins(suggestions: list[dict[str, Any]], coherence: dict[str, Any] | None,
                 channel: str) -> None:
    """Give each line or resonance suggestion document of ``channel`` the ``origin`` its
    classification found (``common``, ``own`` or ``mixed``)."""
    found = [c for c in (coherence or {}).get("classification", []) if c["channel"] == channel]
    for sug in suggestions:
        key = {"sinusoid": "f", "resonance": "f0"}.get(sug.get("term"))
        f = (sug.get("params") or {}).get(key) if key else None
        for c in found:
            if f is not None and c["term"] == sug["term"] \
                    and abs(c["f_hz"] - f) <= 1e-3 * f + 1e-9:
                sug["origin"] = c["origin"]


def temperature_on(record: Record, series: ChannelSeries) -> np.ndarray | None:
    """The temperature interpolated onto the samples of ``series`` (nominal times), or None
    when the record has none or it does not cover the series."""
    temp = record.temperature
    if temp is None or temp.n_samples < 2 or series.n_samples < 2 or temp.fs_hz <= 0:
        return None
    tt = temp.t0_s + np.arange(temp.n_samples) / temp.fs_hz
    ti = series.t0_s + np.arange(series.n_samples) / series.fs_hz
    if tt[0] > ti[0] + 1.0 / temp.fs_hz or tt[-1] < ti[-1] - 1.0 / temp.fs_hz:
        return None
    return np.interp(ti, tt, temp.values)


@dataclass
class CoherenceInputs:
    """What the coherence of a record's channels is computed from: the channels on one time
    base (``values``, the temperature joining them when it covers them), the series whose
    time base they share (``first``), and how channels of other devices were aligned."""

    values: dict[str, np.ndarray]
    first: ChannelSeries
    notes: list[str]
    aligned: Any = None

    def coherence(self) -> Any:
        """The coherence of ``values`` as :func:`imunoise.analysis.cross_channel.
        cross_channel_view` computes it by default (its Welch cross-spectra, their
        log-frequency coherence)."""
        from imunoise.analysis.coherence import cross_spectra, log_coherence

        x = np.column_stack([np.asarray(v, dtype=np.float64) for v in self.values.values()])
        return log_coherence(cross_spectra(x, self.first.fs_hz, list(self.values),
                                           segment_starts=self.first.segment_starts))


def coherence_inputs(record: Record, keys: list[str],
                     series: dict[str, ChannelSeries] | None = None
                     ) -> CoherenceInputs | None:
    """The channels of ``keys`` that share one time base (those of other devices brought onto
    it), with the record's temperature where it covers them; None with fewer than two."""
    series = series if series is not None else record.channels
    group = time_base_group(series, keys)
    notes: list[str] = []
    aligned = None
    others = [k for k in keys if k not in group and k != TEMPERATURE_KEY and k in series]
    if others and group:
        # other devices, sampled at their own instants: onto the largest group's times
        from imunoise.analysis.alignment import align

        aligned = align({k: series[k] for k in group + others}, group[0])
        if aligned.interpolated:
            series = {**series, **aligned.series}
            group = [k for k in keys if k in aligned.series]
            notes.append(aligned.note())
        else:
            aligned = None
    if len(group) < 2:
        return None
    first = series[group[0]]
    values = {k: series[k].values for k in group}
    temp = temperature_on(record, first)
    if temp is not None:
        values[TEMPERATURE_KEY] = temp
    return CoherenceInputs(values, first, notes, aligned)


class PendingCoherence:
    """The coherence of the channels ``keys`` (their :func:`coherence_inputs`), computed in a
    background process (:class:`imunoise.pipeline.workers.Background`) while the caller
    fits; hand it to :func:`coherence_document` (``pending=``) once the suggestions to
    classify are known."""

    def __init__(self, keys: list[str], inputs: CoherenceInputs | None) -> None:
        from imunoise.pipeline.workers import Background

        self.keys = list(keys)
        self.inputs = inputs
        self._job = Background(_coherence_or_error, inputs) if inputs is not None else None

    def coherence(self) -> Any:
        """The coherence (raises the estimate's ValueError, e.g. a record too short)."""
        assert self._job is not None  # only asked for with inputs
        co = self._job.result()
        if isinstance(co, ValueError):
            raise co
        return co


def _coherence_or_error(inputs: CoherenceInputs) -> Any:
    """The coherence, or the ValueError that says why there is none (returned, so that the
    background process sends it back rather than failing)."""
    try:
        return inputs.coherence()
    except ValueError as exc:
        return exc


def coherence_document(record: Record, keys: list[str],
                       suggestions: dict[str, list[Any]] | None = None,
                       subtract: bool = False, only: list[str] | None = None,
                       series: dict[str, ChannelSeries] | None = None,
                       pending: PendingCoherence | None = None
                       ) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """``(coherence document or None, residuals)`` of the channels ``keys`` select
    (:func:`imunoise.analysis.cross_channel.cross_channel_view`), the record's temperature
    joining them when it covers them. None with fewer than two channels on one time base; a
    document with only ``warnings`` when the estimate fails (a record too short).

    ``suggestions`` (channel -> suggestion dicts or objects) get the verdict in their
    ``why``; ``only`` limits the channels classified; ``series`` replaces the record's own
    (a windowed copy); ``pending`` is the same channels' coherence started earlier
    (:class:`PendingCoherence` of the same ``keys`` and ``series``; one started for other
    keys is left unused)."""
    from imunoise.analysis.cross_channel import cross_channel_view

    if pending is not None and pending.keys != list(keys):
        pending = None  # started for other channels (one dropped from the analysis)
    inputs = pending.inputs if pending is not None else coherence_inputs(record, keys, series)
    if inputs is None:
        return None, {}
    first, aligned = inputs.first, inputs.aligned
    try:
        coherence = pending.coherence() if pending is not None else None
        doc, residuals = cross_channel_view(
            inputs.values, first.fs_hz, segment_starts=first.segment_starts,
            suggestions=suggestions, subtract=subtract, coherence=coherence,
            only=[k for k in inputs.values if k != TEMPERATURE_KEY
                  and (only is None or k in only)])
    except ValueError as exc:
        return {"warnings": [f"no coherence: {exc}"]}, {}
    if inputs.notes:
        for sub in residuals.values():  # the residuals lie on the aligned samples
            sub.segment_starts, sub.t0_s = first.segment_starts, first.t0_s
        doc.setdefault("notes", []).extend(inputs.notes)
        doc["aligned"] = {"reference": aligned.reference, "interpolated": aligned.interpolated,
                          "kept_share": aligned.kept_share}
    apart = [k for k in keys if k not in inputs.values and k != TEMPERATURE_KEY]
    if apart:
        doc["not_compared"] = apart
        doc.setdefault("warnings", []).append(
            f"not compared (another time base): {', '.join(apart)}")
    return doc, residuals


def own_series(raw: ChannelSeries, sub: Any) -> ChannelSeries:
    """The residual of a subtraction as a series of ``raw``'s channel (on the aligned samples
    when the channels were aligned first)."""
    if getattr(sub, "segment_starts", None) is not None:
        return ChannelSeries(raw.name, raw.units, raw.fs_hz, sub.residual, sub.segment_starts,
                             sub.t0_s if sub.t0_s is not None else raw.t0_s)
    return ChannelSeries(raw.name, raw.units, raw.fs_hz, sub.residual, raw.segment_starts,
                         raw.t0_s)


def own_channel_json(record: Record, key: str, sub: Any) -> dict[str, Any]:
    """The ``analyze`` channel document of ``key``'s residual after subtraction, with the
    subtraction's summary and error and the own white level at :data:`OWN_TAU_S`."""
    from imunoise.analysis.default_model import DEFAULT_MODEL_TEXT
    from imunoise.analysis.fit import fit_allan
    from imunoise.analysis.terms import TermError
    from imunoise.pipeline.channel_analysis import allan_curve, psd_estimate
    from imunoise.pipeline.documents import channel_json, fit_fields, number

    raw = record.series(key)
    own = own_series(raw, sub)
    warnings: list[str] = []
    curve = psd = fit = None
    try:
        curve = allan_curve(own)
        fit = fit_allan(curve, DEFAULT_MODEL_TEXT)
    except (TermError, ValueError, np.linalg.LinAlgError) as exc:
        warnings.append(f"no own-noise fit: {exc}")
    try:
        psd = psd_estimate(own)
    except ValueError as exc:
        warnings.append(f"no own-noise PSD: {exc}")
    doc = channel_json(own, curve, psd=psd, include_psd=True, warnings=warnings, channel=key,
                       **(fit_fields(fit, curve) if fit is not None and curve is not None
                          else {}))
    doc["subtraction"] = sub.to_dict()
    try:
        level, (lo, hi) = sub.white_level(raw.fs_hz, OWN_TAU_S,
                                          segment_starts=own.segment_starts)
        doc["white_level"] = {"tau_s": OWN_TAU_S, "N": number(level),
                              "ci": [number(lo), number(hi)],
                              "what": "ADEV(tau) sqrt(tau) of the residual; the interval's "
                                      "lower end allows for the references' noise passed in"}
    except ValueError:
        pass
    return doc


def add_own(doc: dict[str, Any], record: Record, residuals: dict[str, Any],
            diagnose: bool = False) -> None:
    """Put each channel's own-noise document under ``channels[key]["own"]``; with
    ``diagnose`` (the report) also the diagnosis of the residual under its ``suggestions``."""
    for key, sub in residuals.items():
        if key not in doc.get("channels", {}):
            continue
        own = own_channel_json(record, key, sub)
        if diagnose and own.get("model"):
            own["suggestions"] = _own_suggestions(record, key, sub.residual)
        doc["channels"][key]["own"] = own


def _own_suggestions(record: Record, key: str, residual: np.ndarray) -> list[dict[str, Any]]:
    """The diagnosis of a channel's residual for the default model (as the raw channel's)."""
    from imunoise.analysis.default_model import DEFAULT_MODEL
    from imunoise.analysis.diagnosis import diagnose

    raw = record.series(key)
    try:
        dx = diagnose(residual, raw.fs_hz, list(DEFAULT_MODEL),
                      segment_starts=raw.segment_starts, t0_s=raw.t0_s, units=raw.units)
    except ValueError:
        return []
    return [s.to_dict() for s in dx.suggestions]


def coherence_lines(co: dict[str, Any] | None) -> list[str]:
    """The cross-channel view for the text output."""
    if not co:
        return []
    if not co.get("pairs"):
        return [f"coherence: {w}" for w in co.get("warnings", [])]
    msc = np.asarray(co["msc"], dtype=float)
    f = np.asarray(co["f_hz"], dtype=float)
    fam = np.asarray(co["threshold_family"], dtype=float)
    lines = [f"coherence between channels (Welch, {co['nperseg']} samples per segment; "
             f"highest value per pair, * = beyond the zero-coherence threshold)"]
    for k, (a, b) in enumerate(co["pairs"]):
        j = int(np.argmax(msc[k]))
        mark = "*" if np.any(msc[k] > fam) else " "
        lines.append(f"  {mark} {a:>14s} - {b:<14s} {msc[k, j]:.3f} at {f[j]:.4g} Hz")
    for c in co.get("classification", []):
        lines.append(f"  {c['channel']} {c['term']} at {c['f_hz']:.4g} Hz: {c['origin']}. "
                     f"{c['why']}")
    for s in co.get("shared_shapes", []):
        lines.append(f"  spectral shape: {s['text']}")
    return lines


def chain_shape_source(record: Record, key: str, group: list[str], whole: ChannelSeries,
                       pending: PendingCoherence | None = None) -> Any:
    """The :class:`imunoise.analysis.chain_shape.ChainSource` of channel ``key``: the response
    it shares with the other channels of ``group``
    (:func:`imunoise.analysis.chain_shape.chain_shape`; None without one), measured when a
    fit first needs it, on the whole record or on either half of it.

    The response is measured on the whole record, ``whole`` being ``key``'s series before
    ``--skip``/``--split``: a cut changes what is fitted, not the chain the samples passed
    through, and a shape measured on the cut record is another estimate (Galaxy S5 accel_z
    cut at 85 s: Allan chi2/dof 1.73 with the whole record's shape, 1.84 with the cut
    one's). ``pending``: the same coherence started in the background (only when nothing
    was cut)."""
    from imunoise.analysis.chain_shape import ChainSource, chain_shape
    from imunoise.analysis.coherence import cross_spectra, log_coherence

    memo: dict[str, Any] = {}

    def inputs() -> CoherenceInputs | None:
        if "inputs" not in memo:
            series = {**{k: record.channels[k] for k in group}, key: whole}
            memo["inputs"] = coherence_inputs(record, group, series) if len(group) > 1 \
                else None
        return memo["inputs"]

    def measure(k: int | None) -> Any:
        """The shape on the whole record (``k`` None) or on half ``k``."""
        got = inputs()
        if got is None:
            return None
        x = np.column_stack([np.asarray(v, dtype=np.float64) for v in got.values.values()])
        lo, hi = 0, x.shape[0]
        if k is not None:
            mid = x.shape[0] // 2
            lo, hi = (0, mid) if k == 0 else (mid, x.shape[0])
        starts = np.asarray(got.first.segment_starts, dtype=np.int64)
        starts = np.unique(np.concatenate(([0], starts[(starts > lo) & (starts < hi)] - lo)))
        try:
            # the shape needs the spectra and the zero-coherence test, not the intervals
            co = log_coherence(cross_spectra(x[lo:hi], got.first.fs_hz, list(got.values),
                                             segment_starts=starts), intervals=False)
        except ValueError:  # too short for a coherence: no shape to measure
            return None
        return chain_shape(co, key)

    def measure_whole() -> Any:
        if pending is not None and pending.inputs is not None:
            try:
                return chain_shape(pending.coherence(), key)
            except ValueError:
                return None
        return measure(None)

    return ChainSource(measure_whole, measure)


def require_chain_shape(model_names: list[str], key: str) -> None:
    """A usage error when the model names ``chain_filter`` and no other channel of the record
    shares ``key``'s spectral shape (call inside :func:`imunoise.analysis.chain_shape.using`)."""
    from imunoise.analysis.chain_shape import current
    from imunoise.errors import UsageError

    if "chain_filter" in model_names and current() is None:
        raise UsageError(f"chain_filter: no other channel of this record has {key}'s spectral "
                         f"shape without a signal in common, so there is no shared response "
                         f"to measure (imunoise analyze lists shared shapes)")
