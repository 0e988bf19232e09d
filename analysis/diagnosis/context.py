"""What every refit of one diagnosis shares (:class:`_Context`), and the refits themselves: a term
appended, a model refitted with its shapes pinned from the spectrum, the error parts after it."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from imunoise.analysis.diagnosis.statistics import (
    PSD_BIN_CORRELATION,
    _chi2_logsf,
    _deviance,
    _dispersion,
    _lowers,
    _part_sd,
    _rises,
)
from imunoise.analysis.evidence.finding import Finding
from imunoise.analysis.fit import FitResult, fit_series
from imunoise.analysis.jobs import JobMap, serial_map
from imunoise.analysis.model_error import psd_parts
from imunoise.analysis.spectral_pins import PINNED, pin_resonances, pinned_of
from imunoise.analysis.terms import Entry, ModelSpec, TermError, get_term, parse_model


def _times(n: int, fs_hz: float, t0_s: float) -> np.ndarray:
    return t0_s + np.arange(n) / fs_hz


def _fold(spec: ModelSpec, fixed: dict | None) -> ModelSpec:
    """``spec`` with the parameters held by ``fixed`` (keyed by model index or term name, its
    first occurrence) written into its entries."""
    entries = list(spec.entries)
    for key, params in (fixed or {}).items():
        idx = key if isinstance(key, int) else spec.names.index(key) \
            if key in spec.names else None
        if idx is None or not 0 <= idx < len(entries):
            raise TermError(f"fixed parameters given for {key!r}, which is not in the model "
                            f"({', '.join(spec.names)})")
        e = entries[idx]
        entries[idx] = Entry(e.name, {**e.fixed, **{k: float(v) for k, v in params.items()}},
                             e.start)
    return parse_model(ModelSpec(tuple(entries)).text()) if entries else spec


@dataclass
class _Context:
    """What every candidate's refit shares."""

    x: np.ndarray
    fs_hz: float
    starts: np.ndarray
    temp_at: np.ndarray | None
    memo: dict
    base: FitResult
    spec: ModelSpec
    by_term: dict[str, Finding]
    n_candidates: int
    sensor_filter: tuple[str, dict[str, float]] | None = None
    time_origin_s: float = 0.0
    psd_est: Any = None
    nperseg: int = 256
    psd_before: dict[str, Any] | None = None
    job_map: JobMap = serial_map
    profile_added: bool = True
    """Whether a candidate's refit profiles the added term's weakly determined parameters
    (the white level's always are); the lookahead's round reports none of them."""
    units: str = ""
    """The samples' units, for the suggestions' text."""


_Interval = tuple[float, float]


def _refit(ctx: _Context, term: str
           ) -> tuple[FitResult | None, ModelSpec, dict[str, float], dict[str, _Interval]]:
    """The model with ``term`` appended, fitted exactly as ``imunoise fit --model`` fits it
    (its ``apply.model``): ``(fit or None, model, parameters the evidence pinned, their
    intervals where the evidence gives them)``."""
    pinned: dict[str, float] = {}
    pinned_ci: dict[str, _Interval] = {}
    if ctx.sensor_filter is not None and term == ctx.sensor_filter[0]:
        # the device's configuration states the filter: it is not fitted
        pinned = dict(ctx.sensor_filter[1])
    f_ev = ctx.by_term.get(term)
    if get_term(term).role == "line" and f_ev is not None and f_ev.significant \
            and "f" in f_ev.params:
        # The PSD pins the frequency far better than the Allan curve can.
        pinned = {"f": float(f_ev.params["f"])}
        pinned_ci = {k: (float(lo), float(hi)) for k, (lo, hi)
                     in f_ev.details.get("ci95", {}).items() if k in pinned}
    after, spec = _fit_appended(ctx, term, pinned)
    imitates = term == "resonance" and _imitation(ctx, after) is not None
    if term == "resonance" and after is not None and (imitates or _psd_rises(ctx, after)):
        # The Allan refit put the resonance where the spectrum has no such peak (ADIS16405
        # run 3 gyro_z: 18.0 Hz with Q 1e4 beside a measured peak at 19.8 Hz, the PSD part
        # 2112 -> 3827), or let it take the white noise's place (run 5 gyro_z: chi2/dof
        # 1.77e4 -> 1.04e3 with the white level traded to zero): the spectrum's centre and
        # width are held instead, where that raises no PSD part (and, for the second, gives
        # the white noise back). Where the Allan refit is consistent with the spectrum it
        # stands: held at the peak, a resonance may follow the Allan curve worse (run 1
        # accel_x: 2029 against 1054 for a lowpass filter, a different first round)
        pin = _spectrum_pin(ctx, after, own_model=not imitates)
        if pin is not None:
            shape = pinned_of(pin.params)
            again, spec_again = _fit_appended(ctx, term, shape)
            if again is not None and not _psd_rises(ctx, again) \
                    and not (imitates and _imitation(ctx, again) is not None):
                after, spec, pinned, pinned_ci = again, spec_again, shape, dict(pin.ci95)
    elif term == "resonance" and after is not None:
        at_peaks = _held_at_peaks(ctx, spec, after, {len(ctx.spec)}, _fit_profiled(ctx, spec))
        if at_peaks is not None:
            after, spec, pins = at_peaks
            pin = pins[len(ctx.spec)]
            pinned, pinned_ci = pinned_of(pin.params), dict(pin.ci95)
    return after, spec, pinned, pinned_ci


