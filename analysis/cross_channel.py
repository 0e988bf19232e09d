"""The cross-channel view of a record: coherence of every pair, the lines classified as common
or own, and (on request) each channel's own noise after the common part is removed.

This is what ``analyze --json`` reports under ``coherence`` and the report and the dashboard
draw. Channels are compared only when they share one time base (same rate, same number of
samples, same gap-free segments); SI units.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imunoise.analysis.coherence import DEFAULT_ALPHA, Coherence, cross_spectra, log_coherence
from imunoise.analysis.environment import (
    SpectralFeature,
    annotate,
    channel_device,
    classify,
    features_from_diagnosis,
)
from imunoise.analysis.hat import sensors_document
from imunoise.analysis.shared_shape import annotate_shapes, shared_shapes
from imunoise.analysis.subtraction import Subtraction, subtract_common

MAX_LINES_PER_CHANNEL = 5
"""Lines of the spectral evidence classified per channel when no diagnosis is given."""


def evidence_features(name: str, values: np.ndarray, fs_hz: float,
                      segment_starts: np.ndarray | None = None,
                      alpha: float = DEFAULT_ALPHA) -> list[SpectralFeature]:
    """The significant lines of one channel's spectral-line evidence (strongest first)."""
    from imunoise.analysis.evidence import spectral_lines

    starts = np.zeros(1, dtype=np.int64) if segment_starts is None \
        else np.asarray(segment_starts, dtype=np.int64)
    bounds = np.append(starts, len(values))
    segments = [values[a:b] for a, b in zip(bounds[:-1], bounds[1:], strict=True) if b > a]
    try:
        found = spectral_lines(segments, fs_hz, alpha=alpha)
    except ValueError:
        return []
    return features_from_diagnosis(name, {"findings": [found]})[:MAX_LINES_PER_CHANNEL]


def cross_channel_view(values: dict[str, np.ndarray], fs_hz: float, *,
                       segment_starts: np.ndarray | None = None,
                       suggestions: dict[str, list[Any]] | None = None,
                       nperseg: int | None = None, points_per_decade: float = 10.0,
                       alpha: float = DEFAULT_ALPHA, ci: float = 0.95,
                       subtract: bool = False, only: list[str] | None = None,
                       coherence: Coherence | None = None
                       ) -> tuple[dict[str, Any], dict[str, Subtraction]]:
    """Coherence, classification and (``subtract``) own-noise residuals of a record's channels.

    Args:
        values: channel name -> samples (SI), all on one time base.
        fs_hz: sampling rate, Hz.
        segment_starts: gap-free segment starts shared by the channels.
        suggestions: channel -> its diagnosis's suggestions (objects or dicts), or the
            :class:`~imunoise.analysis.diagnosis.Diagnosis` itself (its spectral-line evidence
            then joins); their lines and resonances are classified, and each one's ``why``
            gets the verdict appended (dicts also an ``origin``). A channel without
            suggestions has its spectral-line evidence searched instead.
        nperseg: Welch length (default :func:`imunoise.analysis.coherence.default_nperseg`).
        points_per_decade: log-frequency points per decade of the coherence view.
        alpha: level of the zero-coherence tests.
        ci: confidence level of the intervals.
        subtract: also remove from each channel what the others explain.
        only: classify (and subtract) these channels only (default: every channel); the
            others still serve as partners and references.
        coherence: the coherence of these ``values``, when already computed
            (:func:`log_coherence` of their :func:`cross_spectra`, with the same
            ``nperseg``, ``segment_starts``, ``points_per_decade``, ``ci`` and ``alpha``).

    ``shared_shapes`` lists the channels whose spectra have one shape and no coherence (a
    filter of the chain they pass through, :mod:`imunoise.analysis.shared_shape`).

    Channels of several devices with one name (``imu1/gyro_x``, ``imu2/gyro_x``) also give
    ``sensors``: the three-cornered hat of three, the two-sensor bounds of two
    (:func:`imunoise.analysis.hat.sensors_document`).

    Returns:
        ``(document, residuals)``: the JSON-ready ``coherence`` document and, with
        ``subtract``, each channel's :class:`~imunoise.analysis.subtraction.Subtraction`.
    """
    names = list(values)
    if len(names) < 2:
        raise ValueError("the cross-channel view needs at least two channels on one time base")
    lengths = {len(v) for v in values.values()}
    if len(lengths) != 1:
        raise ValueError("the channels do not share one time base (different lengths)")
    x = np.column_stack([np.asarray(values[c], dtype=np.float64) for c in names])
    if coherence is None:
        cs = cross_spectra(x, fs_hz, names, nperseg=nperseg, segment_starts=segment_starts)
        co = log_coherence(cs, points_per_decade=points_per_decade, ci=ci, alpha=alpha)
    else:
        co = coherence
        if co.cross is None or tuple(co.channels) != tuple(names) \
                or (co.ci, co.alpha) != (ci, alpha):
            raise ValueError(f"the coherence given is of {list(co.channels)} at ci {co.ci}, "
                             f"alpha {co.alpha}, not of {names} at ci {ci}, alpha {alpha}")
        cs = co.cross
    features: list[SpectralFeature] = []
    chosen = names if only is None else [c for c in names if c in only]
    for k, c in enumerate(names):
        if c not in chosen:
            continue
        if suggestions is not None and c in suggestions:
            features += features_from_diagnosis(c, suggestions[c])
        else:
            features += evidence_features(c, x[:, k], fs_hz, segment_starts, alpha)
    means = {c: float(np.mean(x[:, k])) for k, c in enumerate(names)}
    origins = classify(features, cs, means=means, alpha=alpha, ci=ci)
    listed = {c: v if isinstance(v, list) else list(getattr(v, "suggestions", []))
              for c, v in (suggestions or {}).items()}
    if listed:
        annotate(listed, origins)
    doc = co.to_dict()
    doc["classification"] = [o.to_dict() for o in origins]
    shapes = shared_shapes(co)
    doc["shared_shapes"] = [s.to_dict() for s in shapes]
    if listed:
        annotate_shapes(listed, shapes)
    shared = [c for c in names if channel_device(c)]
    bases = [c[len(channel_device(c)) + 1:] for c in shared]
    if any(bases.count(b) >= 2 for b in bases):
        # several sensors of one kind on the bench: the hat (three) or the bounds (two)
        doc["sensors"] = sensors_document({c: x[:, names.index(c)] for c in shared}, fs_hz,
                                          segment_starts=segment_starts, ci=ci)
    residuals: dict[str, Subtraction] = {}
    if subtract:
        for c in chosen:
            residuals[c] = subtract_common(x, fs_hz, names, c, segment_starts=segment_starts,
                                           alpha=alpha, cross=cs)
        doc["subtraction"] = {c: r.to_dict() for c, r in residuals.items()}
    return doc, residuals
