"""Diagnosis: which physical effect is the model missing?

Given a channel and a model, the model is fitted to the overlapping Allan curve; then every
term of the vocabulary that the model lacks is added in turn and the model refitted. The
misfit of the fit (``chi2``: the whitened, correlation-aware sum of squared standardised
residuals of :mod:`imunoise.analysis.misfit`) falls when the term is right. Under the hypothesis
that
the term is absent, the fall is approximately chi-square distributed with as many degrees of
freedom as the term has parameters (a likelihood-ratio test on the decorrelated misfit).

Evidence the Allan curve cannot give (:mod:`imunoise.analysis.evidence`) joins in: a spectral line
supports ``sinusoid``, correlation with the temperature record supports ``temperature``, a
steady slope supports ``rate_ramp``. Each candidate's p-value is the smaller of its sources'
(Bonferroni over the sources) and the candidates are ranked by it; a candidate is
``significant`` when its p-value, Bonferroni-corrected for the number of candidates, is below
``alpha``. The ranking follows the p-values (kept in log form, as strong effects give values
far below the floating-point range). So on data the model fully explains, nothing is
flagged with probability at least ``1 - alpha``. Outliers, gaps, a changing noise level and
the shortest taus a sensor's filter pulls below the model are reported alongside: they are
not noise terms to add, but they are why a model can look wrong.

:func:`diagnose` runs one round in four steps, one module each: :mod:`.gathering` (evidence on
the given model before any term is tried), :mod:`.candidates` (each candidate refitted and
judged), :mod:`.ranking` (the order of the suggestions, the simplest explanation first) and
:mod:`.holdout` (the hold-out judgement, and the lookahead to a pair of terms); beside them
:mod:`.context` (what the refits of one round share), :mod:`.statistics` (the tests) and
:mod:`.result` (what a diagnosis returns).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from imunoise.analysis.diagnosis.candidates import (
    _candidates,
    _first_job,
    _swaps,
    wants_band_refit,
)
from imunoise.analysis.diagnosis.context import _Context, _fold, _times
from imunoise.analysis.diagnosis.gathering import _base_test, _BaseTests
from imunoise.analysis.diagnosis.holdout import _check_holdout, _pair
from imunoise.analysis.diagnosis.ranking import (
    RECHOSEN_FILTER_EXCESS,
    _filter_rechosen,
    _ranked,
    _second_job,
)
from imunoise.analysis.diagnosis.result import DEFAULT_ALPHA, Diagnosis, Suggestion
from imunoise.analysis.fit import fit_series
from imunoise.analysis.jobs import JobMap, serial_map
from imunoise.analysis.model_error import HoldoutHalves, holdout_halves
from imunoise.analysis.psd_model import adopt_grid_gains
from imunoise.analysis.terms import parse_model

__all__ = ["DEFAULT_ALPHA", "RECHOSEN_FILTER_EXCESS", "Diagnosis", "Suggestion", "diagnose"]


def diagnose(values: np.ndarray, fs_hz: float, model: str | list[str], *,
             segment_starts: np.ndarray | None = None, t0_s: float = 0.0,
             temperature: tuple[np.ndarray, np.ndarray] | None = None,
             units: str = "rad/s", alpha: float = DEFAULT_ALPHA,
             fixed: dict | None = None,
             sensor_filter: tuple[str, dict[str, float]] | None = None,
             transients: bool = True, time_origin_s: float = 0.0,
             holdout: bool = True, lookahead: bool = True,
             job_map: JobMap = serial_map) -> Diagnosis:
    """Fit ``model`` to a rate series and rank the terms it is missing.

    Args:
        values: rate samples (SI units), all gap-free segments concatenated.
        fs_hz: sampling rate in Hz.
        model: the model (a specification string such as ``"white,gauss_markov:T=100"`` or
            a list of names; see :func:`imunoise.analysis.terms.parse_model`).
        segment_starts: gap-free segment starts (``ChannelSeries.segment_starts``).
        t0_s: time of the first sample, seconds (same base as the temperature times).
        temperature: ``(times_s, degC)`` of the temperature record, any rate.
        units: units of ``values`` (for explanations).
        alpha: family-wise significance level over all candidates.
        fixed: parameters held fixed in the given model (see
        :func:`imunoise.analysis.fit.fit_allan`).
        sensor_filter: the output filter the device's configuration states, ``(term,
            params)`` (e.g. ``("bartlett", {"taps": 4})``); it is then the one filter
            offered, with those parameters held. Without it the filter terms are offered,
            fitted, when the shortest taus lie below the model.
        transients: test for a bias step and a warm-up against the fitted model
            (:func:`imunoise.analysis.evidence.transients`); their remedies are cuts of the record
            (``apply.args``: ``--split T``, ``--skip S``), so a caller that cannot cut (the
            live service) leaves them out.
        time_origin_s: the time of the first sample analysed on the scale step times are
            reported on, seconds (the command line passes its ``--skip``, so that a step's
            ``t_s`` counts from the start of the file, as ``--split`` does).
        holdout: compute the hold-out part (the model fitted on each half predicting the
            other) and require a significant term to lower it; it costs two fits per check.
        lookahead: where the model fails and the hold-out part holds back every term with
            strong evidence, try the strongest of them with the next round's term
            (:func:`_pair`); it costs a few more refits, in that situation only.
        job_map: how the independent jobs run (the candidates' refits, the hold-out halves,
            the profile intervals; see :mod:`imunoise.analysis.jobs`): one after the other
            by default; the command line forks workers. The result is the same.

    Returns:
        A :class:`Diagnosis` with suggestions best first.
    """
    return _diagnose(values, fs_hz, model, segment_starts=segment_starts, t0_s=t0_s,
                     temperature=temperature, units=units, alpha=alpha, fixed=fixed,
                     sensor_filter=sensor_filter, transients=transients,
                     time_origin_s=time_origin_s, holdout=holdout,
                     lookahead=lookahead, job_map=job_map)


def _diagnose(values: np.ndarray, fs_hz: float, model: str | list[str], *,
              segment_starts: np.ndarray | None, t0_s: float,
              temperature: tuple[np.ndarray, np.ndarray] | None, units: str, alpha: float,
              fixed: dict | None, sensor_filter: tuple[str, dict[str, float]] | None,
              transients: bool, time_origin_s: float, holdout: bool, lookahead: bool,
              job_map: JobMap, only: frozenset[str] | None = None,
              memo: dict | None = None) -> Diagnosis:
    """:func:`diagnose`, trying only the candidates named in ``only`` when it is given (the
    lookahead's next round: the terms the first round found strong evidence for); that round
    takes the given model's intervals linearised (its own are not reported) and shares the
    first round's ``memo`` of the series (its Allan curve and solutions)."""
    x = np.asarray(values, dtype=np.float64)
    starts = (np.asarray(segment_starts, dtype=np.int64) if segment_starts is not None
              else np.zeros(1, dtype=np.int64))
    base_spec = _fold(parse_model(model), fixed)
    names = base_spec.names
    t_rate = _times(x.size, fs_hz, t0_s)
    temp_at = None
    if temperature is not None:
        temp_at = np.interp(t_rate, np.asarray(temperature[0], float),
                            np.asarray(temperature[1], float))
    memo = {} if memo is None else memo
    base, curve = fit_series(x, fs_hz, base_spec, segment_starts=starts,
                             temperature=temp_at if "temperature" in names else None,
                             memo=memo, job_map=job_map,
                             intervals="profile" if only is None else "jacobian")
    base = base.in_canonical_order()  # labels of repeated terms as every fit gives them
    segments = [s for s in (x[a:b] for a, b in zip(starts, np.append(starts[1:], x.size),
                                                   strict=True)) if s.size]

    # the evidence and the transient and PSD tests read the base fit, not each other
    tests = _BaseTests(x, fs_hz, starts, segments, t_rate, base, names, temperature, alpha,
                       units, transients, time_origin_s)
    (findings, by_term, filt), (cuts, psd_baseline, time_domain, gains) = job_map(
        _base_test, tests, ["evidence", "spectrum"])
    adopt_grid_gains(gains)  # the workers forked from here on start with them
    findings.extend(cuts)
    psd_est, nperseg, psd_block, psd_before = psd_baseline
    candidates = _candidates(names, base, filt, temperature is not None, sensor_filter)
    swaps = _swaps(base_spec, base, sensor_filter, findings, psd_before) \
        if only is None else []
    if only is not None:
        candidates = [c for c in candidates if c in only]
    # the spectrum's model of the resonance band, where the model misses the spectrum
    band = only is None and wants_band_refit(base, psd_before)
    parts: dict[str, Any] = {"psd": psd_before, "time_domain": time_domain}
    ctx = _Context(x, fs_hz, starts, temp_at, memo, base, base_spec, by_term,
                   len(candidates) + len(swaps) + len(cuts) + int(band), sensor_filter,
                   time_origin_s,
                   psd_est, nperseg, psd_before, job_map, profile_added=only is None,
                   units=units)
    # the given model's hold-out halves are fitted beside the candidates' refits
    halves = holdout_halves(x, fs_hz, base_spec, base, starts) if holdout else None
    jobs: list[tuple[str, Any]] = [("term", c) for c in candidates]
    jobs += [("swap", w) for w in swaps]
    if band:
        jobs.append(("band", None))
    n_tried = len(jobs)
    if isinstance(halves, HoldoutHalves):
        jobs += [("half", 0), ("half", 1)]
    done = job_map(_first_job, (ctx, alpha, halves if isinstance(halves, HoldoutHalves)
                                else None), jobs)
    suggestions = _ranked(ctx, done[:n_tried], cuts, units, alpha)
    if only is None:
        suggestions = _filter_rechosen(ctx, suggestions, alpha)
    # the next line's refit and the given model's hold-out part need nothing of each other
    steps = (["line"] if only is None else []) + \
        (["holdout"] if isinstance(halves, HoldoutHalves) else [])
    second = dict(zip(steps, job_map(
        _second_job, (ctx, suggestions, alpha, units, halves, done[n_tried:]), steps),
        strict=True))
    suggestions = second.get("line", suggestions)
    if halves is None:
        parts["holdout"] = {"chi2_per_dof": None, "parts": 2, "reason": "not requested"}
    else:
        before = second.get("holdout", halves)
        assert isinstance(before, dict)
        parts["holdout"] = _check_holdout(ctx, suggestions, before)
        if lookahead:
            def next_round(spec_text: str, names: frozenset[str]) -> Diagnosis:
                return _diagnose(x, fs_hz, spec_text, segment_starts=starts, t0_s=t0_s,
                                 temperature=temperature, units=units, alpha=alpha,
                                 fixed=None, sensor_filter=sensor_filter, transients=False,
                                 time_origin_s=time_origin_s, holdout=False,
                                 lookahead=False, job_map=job_map, only=names,
                                 memo=memo)

            pair = _pair(ctx, suggestions, parts["holdout"], alpha, next_round)
            if pair is not None:
                suggestions.insert(0, pair)
    return Diagnosis(fit=base, curve=curve, suggestions=suggestions, findings=findings,
                     alpha=alpha, psd=psd_block, error_parts=parts)