def _fit_profiled(ctx: _Context, spec: ModelSpec) -> set[int]:
    """The terms whose intervals a candidate's refit reports (:func:`_fit_appended`)."""
    reported = {i for i, n in enumerate(spec.names) if n == "white"}
    if ctx.profile_added:
        reported.add(len(ctx.spec))
    return reported


def _held_at_peaks(ctx: _Context, spec: ModelSpec, fit: FitResult, which: set[int],
                   profile_terms: set[int]) -> tuple[FitResult, ModelSpec, dict[int, Any]] | None:
    """A refit with its free resonances among ``which`` (model indices) held at the
    spectrum's peaks (:mod:`imunoise.analysis.spectral_pins`), or None where it stands as
    fitted: ``(refit, its model, the pins by index)``.

    The Allan curve sees a resonance as a bump and leaves its f0 and Q to absorb misfit
    elsewhere: ADIS16405 run 1 accel_z with a Bartlett filter and its 0.57 Hz line puts a
    line at 10.5 Hz (Q 1644) where the spectrum shows a peak of Q 11.8 [10.2, 13.6] that the
    term follows exactly (deviance per dof 1.00). Held there, the PSD part falls from 6.5 to
    3.3 while the Allan chi2/dof moves from 5.33 to 5.25. A resonance is held at its peak
    where the refit put f0 or Q outside the peak's 95 % interval, the held refit lowers the
    PSD part by more than its standard deviation, and it raises the Allan part by less than
    one of its own (a resonance held at a peak that the Allan curve contradicts, such as a
    drifting one, stays as the Allan fit put it), or, where it raises the Allan part more,
    when it still lowers the given model's Allan part beyond its noise and lowers the two
    parts together further than the free refit does (:func:`_joint_change`): ADIS16405 run 3
    accel_z with a moving average and its 0.54 Hz line takes a hump at 13.9 Hz (Q 0.5) from
    the Allan curve, chi2/dof 15.3 -> 6.06 with the PSD part 4.50 -> 4.87, where the
    spectrum's peak at 9.87 Hz (Q 6.4) gives 9.18 and 3.08: both parts fall."""
    held = {(i, k) for i, e in enumerate(spec.entries) for k in e.fixed}
    try:
        pins = pin_resonances(ctx.x, ctx.fs_hz, fit.params, held, ctx.starts, ctx.memo)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None
    off = {p.index: p for p in pins if p.index in which and any(
        not p.ci95[k][0] <= fit.terms[p.index].params[k] <= p.ci95[k][1] for k in p.ci95)}
    if not off:
        return None
    entries = list(spec.entries)
    for i, p in off.items():
        e = entries[i]
        entries[i] = Entry(e.name, {**e.fixed, **pinned_of(p.params)}, e.start)
    spec_held = ModelSpec(tuple(entries))
    again = _fit_model(ctx, spec_held, profile_terms)
    if again is None:
        return None
    part_free, part_held = _psd_after(ctx, fit), _psd_after(ctx, again)
    if not _lowers(_deviance(part_free), _deviance(part_held),
                   (part_held or {}).get("bins", 0) / PSD_BIN_CORRELATION):
        return None
    if again.chi2_per_dof > fit.chi2_per_dof + _part_sd(fit.chi2_per_dof, again.misfit.dof) \
            and not (_lowers(ctx.base.chi2_per_dof, again.chi2_per_dof, again.misfit.dof)
                     and _joint_change(ctx, again, part_held) < _joint_change(ctx, fit, part_free)):
        return None
    return again, spec_held, off


