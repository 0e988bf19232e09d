"""What the Python API returns: a recording and its channels, an Allan curve, a PSD, a fitted
model, a diagnosis and several runs of one unit.

Each result gives the command line's JSON document (``document()``, and ``to_json()`` as
text), a table or a labelled array where one is natural (``to_pandas()``, ``to_xarray()``,
with the ``notebook`` extra) and a plot (``plot()``, with the ``plot`` extra). Numbers are in
SI units (rad/s, m/s^2, s, Hz); a unit is labelled wherever one is shown.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np

from imunoise.api import plotting
from imunoise.core.record import Record
from imunoise.core.series import ChannelSeries
from imunoise.extras import require
from imunoise.pipeline import documents
from imunoise.pipeline.reading import select

if TYPE_CHECKING:
    from imunoise.analysis.allan import AllanCurve
    from imunoise.analysis.diagnosis import Diagnosis as AnalysisDiagnosis
    from imunoise.analysis.fit import FitResult
    from imunoise.analysis.psd import PsdEstimate
    from imunoise.analysis.replicates import ReplicateResult


def _pandas() -> Any:
    require("notebook", "to_pandas()", ("pandas",))
    import pandas

    return pandas


def _xarray() -> Any:
    require("notebook", "to_xarray()", ("xarray",))
    import xarray

    return xarray


class Recording:
    """A recording read as ``imunoise analyze`` reads it: the file's timing model (rate, gaps,
    re-timed jitter) and, unless read with ``static="all"``, only the stretches where the
    sensor rested.

    ``rec["gyro_x"]`` (or ``rec["/imu:gyro_x"]``) is a :class:`Channel`; iterating gives every
    IMU channel. ``warnings`` are the reader's and the motion detection's one-line notes,
    ``facts`` what they found (``timing``, ``motion``).
    """

    def __init__(self, path: str, record: Record) -> None:
        self.path = path
        self.record = record

    @property
    def channels(self) -> list[str]:
        """Keys of the IMU channels, as ``analyze`` lists them."""
        return select(self.record, [])

    @property
    def warnings(self) -> list[str]:
        return list(self.record.warnings)

    @property
    def facts(self) -> dict[str, Any]:
        return dict(self.record.facts)

    @property
    def metadata(self) -> dict[str, str]:
        return dict(self.record.metadata)

    def __getitem__(self, selector: str) -> Channel:
        """The channel ``selector`` names (``gyro_x``, ``TOPIC:gyro_x``); an unknown one raises
        :class:`imunoise.errors.UsageError` (a ValueError) listing the valid channels."""
        return Channel(self, select(self.record, [selector])[0])

    def __iter__(self) -> Iterator[Channel]:
        return (Channel(self, key) for key in self.channels)

    def __len__(self) -> int:
        return len(self.channels)

    def __repr__(self) -> str:
        keys = self.channels
        first = self.record.series(keys[0]) if keys else None
        span = (f", {first.duration_s / 3600:.3g} h analysed at {first.fs_hz:g} Hz"
                if first is not None else "")
        return f"<Recording {self.path!r}: {', '.join(keys)}{span}>"


@dataclass(frozen=True)
class Channel:
    """One channel of a :class:`Recording` (its samples are ``series.values``, SI units).

    ``skip_s`` and ``split_s`` are the cuts of :meth:`window` (``--skip``, ``--split``)."""

    recording: Recording
    key: str
    skip_s: float = 0.0
    split_s: tuple[float, ...] = ()
    uncut: Recording | None = None  # the recording before the cuts (the others' time base)

    def window(self, skip_s: float = 0.0, split_s: tuple[float, ...] | list[float] = ()
               ) -> Channel:
        """The channel without its first ``skip_s`` seconds (a warm-up) and cut into separate
        segments at ``split_s`` (seconds from its first sample; bias steps), as ``--skip`` and
        ``--split`` of ``fit`` and ``diagnose`` do: what a suggestion's ``apply.args`` ask.
        The recording itself is left as it is."""
        import dataclasses

        from imunoise.pipeline.reading import apply_window

        record = dataclasses.replace(self.recording.record,
                                     channels=dict(self.recording.record.channels),
                                     warnings=list(self.recording.record.warnings))
        apply_window(record, self.key, float(skip_s), [float(t) for t in split_s])
        return Channel(Recording(self.recording.path, record), self.key, float(skip_s),
                       tuple(float(t) for t in split_s), self.uncut or self.recording)

    def time_base_group(self) -> list[str]:
        """The channels this one is compared with before the cuts (this one first; other
        devices are brought onto its time base)."""
        from imunoise.pipeline.cross_channel import comparison_group

        return comparison_group((self.uncut or self.recording).record.channels, self.key)

    @property
    def series(self) -> ChannelSeries:
        return self.recording.record.series(self.key)

    @property
    def values(self) -> np.ndarray:
        """The analysed samples (still stretches only, gaps removed), SI units."""
        return self.series.values

    @property
    def fs_hz(self) -> float:
        return float(self.series.fs_hz)

    @property
    def units(self) -> str:
        return self.series.units

    @property
    def duration_s(self) -> float:
        """Analysed duration, s (gaps and motion excluded)."""
        return float(self.series.duration_s)

    def __repr__(self) -> str:
        s = self.series
        cut = f", skip {self.skip_s:g} s" if self.skip_s else ""
        return (f"<Channel {self.key} [{s.units}] {s.n_samples:,} samples at {s.fs_hz:g} Hz, "
                f"{len(s.segment_starts)} segment(s){cut}>")


@dataclass(frozen=True, repr=False)
class AllanResult:
    """An overlapping Allan deviation on octave taus with 95 % intervals (``analyze``'s).

    Attributes:
        curve: the estimate (:class:`imunoise.analysis.allan.AllanCurve`).
        units: units of the deviation (the channel's).
        channel: the channel it was computed from, or None for an array.
    """

    curve: AllanCurve
    units: str = ""
    channel: Channel | None = None

    @property
    def tau_s(self) -> np.ndarray:
        return np.asarray(self.curve.tau_s)

    @property
    def adev(self) -> np.ndarray:
        return np.asarray(self.curve.dev)

    @property
    def ci_low(self) -> np.ndarray:
        return np.asarray(self.curve.ci_low)

    @property
    def ci_high(self) -> np.ndarray:
        return np.asarray(self.curve.ci_high)

    def document(self) -> dict[str, Any]:
        """The ``allan`` object of the JSON documents (``model_adev`` and ``z`` null: no
        model)."""
        return documents.allan_json(self.curve)

    def to_json(self) -> str:
        return documents.dumps(self.document())

    def to_pandas(self) -> Any:
        """A DataFrame indexed by ``tau_s``: ``adev``, ``ci_low``, ``ci_high``, ``edf``,
        ``n_terms`` (``notebook`` extra)."""
        pd = _pandas()
        c = self.curve
        return pd.DataFrame({"adev": c.dev, "ci_low": c.ci_low, "ci_high": c.ci_high,
                             "edf": c.edf, "n_terms": c.n_terms},
                            index=pd.Index(np.asarray(c.tau_s), name="tau_s"))

    def to_xarray(self) -> Any:
        """A Dataset on the coordinate ``tau_s`` (s), units in the attributes (``notebook``
        extra)."""
        xr = _xarray()
        c = self.curve
        attrs = {"units": self.units}
        return xr.Dataset(
            {name: ("tau_s", np.asarray(v), attrs) for name, v in
             (("adev", c.dev), ("ci_low", c.ci_low), ("ci_high", c.ci_high))} |
            {"edf": ("tau_s", np.asarray(c.edf))},
            coords={"tau_s": ("tau_s", np.asarray(c.tau_s), {"units": "s"})},
            attrs={"ci": float(c.ci), "fs_hz": float(c.fs_hz),
                   "channel": self.channel.key if self.channel else ""})

    def plot(self, ax: Any = None) -> Any:
        """The deviation and its 95 % band on log axes (``plot`` extra); returns the axes."""
        ax = plotting.axes(ax)
        plotting.allan(ax, self.tau_s, self.adev, self.ci_low, self.ci_high, self.units,
                       self.channel.key if self.channel else "measured")
        return ax

    def __repr__(self) -> str:
        i = int(np.argmin(self.adev)) if self.adev.size else 0
        low = (f", minimum {self.adev[i]:.4g} {self.units} at tau {self.tau_s[i]:.4g} s"
               if self.adev.size else "")
        return f"<AllanResult {self.adev.size} taus{low}>"


@dataclass(frozen=True, repr=False)
class PsdResult:
    """A one-sided PSD (units^2/Hz) on log-spaced frequencies with 95 % intervals
    (``analyze``'s).

    Attributes:
        estimate: :class:`imunoise.analysis.psd.PsdEstimate`.
        units: units of the samples (the PSD is in units^2/Hz).
        channel: the channel it was computed from, or None for an array.
    """

    estimate: PsdEstimate
    units: str = ""
    channel: Channel | None = None

    @property
    def f_hz(self) -> np.ndarray:
        return np.asarray(self.estimate.f_hz)

    @property
    def psd(self) -> np.ndarray:
        return np.asarray(self.estimate.psd)

    def document(self) -> dict[str, Any]:
        """The ``psd`` object of the ``analyze`` document."""
        return documents.psd_json(self.estimate)

    def to_json(self) -> str:
        return documents.dumps(self.document())

    def to_pandas(self) -> Any:
        """A DataFrame indexed by ``f_hz``: ``psd``, ``ci_low``, ``ci_high``, ``dof``,
        ``method`` (``notebook`` extra)."""
        pd = _pandas()
        e = self.estimate
        return pd.DataFrame({"psd": e.psd, "ci_low": e.ci_low, "ci_high": e.ci_high,
                             "dof": e.dof, "method": e.method},
                            index=pd.Index(np.asarray(e.f_hz), name="f_hz"))

    def to_xarray(self) -> Any:
        """A Dataset on the coordinate ``f_hz`` (Hz) (``notebook`` extra)."""
        xr = _xarray()
        e = self.estimate
        attrs = {"units": f"({self.units})^2/Hz" if self.units else "1/Hz"}
        return xr.Dataset(
            {name: ("f_hz", np.asarray(v), attrs) for name, v in
             (("psd", e.psd), ("ci_low", e.ci_low), ("ci_high", e.ci_high))} |
            {"dof": ("f_hz", np.asarray(e.dof))},
            coords={"f_hz": ("f_hz", np.asarray(e.f_hz), {"units": "Hz"})},
            attrs={"ci": float(e.ci), "channel": self.channel.key if self.channel else ""})

    def plot(self, ax: Any = None) -> Any:
        """The PSD and its 95 % band on log axes (``plot`` extra); returns the axes."""
        ax = plotting.axes(ax)
        e = self.estimate
        plotting.psd(ax, self.f_hz, self.psd, np.asarray(e.ci_low), np.asarray(e.ci_high),
                     self.units, self.channel.key if self.channel else "measured")
        return ax

    def __repr__(self) -> str:
        return (f"<PsdResult {self.f_hz.size} frequencies, {self.f_hz[0]:.3g} .. "
                f"{self.f_hz[-1]:.3g} Hz>" if self.f_hz.size else "<PsdResult empty>")


def _findings(error: dict[str, Any]) -> list[str]:
    from imunoise.analysis.model_error import holdout_findings

    return holdout_findings(error.get("holdout") or {})


@dataclass(frozen=True, repr=False)
class FitReport:
    """A noise model fitted to an Allan curve, with its 95 % intervals and where it fails.

    Attributes:
        result: :class:`imunoise.analysis.fit.FitResult`.
        curve: the measured curve it was fitted to.
        units: the channel's units.
        channel: the channel, or None for a curve of an array.
    """

    result: FitResult
    curve: AllanCurve
    units: str = ""
    channel: Channel | None = None
    model_text: str = ""

    @property
    def model(self) -> list[dict[str, Any]]:
        """The ``model`` entries of the JSON: term, params (SI), ci95, unresolved."""
        return documents.model_json(self.result)

    @property
    def params(self) -> dict[str, dict[str, float]]:
        """Fitted parameters by term label (``gauss_markov#2`` for a second one), SI units."""
        return {label: dict(t.params) for label, t in
                zip(self.result.labels, self.result.terms, strict=True)}

    @property
    def chi2_per_dof(self) -> float:
        return float(self.result.chi2_per_dof)

    @property
    def failures(self) -> list[dict[str, Any]]:
        """The tau ranges where the measurement leaves the model's band."""
        return list(self.result.failures)

    @cached_property
    def error(self) -> dict[str, Any]:
        """The error in its parts, as ``imunoise fit --json`` gives it: ``chi2_per_dof`` and
        ``max_abs_z`` of the Allan fit, and for a channel the ``psd``, ``holdout`` and
        ``time_domain`` parts (each about 1 when the model describes the sensor; computed on
        first use: two fits of the record's halves and a transient search)."""
        from imunoise.analysis.model_error import plain
        from imunoise.pipeline.fitting import fit_error_parts

        out: dict[str, Any] = dict(documents.error_json(self.result))
        if self.channel is not None:
            out.update(plain(fit_error_parts(self.channel.recording.record, self.channel.key,
                                             self.model_text, self.result)[1]))
        return out

    @property
    def findings(self) -> list[str]:
        """The hold-out part's findings as the text output prints them: each parameter that
        changed between the halves of the record, where each half's model misses the other
        half (empty for a curve of an array, which has no halves)."""
        return _findings(self.error)

    def document(self) -> dict[str, Any]:
        """``imunoise fit --json``'s document for a channel; for a curve of an array, its
        ``model``, ``error``, ``failures`` and ``allan``."""
        if self.channel is not None:
            from imunoise.pipeline.assembly import fit_document

            return fit_document(self.channel.recording.record, self.channel.key,
                                self.model_text, self.result, self.curve)[0]
        fields = documents.fit_fields(self.result, self.curve)
        return {"model": fields["model"], "error": fields["error"],
                "failures": fields["failures"],
                "allan": documents.allan_json(self.curve, fields["model_adev"], fields["z"])}

    def to_json(self) -> str:
        return documents.dumps(self.document())

    def to_pandas(self) -> Any:
        """One row per parameter: ``term`` (its label, ``name#K`` for a repeated term),
        ``param``, ``value``, ``ci95_low``, ``ci95_high``, ``unit``, ``resolved``
        (``notebook`` extra)."""
        from imunoise.analysis.terms import get_term, param_unit

        pd = _pandas()
        rows = []
        for label, t in zip(self.result.labels, self.result.terms, strict=True):
            term = get_term(t.term)
            for p in term.params:
                lo, hi = t.ci95[p.name]
                rows.append({"term": label, "param": p.name, "value": t.params[p.name],
                             "ci95_low": lo, "ci95_high": hi,
                             "unit": param_unit(p, self.units or "rad/s"),
                             "resolved": term.resolved(p.name, (lo, hi))})
        return pd.DataFrame(rows)

    def plot(self, ax: Any = None) -> Any:
        """The measured deviation with its band, the model and each term (``plot`` extra)."""
        from imunoise.analysis.terms import get_term

        ax = plotting.axes(ax)
        c = self.curve
        tau = np.asarray(c.tau_s)
        plotting.allan(ax, tau, np.asarray(c.dev), np.asarray(c.ci_low), np.asarray(c.ci_high),
                       self.units, self.channel.key if self.channel else "measured")
        terms = {}
        for t in self.result.terms:
            if t.term != "temperature":
                terms[t.term] = np.sqrt(np.maximum(
                    get_term(t.term).avar(tau, float(c.fs_hz), **t.params), 0.0))
        plotting.model(ax, tau, np.sqrt(self.result.model_avar(tau)), terms)
        return ax

    def __repr__(self) -> str:
        parts = [f"{label} " + ", ".join(f"{k}={v:.4g}" for k, v in p.items())
                 for label, p in self.params.items()]
        return (f"<FitReport {'; '.join(parts)}; chi2/dof {self.chi2_per_dof:.3g}, "
                f"{len(self.failures)} failing tau range(s)>")


@dataclass(frozen=True, repr=False)
class Diagnosis:
    """What a model misses on a channel: the fit, the ranked suggestions (each a refit with
    one more term or a cut, with its p-value) and the evidence beyond the Allan curve.

    Attributes:
        diagnosis: :class:`imunoise.analysis.diagnosis.Diagnosis`.
        channel: the channel diagnosed.
        model_text: the model given to the diagnosis.
    """

    diagnosis: AnalysisDiagnosis
    channel: Channel
    model_text: str = ""

    @property
    def fit(self) -> FitReport:
        return FitReport(self.diagnosis.fit, self.diagnosis.curve, self.channel.units,
                         self.channel, self.model_text)

    @property
    def suggestions(self) -> list[dict[str, Any]]:
        """The suggestions, best first (the JSON's ``suggestions`` entries)."""
        return [s.to_dict() for s in self.diagnosis.suggestions]

    @property
    def best(self) -> dict[str, Any] | None:
        """The best significant suggestion, or None when the model explains the data."""
        return next((s for s in self.suggestions if s["significant"]), None)

    @property
    def error(self) -> dict[str, Any]:
        """The given model's error in its parts (Allan, ``psd``, ``holdout``,
        ``time_domain``), as ``imunoise diagnose --json`` gives it."""
        from imunoise.analysis.model_error import plain

        out: dict[str, Any] = dict(documents.error_json(self.diagnosis.fit))
        out.update(plain(self.diagnosis.error_parts or {}))
        return out

    @property
    def findings(self) -> list[str]:
        """The hold-out part's findings for the given model, as the text output prints
        them (:attr:`FitReport.findings`)."""
        return _findings(self.error)

    def document(self) -> dict[str, Any]:
        """``imunoise diagnose --json``'s document."""
        from imunoise.pipeline.assembly import diagnosis_document

        ch = self.channel
        return diagnosis_document(ch.recording.record, ch.key, self.diagnosis,
                                  ch.time_base_group(), ch.skip_s, ch.split_s)[0]

    def to_json(self) -> str:
        return documents.dumps(self.document())

    def to_pandas(self) -> Any:
        """One row per suggestion: ``action`` (add, cut or remove), ``term`` (its ``label``
        where it has one: a removed term's ``name#K``, the two terms of a pair),
        ``significant``, ``p_value``, ``chi2_per_dof_before``, ``chi2_per_dof_after``,
        ``model`` to apply, ``why`` (``notebook`` extra)."""
        pd = _pandas()
        return pd.DataFrame([{"action": s.get("action", "add"),
                              "term": s.get("label") or s["term"],
                              "significant": s["significant"],
                              "p_value": s["p_value"],
                              "chi2_per_dof_before": s["chi2_per_dof_before"],
                              "chi2_per_dof_after": s["chi2_per_dof_after"],
                              "model": s["apply"]["model"], "why": s["why"]}
                             for s in self.suggestions])

    def plot(self, ax: Any = None) -> Any:
        """The fit's plot, titled with the best suggestion (``plot`` extra)."""
        ax = self.fit.plot(ax)
        best = self.best
        ax.set_title(f"{self.channel.key}: {best.get('action', 'add')} "
                     f"{best.get('label') or best['term']} (p = {best['p_value']:.2g})"
                     if best else f"{self.channel.key}: the model explains the curve")
        return ax

    def __repr__(self) -> str:
        best = self.best
        verdict = (f"best: {best.get('action', 'add')} {best.get('label') or best['term']} "
                   f"(p = {best['p_value']:.2g})" if best else "nothing significant is missing")
        return f"<Diagnosis {self.channel.key}: {len(self.suggestions)} suggestion(s), {verdict}>"


@dataclass
class Replicates:
    """Several runs of one unit described by one model (:func:`imunoise.replicates`).

    Attributes:
        result: :class:`imunoise.analysis.replicates.ReplicateResult` (each run's fits, the
            homogeneity tests).
        records: ``(label, record)`` of each run, in the order given.
        key: the channel compared.
        model_text: the model given.
    """

    result: ReplicateResult
    records: list[tuple[str, Record]]
    key: str
    model_text: str = ""

    @property
    def runs(self) -> list[str]:
        """The runs' labels (their files, with their cuts)."""
        return list(self.result.runs)

    @property
    def term_set(self) -> list[str]:
        """Term names of the model fitted to every run."""
        return list(self.result.term_set)

    @property
    def differ(self) -> list[dict[str, Any]]:
        """The parameters that differ between runs beyond their intervals (the JSON's
        ``differ`` entries: each run's own value and interval under ``per_run``)."""
        return list(self.result.to_dict()["differ"])

    def document(self) -> dict[str, Any]:
        """``imunoise diagnose FILE1 FILE2 ... --json``'s document."""
        from imunoise.pipeline.assembly import replicates_document

        return replicates_document(self.records, self.key, self.model_text, self.result)

    def to_json(self) -> str:
        return documents.dumps(self.document())

    def text(self) -> str:
        """The command's readable report: each run's term set and error parts, the shared
        shapes with their test, the per-run amplitudes, what differs between runs."""
        from imunoise.pipeline.replicates_text import replicates_text

        units = self.records[0][1].series(self.key).units
        return replicates_text(self.key, units, self.result)

    def plot(self, ax: Any = None) -> Any:
        """Each run's measured Allan deviation (points) and its model with the shared shapes
        held (line, the run's colour) on one plot (``plot`` extra)."""
        ax = plotting.axes(ax)
        units = self.records[0][1].series(self.key).units
        for label, fit in zip(self.result.runs, self.result.tied_fits, strict=True):
            plotting.run(ax, np.asarray(fit.tau_s), np.sqrt(np.asarray(fit.avar_measured)),
                         np.sqrt(np.asarray(fit.avar_fit)), units, label)
        ax.set_title(f"{self.key}: {len(self.runs)} runs, model {','.join(self.term_set)}")
        return ax

    def to_pandas(self) -> Any:
        """One row per run: ``run``, ``chi2_per_dof`` (its own fit's Allan part),
        ``chi2_per_dof_tied`` (with the agreeing shapes held), ``psd_deviance_per_bin``,
        ``holdout_chi2_per_dof`` (``notebook`` extra)."""
        pd = _pandas()
        rows = []
        for run in self.result.to_dict()["runs"]:
            error = run["error"] or {}
            rows.append({"run": run["label"], "chi2_per_dof": run["chi2_per_dof"],
                         "chi2_per_dof_tied": run["chi2_per_dof_tied"],
                         "psd_deviance_per_bin": (error.get("psd") or {}).get(
                             "deviance_per_bin"),
                         "holdout_chi2_per_dof": (error.get("holdout") or {}).get(
                             "chi2_per_dof")})
        return pd.DataFrame(rows)

    def __repr__(self) -> str:
        named = [f"{d['term']}.{d['param']}" for d in self.differ]
        verdict = f"differ: {', '.join(named)}" if named else "no parameter differs"
        return (f"<Replicates {self.key}: {len(self.runs)} runs, model "
                f"{','.join(self.term_set)}, {verdict}>")
