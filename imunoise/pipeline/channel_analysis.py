"""Channel analysis of a record in memory: Allan deviation, PSD and the default model fit.

What ``imunoise analyze`` computes for every selected channel (:func:`analyze_record`); the
streamed analysis of a file too long to hold
(:mod:`imunoise.pipeline.streamed_analysis`) fills the same :class:`ChannelAnalysis`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from imunoise.analysis.default_model import DEFAULT_MODEL, DEFAULT_MODEL_TEXT
from imunoise.core.record import Record
from imunoise.core.series import ChannelSeries
from imunoise.core.units import CI95
from imunoise.progress import progress_bar

if TYPE_CHECKING:  # scipy-backed modules load only when an analysis runs
    from imunoise.analysis.psd import PsdEstimate

__all__ = ["DEFAULT_MODEL", "ChannelAnalysis", "allan_curve", "analyze_record", "psd_estimate"]


# Samples (summed over channels) above which the work takes more than a few seconds.
_PROGRESS_SAMPLES = 2_000_000


@dataclass
class ChannelAnalysis:
    """What ``analyze`` computed for one channel."""

    key: str
    series: ChannelSeries
    allan: Any | None = None  # imunoise.analysis.allan.AllanCurve
    psd: PsdEstimate | None = None
    fit: Any | None = None  # imunoise.analysis.fit.FitResult of DEFAULT_MODEL
    warnings: list[str] = field(default_factory=list)


def _fit(out: ChannelAnalysis) -> None:
    from imunoise.analysis.fit import fit_allan
    from imunoise.analysis.terms import TermError

    if out.allan is None:
        return
    try:
        out.fit = fit_allan(out.allan, DEFAULT_MODEL_TEXT)
    except (TermError, ValueError, np.linalg.LinAlgError) as exc:
        out.warnings.append(f"no model fit: {exc}")


def allan_curve(series: ChannelSeries) -> Any:
    """The overlapping Allan deviation ``analyze`` reports for a channel
    (``imunoise.analysis.allan.AllanCurve``): octave taus, no difference across a gap, 95 %
    intervals.

    Raises ValueError for a series too short for any tau."""
    from imunoise.analysis.allan import oadev

    return oadev(series.values, series.fs_hz, m="octave", segment_starts=series.segment_starts,
                 ci=CI95)


def psd_estimate(series: ChannelSeries) -> PsdEstimate:
    """The one-sided PSD ``analyze`` reports for a channel: log-spaced points, segments of the
    length the longest gap-free stretch allows, 95 % intervals.

    Raises ValueError for a series too short for a PSD."""
    from imunoise.analysis.psd import default_nperseg, log_psd

    bounds = np.append(series.segment_starts, series.n_samples)
    longest = int(np.max(np.diff(bounds))) if series.n_samples else 0
    return log_psd(series.values, series.fs_hz, segment_starts=series.segment_starts,
                   ci=CI95, nperseg=default_nperseg(longest))


def _allan(series: ChannelSeries, out: ChannelAnalysis) -> None:
    try:
        out.allan = allan_curve(series)
    except ValueError as exc:
        out.warnings.append(f"no Allan deviation: {exc}")


def _psd(series: ChannelSeries, out: ChannelAnalysis) -> None:
    try:
        out.psd = psd_estimate(series)
    except ValueError as exc:
        out.warnings.append(f"no PSD: {exc}")


def _held(series: ChannelSeries, out: ChannelAnalysis) -> None:
    from imunoise.analysis.evidence.held import held_samples, warning_text

    warning = warning_text(held_samples(series.segments(), series.fs_hz, units=series.units))
    if warning:
        out.warnings.append(warning)


def analyze_record(record: Record, keys: list[str], show_progress: bool | None = None
                   ) -> list[ChannelAnalysis]:
    """Allan deviation and PSD of the selected channels of a record."""
    total = sum(record.series(k).n_samples for k in keys)
    if show_progress is None:
        show_progress = total > _PROGRESS_SAMPLES
    results = []
    with progress_bar(show_progress) as bar:
        task = bar.add_task("analysing", total=2 * len(keys))
        for key in keys:
            series = record.series(key)
            out = ChannelAnalysis(key=key, series=series)
            bar.update(task, description=f"{key}: Allan deviation")
            _held(series, out)
            _allan(series, out)
            _fit(out)
            bar.advance(task)
            bar.update(task, description=f"{key}: PSD")
            _psd(series, out)
            bar.advance(task)
            results.append(out)
    return results