def _joint_change(ctx: _Context, after: FitResult, psd_after: dict[str, Any] | None) -> float:
    """The change of the Allan and the PSD part from the given model's fit to ``after``, each
    in standard deviations of the given model's part (:func:`_part_sd`), summed: negative
    when the two fall together. A part not computed counts as unchanged."""
    change = (after.chi2_per_dof - ctx.base.chi2_per_dof) \
        / _part_sd(ctx.base.chi2_per_dof, after.misfit.dof)
    before_psd, after_psd = _deviance(ctx.psd_before), _deviance(psd_after)
    if before_psd is not None and after_psd is not None:
        dof = (psd_after or {}).get("bins", 0) / PSD_BIN_CORRELATION
        change += (after_psd - before_psd) / _part_sd(before_psd, dof)
    return float(change)


def _psd_rises(ctx: _Context, after: FitResult) -> bool:
    """Whether a refit raises the PSD part beyond its noise."""
    part = _psd_after(ctx, after)
    return _rises(_deviance(ctx.psd_before), _deviance(part),
                  (part or {}).get("bins", 0) / PSD_BIN_CORRELATION)


def _fit_model(ctx: _Context, spec: ModelSpec, profile_terms: set[int] | None = None,
               start: list[tuple[str, dict[str, float]]] | None = None) -> FitResult | None:
    """``spec`` fitted to the channel exactly as ``imunoise fit --model`` fits it (None where
    it cannot be fitted); ``profile_terms``: the terms whose intervals are profiled (None:
    every term's); ``start``: the one starting point, ``[(term, params)]`` in model order
    (None: the fit's own search)."""
    needs = any(get_term(n).needs_record == "temperature" for n in spec.names)
    try:
        return fit_series(ctx.x, ctx.fs_hz, spec, segment_starts=ctx.starts,
                          temperature=ctx.temp_at if needs else None, memo=ctx.memo,
                          intervals="jacobian", profile_terms=profile_terms, start=start)[0]
    except (ValueError, np.linalg.LinAlgError):
        return None


def _fit_appended(ctx: _Context, term: str, pinned: dict[str, float]
                  ) -> tuple[FitResult | None, ModelSpec]:
    spec = ModelSpec(ctx.spec.entries + (Entry(term, pinned),))
    # the suggestion reports the appended term's intervals; the white level's tells whether
    # the term took its place (_imitation)
    return _fit_model(ctx, spec, _fit_profiled(ctx, spec)), spec


def _spectrum_pin(ctx: _Context, after: FitResult, own_model: bool = True) -> Any:
    """The spectrum's f0 and Q of the resonance just appended to the model, or None where the
    spectrum does not resolve its peak (:mod:`imunoise.analysis.spectral_pins`); the model's
    other resonances stay as fitted. The other terms are the refit's, or with ``own_model``
    false the given model's fit (a refit that traded the white noise away leaves the peak
    no floor to stand on)."""
    new = len(ctx.spec)
    held = {(i, k) for i, t in enumerate(after.terms) if i != new for k in PINNED}
    model = after.params if own_model else list(ctx.base.params) + [after.params[new]]
    try:
        pins = pin_resonances(ctx.x, ctx.fs_hz, model, held, ctx.starts, ctx.memo)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None
    return next((p for p in pins if p.index == new), None)


