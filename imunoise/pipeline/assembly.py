"""The whole JSON documents of ``analyze``, ``fit`` and ``diagnose`` (of one file, and of several
files of one unit), as the command line prints
them and the Python API returns them: the per-channel documents of
:mod:`imunoise.pipeline.documents` completed with what needs the whole record (the error parts
of a fit, the coherence with the other channels, the own noise after subtraction).

One place builds them, so that ``imunoise.fit(channel).document()`` and ``imunoise fit --json``
cannot drift apart.
"""

from __future__ import annotations

from typing import Any

from imunoise.core.record import Record
from imunoise.pipeline import channel_extras, cross_channel
from imunoise.pipeline.documents import analysis_json, diagnosis_json, fit_json
from imunoise.pipeline.fitting import fit_error_parts


def analysis_document(path: str, record: Record, results: list, *, streamed: bool = False,
                      subtract: bool = False, full: bool = False,
                      band_hz: tuple[float, float] | None = None,
                      pending: cross_channel.PendingCoherence | None = None
                      ) -> tuple[dict, dict | None, dict | None]:
    """``analyze``'s document with its ``coherence`` (and each channel's ``own`` with
    ``subtract``): ``(document, coherence, residuals)``. ``full`` keeps what only the HTML
    report shows (and diagnoses the own noise); a streamed analysis has no coherence.
    ``pending``: the same channels' coherence, started before the channels were analysed
    (:class:`imunoise.pipeline.cross_channel.PendingCoherence`)."""
    doc = channel_extras.complete_document(analysis_json(path, record, results), record,
                                           full=full, band_hz=band_hz, diagnose=not streamed)
    if streamed:
        return doc, None, None
    suggestions = {k: ch["suggestions"] for k, ch in doc["channels"].items()
                   if ch.get("suggestions")}
    coherence, residuals = cross_channel.coherence_document(
        record, [r.key for r in results], suggestions=suggestions or None, subtract=subtract,
        pending=pending)
    if coherence is not None:
        doc["coherence"] = coherence
    if residuals:
        cross_channel.add_own(doc, record, residuals, diagnose=full)
    return doc, coherence, residuals


def printed_analysis(doc: dict[str, Any]) -> dict[str, Any]:
    """What ``analyze --json`` prints of an :func:`analysis_document`: without the report's
    extras (the own noise's diagnosis included)."""
    out = channel_extras.without_report_extras(doc)
    for ch in out["channels"].values():
        if "own" in ch:
            ch["own"] = {k: v for k, v in ch["own"].items() if k != "suggestions"}
    return out


def fit_document(record: Record, key: str, model_text: str, result: Any, curve: Any
                 ) -> tuple[dict[str, Any], dict[str, Any]]:
    """``fit``'s document of a fit of ``model_text`` to channel ``key``, with the PSD, hold-out
    and time-domain parts of its error: ``(document, parts)``."""
    parts = fit_error_parts(record, key, model_text, result)
    doc = fit_json(record, key, result, curve, parts)
    if any(t.term == "chain_filter" for t in result.terms):
        _add_chain_shape(doc)
    return doc, parts[1]


def _add_chain_shape(doc: dict[str, Any]) -> None:
    """``doc["chain_shape"]``: the response the record's other channels measure, which
    ``chain_filter`` applies (:func:`imunoise.analysis.chain_shape.current`), where there is
    one."""
    from imunoise.analysis.chain_shape import current

    shape = current()
    if shape is not None:
        doc["chain_shape"] = shape.to_dict()


def diagnosis_document(record: Record, key: str, diagnosis: Any, group: list[str],
                       skip_s: float = 0.0, split_s: list[float] | tuple[float, ...] = (),
                       pending: cross_channel.PendingCoherence | None = None
                       ) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """``diagnose``'s document, its lines and resonances judged against the other channels of
    ``group`` (``key``'s time base before the cuts): ``(document, coherence)``. ``pending``:
    the coherence started before the diagnosis
    (:func:`imunoise.pipeline.cross_channel.start_channel_coherence`)."""
    coherence = cross_channel.channel_coherence(record, key, diagnosis, group, skip_s,
                                                list(split_s), pending)
    doc = diagnosis_json(record, key, diagnosis)
    _add_chain_shape(doc)
    if coherence is not None:
        doc["coherence"] = coherence
        cross_channel.mark_origins(doc["suggestions"], coherence, key)
    return doc, coherence


def replicates_warnings(records: list[tuple[str, Record]], key: str) -> list[str]:
    """The warnings of several runs of one unit: what reading each record found, prefixed with
    its label, and a note where the runs were sampled at different rates (a filter's taps
    and a Markov term near the sample period mean different things at each rate)."""
    warnings = [f"{label}: {w}" for label, record in records for w in record.warnings]
    rates = {label: float(record.series(key).fs_hz) for label, record in records}
    if len({round(r, 9) for r in rates.values()}) > 1:
        listed = ", ".join(f"{r:g} Hz in {label}" for label, r in rates.items())
        warnings.append(f"the runs' sample rates differ ({listed}): shapes counted in samples "
                        f"(a filter's taps) are compared across different sample periods")
    return warnings


def replicates_document(records: list[tuple[str, Record]], key: str, model_text: str,
                        result: Any) -> dict[str, Any]:
    """``diagnose FILE1 FILE2 ... --json``'s document of channel ``key`` of ``records``
    (``(label, record)`` per run) and their
    :class:`imunoise.analysis.replicates.ReplicateResult`."""
    return {"channel": key, "units": records[0][1].series(key).units, "model": model_text,
            "replicates": result.to_dict(), "warnings": replicates_warnings(records, key)}
