"""Fitting and diagnosing one channel of a record, as ``imunoise fit`` and ``diagnose`` do.

A model is written as the command line takes it (``white,gauss_markov:T=100``); an unknown
term, a bad parameter or a record the fit cannot use raises
:class:`imunoise.errors.UsageError`, a numerical breakdown
:class:`imunoise.errors.RuntimeFailure`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from imunoise.core.record import Record
from imunoise.core.units import CI95
from imunoise.errors import RuntimeFailure, UsageError
from imunoise.pipeline.workers import cpu_job_map


def parse_model(text: str) -> tuple[list[str], dict[str | int, dict[str, float]]]:
    """Term names and held parameters (by model index) of ``--model TERMS``; an unknown term,
    a bad or out-of-range parameter or an empty model is a usage error naming the valid
    terms."""
    from imunoise.analysis.common_steps import TERM
    from imunoise.analysis.terms import TermError, parse_model

    if not text.strip(" ,"):
        raise UsageError(f"--model {text!r} names no term")
    if TERM in [t.split(":")[0].strip() for t in text.split(",")]:
        # imunoise fit and diagnose take it out of the model before it reaches here
        raise UsageError(f"{TERM} is a correction of the record, not a term: imunoise fit "
                         f"and diagnose apply it, reading the record's other channels; here "
                         f"name the noise terms only")
    try:
        spec = parse_model(text)
    except TermError as exc:
        raise UsageError(str(exc)) from None
    fixed: dict[str | int, dict[str, float]] = {i: p for i, p in spec.fixed.items()}
    return spec.names, fixed


@contextmanager
def fit_errors(key: str) -> Iterator[None]:
    """Turn a fit's exceptions into the command line's: a bad model or a record the fit
    cannot use is a usage error (exit 2), a numerical breakdown a runtime failure (exit 1)."""
    from imunoise.analysis.terms import TermError

    try:
        yield
    except TermError as exc:
        raise UsageError(str(exc)) from None
    except ValueError as exc:
        raise UsageError(f"{key}: {exc}") from None
    except np.linalg.LinAlgError as exc:
        raise RuntimeFailure(f"{key}: the fit failed numerically ({exc})") from None


def temperature_at(record: Record, key: str) -> np.ndarray | None:
    """The record's temperature (degC) at each sample of channel ``key``, by linear
    interpolation in time (sample times from each series' start and rate), or None."""
    temp = record.temperature
    if temp is None or temp.n_samples == 0:
        return None
    series = record.series(key)
    t_chan = series.t0_s + np.arange(series.n_samples) / series.fs_hz
    t_temp = temp.t0_s + np.arange(temp.n_samples) / temp.fs_hz
    return np.interp(t_chan, t_temp, temp.values)


def fit_channel(record: Record, key: str, model_text: str) -> tuple[Any, Any]:
    """Fit ``model_text`` to channel ``key`` of ``record``: ``(FitResult, AllanCurve)``.

    Raises UsageError for an unknown term, a bad parameter or a record too short to fit."""
    from imunoise.analysis.fit import fit_series

    names, fixed = parse_model(model_text)
    series = record.series(key)
    temperature = temperature_at(record, key) if "temperature" in names else None
    with fit_errors(key):
        result, curve = fit_series(series.values, series.fs_hz, names,
                                   segment_starts=series.segment_starts,
                                   temperature=temperature, fixed=fixed, ci=CI95,
                                   job_map=cpu_job_map())
    return result.in_canonical_order(), curve


def fit_error_parts(record: Record, key: str, model_text: str, result: Any,
                    holdout: bool = True) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """``(psd block, error parts)`` of a fit of ``model_text`` to channel ``key``: the PSD,
    hold-out and time-domain parts beside the Allan chi2/dof
    (:func:`imunoise.analysis.model_error.error_parts`); ``holdout`` False leaves the
    hold-out part out (for a caller that computes it on other halves)."""
    from imunoise.analysis.model_error import error_parts

    series = record.series(key)
    with fit_errors(key):
        return error_parts(series.values, series.fs_hz, model_text, result,
                           segment_starts=series.segment_starts, units=series.units,
                           holdout=holdout, job_map=cpu_job_map())


ADIS_INTERNAL_RATE_HZ = 819.2
"""Internal sample rate of the ADIS16350, at which its Bartlett filter runs (Hz)."""


def diagnose_channel(record: Record, key: str, model_text: str,
                     time_origin_s: float = 0.0) -> Any:
    """Run :func:`imunoise.analysis.diagnosis.diagnose` on one channel of a record (its first sample
    ``time_origin_s`` seconds after the start of the file: the ``--skip`` applied).

    Raises UsageError for an unknown term or a record too short to fit."""
    from imunoise.analysis.diagnosis import diagnose

    names, fixed = parse_model(model_text)
    series = record.series(key)
    temp = record.temperature
    temperature = None
    if temp is not None and temp.n_samples >= 2:
        temperature = (temp.t0_s + np.arange(temp.n_samples) / temp.fs_hz, temp.values)
    with fit_errors(key):
        return diagnose(series.values, series.fs_hz, names,
                        segment_starts=series.segment_starts, t0_s=series.t0_s,
                        temperature=temperature, units=series.units, fixed=fixed,
                        sensor_filter=device_filter(record.metadata, key),
                        time_origin_s=time_origin_s, job_map=cpu_job_map())


def device_filter(metadata: dict[str, str], key: str) -> tuple[str, dict[str, float]] | None:
    """The output filter an imunoise recording's device configuration states for channel
    ``key``, or None for other files and devices:

    * ADIS16350: the Bartlett window of ``filter_taps`` taps per stage runs at the internal
      819.2 Hz; at the output rate it spans ``taps * rate / 819.2`` output samples, stated
      when that is at least one sample (shorter, it averages within one output sample);
    * ITG-3200: the digital low-pass (``dlpf_bandwidth_hz``), modelled as one pole at that
      bandwidth, when it lies below the output Nyquist frequency.
    """
    device = metadata.get("config.device", "")
    rate = float(metadata.get("config.rate_hz", "nan"))
    channel = key.split(":")[-1]
    if not np.isfinite(rate):
        return None
    if device == "adis16350" and "config.filter_taps" in metadata:
        taps = float(metadata["config.filter_taps"]) * rate / ADIS_INTERNAL_RATE_HZ
        return ("bartlett", {"taps": taps}) if taps >= 1.0 else None
    if device == "itg3200" and channel.startswith("gyro") \
            and "config.dlpf_bandwidth_hz" in metadata:
        fc = float(metadata["config.dlpf_bandwidth_hz"])
        if fc < 0.5 * rate:
            return "lowpass", {"fc": fc}
    return None


def full_window_args(own: list[str], skip_s: float, split_s: list[float]) -> list[str]:
    """A suggestion's ``apply.args`` for the whole command: the ``--skip``/``--split`` this
    diagnosis ran with, joined with the suggestion's own cut (whose times count from the
    first sample the diagnosis saw, i.e. after ``skip_s``), so that applying it keeps the
    cuts already made."""
    skip, splits = float(skip_s), [float(t) for t in split_s]
    if len(own) == 2 and own[0] == "--skip":
        skip += float(own[1])
    elif len(own) == 2 and own[0] == "--split":
        splits.append(float(skip_s) + float(own[1]))
    out: list[str] = []
    if skip:
        out += ["--skip", f"{skip:.10g}"]
    if splits:
        out += ["--split", ",".join(f"{t:.10g}" for t in sorted(set(splits)))]
    return out


def diagnose_replicates(records: list[tuple[str, Record]], key: str, model_text: str,
                        rounds: int = 0) -> Any:
    """:func:`imunoise.analysis.replicates.fit_replicates` on channel ``key`` of several
    records of one unit (``(label, record)`` each): one model, shared shapes, per-run
    amplitudes; with ``rounds`` each run is first diagnosed alone that many rounds.

    Raises UsageError for an unknown term or a record too short to fit."""
    from imunoise.analysis.replicates import Run, fit_replicates

    names, _ = parse_model(model_text)
    runs = []
    for label, record in records:
        series = record.series(key)
        temp = record.temperature
        temp_rec = None
        if temp is not None and temp.n_samples >= 2:
            temp_rec = (temp.t0_s + np.arange(temp.n_samples) / temp.fs_hz, temp.values)
        runs.append(Run(label, series.values, series.fs_hz, series.segment_starts,
                        temperature_at(record, key) if "temperature" in names else None,
                        {"t0_s": series.t0_s, "temperature": temp_rec, "units": series.units,
                         "sensor_filter": device_filter(record.metadata, key)}))
    with fit_errors(key):
        return fit_replicates(runs, model_text, rounds=rounds, job_map=cpu_job_map())
