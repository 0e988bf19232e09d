"""The Python API: ``imunoise.read``, ``oadev``, ``psd``, ``fit``, ``diagnose``, ``replicates``,
``analyze``.

Every function computes what the command of the same name computes, with the same code: a
recording read with :func:`read` is cut to its still stretches and timed as ``imunoise
analyze`` does, :func:`oadev` and :func:`psd` are ``analyze``'s estimates, :func:`fit` and
:func:`diagnose` are ``imunoise fit`` and ``imunoise diagnose``, :func:`replicates` is
``imunoise diagnose`` given several files of one unit, and each result's
``document()`` is the JSON document that command prints (docs/json.md). Bad input raises
:class:`imunoise.errors.UsageError` (a ValueError) with the command line's one-line message.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from imunoise.analysis.default_model import DEFAULT_MODEL_TEXT
from imunoise.api.results import (
    AllanResult,
    Channel,
    Diagnosis,
    FitReport,
    PsdResult,
    Recording,
    Replicates,
)
from imunoise.core.series import ChannelSeries

DEFAULT_MODEL = DEFAULT_MODEL_TEXT
"""The model ``analyze`` fits: ``"white,bias_instability,random_walk"``."""

__all__ = ["DEFAULT_MODEL", "AllanResult", "Channel", "Diagnosis", "FitReport", "PsdResult",
           "Recording", "Replicates", "analyze", "diagnose", "fit", "oadev", "psd", "read",
           "replicates"]


def read(path: str, *, rate_hz: float | None = None, static: str = "auto") -> Recording:
    """Read a recording (.csv, .mcap, rosbag2 folder, ROS 1 bag) as ``imunoise analyze`` does.

    Args:
        path: the file or folder.
        rate_hz: sampling rate in Hz for a CSV without a time column (otherwise it overrides
            the rate found from the time stamps), as ``--rate``.
        static: ``"auto"`` keeps only the stretches where the sensor rested (a warning says
            what was cut), ``"all"`` everything, as ``--static``.

    Raises:
        UsageError: an unreadable file, with the reader's one-line reason.

    >>> import numpy as np, imunoise
    >>> rate = np.random.default_rng(0).normal(0.0, 0.01, 36_000)   # rad/s, 6 min at 100 Hz
    >>> path = _example_csv(rate)   # a CSV with columns t, gyro_x
    >>> rec = imunoise.read(path)
    >>> rec.channels
    ['gyro_x']
    >>> ch = rec["gyro_x"]
    >>> ch.units, ch.fs_hz, ch.series.n_samples
    ('rad/s', 100.0, 36000)
    """
    from imunoise.pipeline.reading import read_record

    return Recording(str(path), read_record(str(path), rate_hz, static))


def _series(data: Any, fs_hz: float | None, what: str) -> tuple[ChannelSeries, Channel | None]:
    """The samples of a :class:`Channel`, a ``ChannelSeries`` or an array at ``fs_hz``."""
    if isinstance(data, Channel):
        return data.series, data
    if isinstance(data, ChannelSeries):
        return data, None
    if isinstance(data, (AllanResult, PsdResult, FitReport, Recording)):
        raise TypeError(f"{what} needs samples (a channel or an array), not a "
                        f"{type(data).__name__}")
    if fs_hz is None:
        raise TypeError(f"{what} of an array needs fs_hz, the sampling rate in Hz")
    values = np.asarray(data, dtype=np.float64).ravel()
    return ChannelSeries("data", "", float(fs_hz), values), None


def oadev(data: Channel | ChannelSeries | np.ndarray, fs_hz: float | None = None
          ) -> AllanResult:
    """Overlapping Allan deviation on octave taus with 95 % intervals, as ``analyze`` reports
    it (no difference spans a gap between segments).

    Args:
        data: a channel of :func:`read`, or rate samples (SI units) with ``fs_hz``.
        fs_hz: sampling rate in Hz, for an array.

    >>> import numpy as np, imunoise
    >>> rate = np.random.default_rng(0).normal(0.0, 0.01, 36_000)   # white, rad/s
    >>> curve = imunoise.oadev(rate, fs_hz=100.0)
    >>> curve.tau_s[:3]
    array([0.01, 0.02, 0.04])
    >>> # white noise: sigma(tau) = 0.01 / sqrt(tau fs)
    >>> bool(np.allclose(curve.adev[:4], 0.01 / np.sqrt(curve.tau_s[:4] * 100), rtol=0.05))
    True
    """
    from imunoise.pipeline.channel_analysis import allan_curve

    series, channel = _series(data, fs_hz, "oadev")
    return AllanResult(allan_curve(series), series.units, channel)


def psd(data: Channel | ChannelSeries | np.ndarray, fs_hz: float | None = None) -> PsdResult:
    """One-sided power spectral density (units^2/Hz) on log-spaced frequencies with 95 %
    intervals, as ``analyze`` reports it.

    Args:
        data: a channel of :func:`read`, or samples (SI units) with ``fs_hz``.
        fs_hz: sampling rate in Hz, for an array.

    >>> import numpy as np, imunoise
    >>> rate = np.random.default_rng(0).normal(0.0, 0.01, 36_000)
    >>> spectrum = imunoise.psd(rate, fs_hz=100.0)
    >>> # white noise of variance s^2: a flat one-sided PSD of 2 s^2 / fs
    >>> level = float(np.median(spectrum.psd))
    >>> bool(abs(level / (2 * 0.01**2 / 100) - 1) < 0.1)
    True
    """
    from imunoise.pipeline.channel_analysis import psd_estimate

    series, channel = _series(data, fs_hz, "psd")
    return PsdResult(psd_estimate(series), series.units, channel)


def fit(data: AllanResult | Channel, model: str = DEFAULT_MODEL) -> FitReport:
    """Fit a noise model to an Allan curve or to a channel.

    Args:
        data: an :class:`AllanResult` (the fit ``analyze`` makes of it) or a :class:`Channel`
            (``imunoise fit``: also the ``temperature`` term, from the record's temperature).
        model: comma-separated terms, a parameter after a term held at that value (SI
            units): ``"white,gauss_markov:T=100,random_walk"``.

    Raises:
        UsageError: an unknown term or parameter, or a curve too short for the model.

    >>> import numpy as np, imunoise
    >>> rng = np.random.default_rng(0)
    >>> rate = rng.normal(0.0, 0.01, 36_000) + np.cumsum(rng.normal(0.0, 1e-4, 36_000))
    >>> report = imunoise.fit(imunoise.oadev(rate, fs_hz=100.0), "white,random_walk")
    >>> sorted(report.params)
    ['random_walk', 'white']
    >>> # white: N = 0.01 / sqrt(100 Hz) = 1e-3 rad/s/sqrt(Hz)
    >>> bool(abs(report.params["white"]["N"] / 1e-3 - 1) < 0.05)
    True
    """
    from imunoise.pipeline.fitting import fit_channel, fit_errors, parse_model

    if isinstance(data, Channel):
        result, curve = fit_channel(data.recording.record, data.key, model)
        return FitReport(result, curve, data.units, data, model)
    if not isinstance(data, AllanResult):
        raise TypeError("fit needs an AllanResult (imunoise.oadev) or a channel, not a "
                        f"{type(data).__name__}")
    from imunoise.analysis.fit import fit_allan

    names, fixed = parse_model(model)
    with fit_errors(data.channel.key if data.channel else "curve"):
        result = fit_allan(data.curve, names, fixed=fixed or None).in_canonical_order()
    return FitReport(result, data.curve, data.units, data.channel, model)


def diagnose(channel: Channel, model: str = DEFAULT_MODEL) -> Diagnosis:
    """What ``model`` misses on a channel, as ``imunoise diagnose``: every term the model
    lacks added in turn and refitted, with the evidence the Allan curve cannot give
    (spectral lines, temperature, drift, outliers, gaps); a suggestion is significant only
    when it passes a test that, on data the model fully explains, stays silent in at least
    95 % of cases.

    >>> import numpy as np, imunoise
    >>> rate = np.random.default_rng(0).normal(0.0, 0.01, 36_000)
    >>> rec = imunoise.read(_example_csv(rate))
    >>> dx = imunoise.diagnose(rec["gyro_x"], "white")
    >>> dx.best is None   # white noise: nothing is missing
    True

    A suggestion that cuts the record (a warm-up, a bias step) is applied with
    ``channel.window(skip_s, split_s)``, as its ``apply.args`` say.
    """
    from imunoise.pipeline.fitting import diagnose_channel, full_window_args

    if not isinstance(channel, Channel):
        raise TypeError("diagnose needs a channel of imunoise.read (its samples), not a "
                        f"{type(channel).__name__}")
    diag = diagnose_channel(channel.recording.record, channel.key, model,
                            time_origin_s=channel.skip_s)
    for sug in diag.suggestions:
        sug.apply["args"] = full_window_args(sug.apply.get("args", []), channel.skip_s,
                                             list(channel.split_s))
    return Diagnosis(diag, channel, model)


def replicates(channels: Sequence[Channel], model: str = DEFAULT_MODEL, rounds: int = 0
               ) -> Replicates:
    """Several recordings of one unit described by one model, as ``imunoise diagnose FILE1
    FILE2 ...`` (docs/replicates.md): each run fitted alone (with ``rounds``, first
    diagnosed alone that many rounds, and the term set most runs choose fitted to all), the
    shape parameters tested for agreement across runs and held at their pooled values where
    they agree, the amplitudes per run, and the parameters that differ between runs named.

    ``channels``: the same channel of two or more recordings of :func:`read` (cut with
    :meth:`Channel.window` where a run needs it); each run is labelled with its file.

    Raises:
        UsageError: fewer than two runs, one run given twice, channels with different keys,
            ``rounds`` not a whole number >= 0, an unknown term, or a run too short to fit
            (the message names the run).

    >>> import numpy as np, imunoise
    >>> runs = [imunoise.read(_example_csv(np.random.default_rng(s).normal(0.0, 0.01, 36_000)))
    ...         for s in (1, 2)]
    >>> rep = imunoise.replicates([r["gyro_x"] for r in runs], "white")
    >>> rep.term_set, [d["param"] for d in rep.differ]
    (['white'], [])
    """
    import os

    from imunoise.errors import UsageError
    from imunoise.pipeline.fitting import diagnose_replicates

    runs = list(channels)
    if not all(isinstance(ch, Channel) for ch in runs):
        raise TypeError("replicates needs channels of imunoise.read (their samples)")
    if len(runs) < 2:
        raise UsageError(f"replicates needs two or more runs of one unit, got {len(runs)}")
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 0:
        raise UsageError(f"replicates: rounds {rounds!r}: a whole number >= 0")
    keys = sorted({ch.key for ch in runs})
    if len(keys) > 1:
        raise UsageError(f"replicates compares one channel across runs, got {', '.join(keys)}")
    labels = [_run_label(ch) for ch in runs]
    same = [(os.path.realpath(ch.recording.path), ch.skip_s, ch.split_s) for ch in runs]
    twice = next((n for n in range(len(runs)) if same[n] in same[:n]), None)
    if twice is not None:
        raise UsageError(f"replicates: {labels[twice]} is given twice: a run compared with "
                         f"itself agrees by construction")
    records = [(lab, ch.recording.record) for lab, ch in zip(labels, runs, strict=True)]
    result = diagnose_replicates(records, keys[0], model, rounds)
    return Replicates(result, records, keys[0], model)


def _run_label(channel: Channel) -> str:
    """A run's label: its file as read, with its cuts where it has any."""
    cuts = [f"skip {channel.skip_s:g} s"] if channel.skip_s else []
    if channel.split_s:
        cuts.append(f"split {', '.join(f'{t:g}' for t in channel.split_s)} s")
    path = channel.recording.path
    return f"{path} ({'; '.join(cuts)})" if cuts else path


def analyze(source: str | Recording, channels: list[str] | None = None) -> dict[str, Any]:
    """The ``imunoise analyze --json`` document of a recording (a path or a :class:`Recording`
    of :func:`read`): every IMU channel's (or ``channels``') Allan deviation, PSD, default
    model fit and discrete-time model.

    >>> import numpy as np, imunoise
    >>> rate = np.random.default_rng(0).normal(0.0, 0.01, 36_000)
    >>> doc = imunoise.analyze(_example_csv(rate))
    >>> list(doc["channels"]), [t["term"] for t in doc["channels"]["gyro_x"]["model"]]
    (['gyro_x'], ['white', 'bias_instability', 'random_walk'])
    """
    from imunoise.pipeline.assembly import analysis_document, printed_analysis
    from imunoise.pipeline.channel_analysis import analyze_record
    from imunoise.pipeline.reading import select

    rec = source if isinstance(source, Recording) else read(source)
    keys = select(rec.record, list(channels or []))
    results = analyze_record(rec.record, keys, show_progress=False)
    return printed_analysis(analysis_document(rec.path, rec.record, results)[0])


_EXAMPLES: list[Any] = []
"""The temporary folder of the examples' recordings (one per process, removed when the
process ends)."""


def _example_csv(rate: np.ndarray, fs_hz: float = 100.0) -> str:
    """A CSV recording (columns ``t``, ``gyro_x`` in rad/s) of ``rate`` in this process's
    temporary folder of examples, for the examples."""
    import tempfile
    from pathlib import Path

    if not _EXAMPLES:
        # a TemporaryDirectory removes its folder when the interpreter exits
        _EXAMPLES.append(tempfile.TemporaryDirectory(prefix="imunoise-example-"))
    folder = Path(_EXAMPLES[0].name)
    path = folder / f"imu{len(list(folder.iterdir()))}.csv"
    t = np.arange(len(rate)) / fs_hz
    np.savetxt(path, np.column_stack([t, rate]), delimiter=",", header="t,gyro_x",
               comments="", fmt="%.9g")
    return str(path)