def _psd_after(ctx: _Context, after: FitResult | None) -> dict[str, Any] | None:
    """The PSD part of a refit, computed once per model (a resonance held at its peak is
    judged by it and then reported with it)."""
    if ctx.psd_est is None or after is None:
        return None
    key = ("psd part", tuple((n, tuple(sorted(p.items()))) for n, p in after.params))
    if key not in ctx.memo:
        ctx.memo[key] = psd_parts(after.params, ctx.psd_est, ctx.fs_hz, ctx.nperseg)[1]
    return dict(ctx.memo[key])


def _psd_logp(ctx: _Context, part: dict[str, Any] | None, k: int) -> float:
    """Log p-value of the fall of the PSD deviance with ``k`` added parameters (0 when it
    does not fall), the fall divided by the larger model's dispersion
    (:func:`_dispersion` of its deviance per bin, as :func:`_lr_logp` does the Allan
    chi2's)."""
    b, a = _deviance(ctx.psd_before), _deviance(part)
    if part is None or b is None or a is None:
        return 0.0
    dof = part["bins"] / PSD_BIN_CORRELATION
    if not _lowers(b, a, dof):
        return 0.0
    return _chi2_logsf((b - a) * dof / _dispersion(a, dof), k)


def _not_computed(what: str) -> dict[str, Any]:
    return {"reason": f"{what} is not computed for every suggestion"}


def _error_after(after: FitResult, psd: dict[str, Any] | None,
                 time_domain: dict[str, Any] | None = None) -> dict[str, Any]:
    """A suggestion's ``error_after``: the refit's Allan part, its PSD part as given, and the
    time-domain part where computed (a part left out says so; the hold-out part is filled in
    for the suggestions checked)."""
    return {"chi2_per_dof": after.chi2_per_dof, "max_abs_z": float(after.max_abs_z),
            "psd": psd, "holdout": _not_computed("the hold-out part"),
            "time_domain": time_domain if time_domain is not None
            else _not_computed("the time-domain part")}


def _parts_rise(ctx: _Context, after: FitResult, psd_after: dict[str, Any] | None) -> bool:
    """Whether a refit raises the Allan or the PSD part beyond its noise."""
    return _rises(ctx.base.chi2_per_dof, after.chi2_per_dof, after.misfit.dof) \
        or _rises(_deviance(ctx.psd_before), _deviance(psd_after),
                  (psd_after or {}).get("bins", 0) / PSD_BIN_CORRELATION)


def _imitation(ctx: _Context, after: FitResult | None, index: int | None = None
               ) -> str | None:
    """Why the refit's solution is not identifiable in the sampled band (one term doing
    another's part), or None: a resonance whose peak does not lie below the Nyquist
    frequency (its centre plus half its bandwidth at or above it) is a rising spectrum, not
    a resonance; a refit that leaves the white level unresolved where the given model
    resolved it has traded the white noise to zero for the new term (at ``index``: by
    default the term appended). A Markov term at its shortest time is judged with the
    other candidates (:func:`_markov_beside_a_filter`)."""
    if after is None:
        return None
    added = after.terms[len(ctx.spec) if index is None else index]
    nyquist = 0.5 * ctx.fs_hz
    if added.term == "resonance":
        f0, q = float(added.params["f0"]), float(added.params["Q"])
        if f0 * (1.0 + 0.5 / q) >= nyquist:
            return (f"its peak ({f0:.4g} Hz, half-bandwidth {0.5 * f0 / q:.3g} Hz) does not lie "
                    f"below the Nyquist frequency {nyquist:g} Hz")
    white = get_term("white")
    for tb, ta in zip(ctx.base.terms, after.terms, strict=False):
        if tb.term == "white" and white.resolved("N", tb.ci95.get("N")) \
                and not white.resolved("N", ta.ci95.get("N")):
            return "the refit trades the white-noise level to zero for it"
    return None
