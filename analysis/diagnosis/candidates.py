"""The candidates of one round, each refitted and judged: terms added, removed or swapped, and the
remedies (cuts) of findings."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from imunoise.analysis.default_model import DEFAULT_MODEL
from imunoise.analysis.diagnosis.context import (
    _Context,
    _error_after,
    _fit_model,
    _held_at_peaks,
    _imitation,
    _Interval,
    _not_computed,
    _parts_rise,
    _psd_after,
    _psd_logp,
    _refit,
)
from imunoise.analysis.diagnosis.gathering import _filter_signature, _in_band
from imunoise.analysis.diagnosis.result import Suggestion
from imunoise.analysis.diagnosis.statistics import (
    _chi2_logsf,
    _deviance,
    _dispersion,
    _logp,
    _lr_logp,
    _rises,
    _z_range,
)
from imunoise.analysis.evidence.finding import Finding
from imunoise.analysis.fit import FitResult, fit_series
from imunoise.analysis.model_error import (
    HoldoutHalves,
    fit_half,
    measured_psd,
    psd_parts,
    time_domain_part,
)
from imunoise.analysis.spectral_band import NARROW_Q, RESONANT, SHORT_TAU_BAND, band_fit
from imunoise.analysis.spectral_pins import PINNED, pin_resonances, pinned_of
from imunoise.analysis.terms import TERMS, Entry, ModelSpec, get_term
from imunoise.analysis.terms.gauss_markov import MIN_T_SAMPLES
from imunoise.core.series import ChannelSeries


def _why(term: str, rng: tuple[float, float] | None, before: float, after: float,
         findings: list[Finding]) -> str:
    t = get_term(term)
    parts = [f"{t.effect[0].upper()}{t.effect[1:]}: {t.explanation}"]
    if rng is not None:
        lo, hi = rng
        where = f"tau = {lo:.3g} s" if np.isclose(lo, hi) else f"tau = {lo:.3g} .. {hi:.3g} s"
        parts.append(f"The measured Allan deviation departs from the model near {where}.")
    parts += [f.why for f in findings if f.significant]
    if np.isfinite(after):
        parts.append(f"Adding it brings chi2/dof from {before:.3g} to {after:.3g}.")
    return " ".join(parts)


def _line_disagreement(term: str, ev: Finding, params: dict[str, float],
                       ci: dict[str, _Interval], units: str) -> tuple[str, str]:
    """``(sentence for why, clause for the held-back reason)`` for a line whose Allan refit
    leaves no room for the amplitude the spectrum measures (its 95 % interval ends below the
    spectrum's estimate), or two empty strings.

    ADIS16405 run 3 accel_x at its final model: the spectrum shows a line at 0.443 Hz, 4.7
    times its floor in bins of 60 dof, an amplitude of 1.38e-3 m/s^2 (at least 1.0e-3 by the
    rule below). Held at that frequency, the Allan refit puts the amplitude at zero with a
    95 % upper limit of 8.7e-4 m/s^2: near tau = 0.37/f the Allan curve holds no more power
    than the terms already in the model give it. The chi2/dof then rises by the lost degree of
    freedom alone (2.50 -> 2.78), which without this sentence reads as a line that makes the
    model worse."""
    amplitude = get_term(term).amplitude
    if get_term(term).role != "line" or amplitude is None or not ev.significant \
            or "f" not in params or params["f"] != ev.params.get("f"):
        return "", ""  # only a line refitted where the spectrum found it (its frequency held)
    measured, interval = ev.params.get(amplitude), ci.get(amplitude)
    lines, nu = ev.details.get("lines") or [], ev.details.get("nu")
    if measured is None or interval is None or not np.isfinite(interval[1]) or not lines \
            or not nu or float(lines[0].get("ratio", 0.0)) <= 1.0:
        return "", ""
    # The spectrum's amplitude is noisy too: the peak bin's power over the floor, a chi-square
    # of nu dof, is (ratio - 1) floors with a standard deviation of ratio sqrt(2/nu) floors.
    # Only an Allan upper limit below the amplitude of that excess less two standard
    # deviations is a disagreement.
    ratio = float(lines[0]["ratio"])
    kept = 1.0 - 2.0 * ratio * math.sqrt(2.0 / float(nu)) / (ratio - 1.0)
    if kept <= 0.0 or not float(interval[1]) < float(measured) * math.sqrt(kept):
        return "", ""
    lo, hi = float(interval[0]), float(interval[1])
    fitted = (f"at zero (95 % upper limit {hi:.3g} {units})" if lo <= 0.0 else
              f"at {float(params[amplitude]):.3g} {units} (95 % {lo:.3g} .. {hi:.3g})")
    sentence = (f" The Allan refit leaves no room for the line the spectrum measures: it puts "
                f"its amplitude {fitted}, below the spectrum's {float(measured):.3g} {units}; "
                f"near tau = {0.37 / float(params['f']):.3g} s the Allan curve holds no more "
                f"power than the model's other terms already give it. The Allan curve and the "
                f"spectrum disagree about the model there.")
    return sentence, (f", whose refit leaves no room for the {float(measured):.3g} {units} "
                      f"the spectrum measures")


def _markov_beside_a_filter(suggestions: list[Suggestion], fs_hz: float
                            ) -> list[Suggestion]:
    """Hold back a significant Markov term whose refit stops at the shortest correlation time
    the fit allows (:data:`~imunoise.analysis.terms.gauss_markov.MIN_T_SAMPLES` sample
    periods) when an output filter is significant too.

    Such a term shows no correlation time of its own, only a spectrum falling towards the
    Nyquist frequency: what an output filter describes. Taken in the filter's place it
    leaves the model two ways to draw one fall, and the next term trades with it: on
    ADIS16405 run 1 gyro_z a second resonance beside it sat at 15.8 Hz (Q 150) on one half
    and at 8.2 Hz (Q 1.3) on the other, each half's model predicting the other at chi2/dof
    58 and 9787. Where no filter is significant (the Galaxy S5's decimation filter falls
    too close to its Nyquist frequency for one) the Markov term is the description the data
    support and stands."""
    if not any(s.significant and get_term(s.term).kind == "filter" for s in suggestions):
        return suggestions
    t_min = MIN_T_SAMPLES / fs_hz
    for s in suggestions:
        if s.term == "gauss_markov" and s.action == "add" and s.significant \
                and float(s.params.get("T", np.inf)) <= t_min * (1.0 + 1e-3):
            s.significant = False
            s.held_by = "identifiability"
            s.held_reason = (f"not identifiable: its correlation time is the shortest the fit "
                             f"allows ({t_min:.3g} s, {MIN_T_SAMPLES:g} sample periods), a "
                             f"spectrum falling towards the Nyquist frequency that the "
                             f"significant output filter describes.")
            s.why += " " + s.held_reason[0].upper() + s.held_reason[1:]
    return suggestions


def _combined_logp(ctx: _Context, sources: list[float]) -> float:
    """Log p-value of a suggestion from its sources' (log p-values): the smallest,
    Bonferroni-corrected over the sources and over the candidates (0: no evidence)."""
    if not sources:
        return 0.0
    return float(min(0.0, min(sources) + np.log(len(sources)) + np.log(ctx.n_candidates)))


def _held_back(imitation: str | None, rises: bool) -> tuple[str, str]:
    """``(held_by, held_reason)`` of a refit that would lower the error but may not be
    applied: its solution is not identifiable, or it raises a part of the error."""
    if imitation is not None:
        return "identifiability", f"not identifiable: {imitation}."
    if rises:
        return "rise", "it raises a part of the error beyond its noise."
    return "", ""


def _suggest(ctx: _Context, term: str, alpha: float) -> Suggestion:
    """Refit with ``term`` and weigh the fall of the error with the evidence."""
    base, before = ctx.base, ctx.base.chi2_per_dof
    after, spec, pinned, pinned_ci = _refit(ctx, term)
    k = len(get_term(term).params)
    regressor = get_term(term).role == "regressor"
    falls = after is not None and bool(np.isfinite(after.chi2_per_dof)) \
        and after.chi2_per_dof < before
    sources: list[float] = []
    if falls and not regressor and after is not None:
        # A term that leaves the misfit per degree of freedom no better is no suggestion,
        # even if the raw chi2 fell (it does whenever the given model is wrong anyway).
        sources.append(_lr_logp(base, after, k))
    psd_after = None if regressor else _psd_after(ctx, after)
    psd_logp = _psd_logp(ctx, psd_after, k)
    if psd_logp < 0.0:
        # the spectrum knows more than the Allan curve about lines, resonances and filters
        sources.append(psd_logp)
    ev = ctx.by_term.get(term)
    if ev is not None:
        sources.append(_logp(ev.p_value))
    if get_term(term).role == "line" and ev is not None and not ev.significant \
            and after is not None and _in_band(after, ev, len(ctx.spec)):
        # A sinusoid big enough to bend the Allan curve is a line in the spectrum; with no
        # line where the refit put it, the Allan improvement is some other bump.
        sources = [_logp(ev.p_value)]
    logp = _combined_logp(ctx, sources)
    params: dict[str, float] = {}
    ci: dict[str, tuple[float, float]] = {}
    chi_after = float("nan")
    if after is not None:
        tf = after.terms[len(ctx.spec)]  # the added term (the model may repeat its name)
        params, ci = dict(tf.params), dict(tf.ci95)
        # Parameters the evidence pinned (held fixed in the refit) take its interval.
        ci.update(pinned_ci)
        chi_after = after.chi2_per_dof
    elif ev is not None:
        params = dict(ev.params)
    rng = _z_range(base, after) if after is not None and not regressor else None
    supporting = [ev] if ev is not None else []
    why = _why(term, rng, before, chi_after, supporting)
    imitation = _imitation(ctx, after)
    rises = after is not None and _parts_rise(ctx, after, psd_after)
    # Applied, a significant term must lower the Allan chi2/dof, not only the PSD part: a
    # term the spectrum wants that leaves the Allan curve no better per degree of freedom
    # (ADIS16405 run 4 gyro_z: a fourth resonance at 0.49 Hz, PSD part 23.5 -> 21.0, Allan
    # 2.37 -> 2.43) would show the user an error that rose.
    allan_up = after is not None and not rises and not falls \
        and bool(np.isfinite(after.chi2_per_dof))
    held_by, held_reason = _held_back(imitation, rises or allan_up)
    if imitation is not None:
        why += f" Not identifiable: {imitation}."
    if rises:
        why += " It raises a part of the error beyond its noise."
    elif allan_up:
        why += (f" It does not lower the Allan chi2/dof ({before:.3g} -> {chi_after:.3g}), "
                f"so applying it would not lower the error the fit reports.")
        sentence, clause = _line_disagreement(term, ev, params, ci, ctx.units) \
            if ev is not None and after is not None else ("", "")
        why += sentence
        if imitation is None:
            held_reason = f"it does not lower the Allan chi2/dof{clause}."
    error_after = {} if after is None else _error_after(after, psd_after)
    if pinned and get_term(term).kind == "filter":
        held = ", ".join(f"{k} = {v:g}" for k, v in pinned.items())
        why += f" The recording's device configuration states this filter ({held}), so it " \
               f"is held, not fitted."
    return Suggestion(
        term=term, params=params, ci95=ci, chi2_per_dof_before=before,
        chi2_per_dof_after=chi_after, p_value=float(np.exp(logp)), log_p=logp,
        # significant only when applying it really lowers the error the fit reports
        significant=bool(logp < np.log(alpha) and (falls or psd_logp < 0.0)
                         and not rises and not allan_up and imitation is None),
        why=why,
        evidence=[f.kind for f in supporting if f.significant], fit=after,
        apply={"model": spec.text(), "args": []}, held_by=held_by, held_reason=held_reason,
        error_after=error_after)


def _first_job(shared: tuple[_Context, float, HoldoutHalves | None], item: tuple[str, Any]
               ) -> Any:
    """One job of the diagnosis's first map, as a job map calls it: a candidate's
    :func:`_suggest` (``("term", name)``), a filter swap's :func:`_swap` (``("swap",
    (index, name))``), the spectrum's model of the resonance band (``("band", None)``,
    :func:`_band_refit`), or a hold-out half of the given model
    (``("half", k)``, :func:`imunoise.analysis.model_error.fit_half`), which needs no
    candidate and so runs beside them."""
    ctx, alpha, halves = shared
    kind, what = item
    if kind == "half":
        assert halves is not None  # halves are only asked for when set up
        return fit_half(halves.shared(), what)
    if kind == "swap":
        index, new = what
        return _swap(ctx, index, new, alpha)
    if kind == "band":
        return _band_refit(ctx, alpha)
    return _suggest(ctx, what, alpha)


def _remedy(ctx: _Context, finding: Finding, units: str, alpha: float) -> Suggestion:
    """A warm-up or bias step as a suggestion: not a term but a cut of the record (its
    ``apply.args``), refitted exactly as ``imunoise fit --model M ARGS`` fits it."""
    step = finding.kind == "bias_step"
    # a cut counts from the first sample analysed; the step's time from the time origin
    at = float(finding.params["t_s"] - ctx.time_origin_s if step
               else finding.details["skip_s"])
    args = ["--split" if step else "--skip", f"{at:.10g}"]
    series = ChannelSeries("x", units, ctx.fs_hz, ctx.x, ctx.starts).windowed(
        skip_s=0.0 if step else float(args[1]), split_s=[float(args[1])] if step else [])
    before = ctx.base.chi2_per_dof
    try:
        after, _ = fit_series(series.values, ctx.fs_hz, ctx.spec,
                              segment_starts=series.segment_starts, intervals="jacobian")
        chi_after = after.chi2_per_dof
    except (ValueError, np.linalg.LinAlgError):
        after, chi_after = None, float("nan")
    falls = bool(np.isfinite(chi_after) and chi_after < before)
    logp = min(0.0, _logp(finding.p_value) + float(np.log(ctx.n_candidates)))
    why = finding.why
    if np.isfinite(chi_after):
        why += f" Doing so brings chi2/dof from {before:.3g} to {chi_after:.3g}."
    # The Allan curve barely sees a step (a random walk takes it in), so the cut is judged by
    # the part that does: the transient test on the cut record under its own refit. It must
    # no longer find a transient, and the Allan part must not rise beyond its noise. Like a
    # term, a cut may raise neither the Allan nor the PSD part beyond its noise: ADIS16405
    # run 3 accel_z, cut at 289 s by a step that lowered the Allan part (1.14 -> 0.89): the
    # cut record's refit moved a resonance from 0.002 Hz to 1.77 Hz, PSD part 2.62 -> 3.90
    td_after: dict[str, Any] | None = None
    psd_after: dict[str, Any] | None = None
    clears = False
    rises = False
    if after is not None:
        td_after = time_domain_part(series.values, ctx.fs_hz, after.params,
                                    series.segment_starts, units)
        p_after = td_after.get("p")
        clears = bool(p_after is not None and p_after >= alpha
                      and not _rises(before, chi_after, after.misfit.dof))
        if clears and not falls:
            why += (f" The cut record shows no transient (time-domain p {p_after:.2g}) and "
                    f"the Allan part stays within its noise.")
        if ctx.psd_est is not None:
            est, nperseg = measured_psd(series.values, ctx.fs_hz, series.segment_starts)
            psd_after = psd_parts(after.params, est, ctx.fs_hz, nperseg)[1]
        rises = _parts_rise(ctx, after, psd_after)
    held_by, held_reason = _held_back(None, rises)
    if rises:
        why += " The cut raises a part of the error beyond its noise."
    names = ("t_s", "size") if step else ("tau_s", "amplitude")
    ci = {k: (float(finding.details[f"{k}_ci95"][0]), float(finding.details[f"{k}_ci95"][1]))
          for k in names if np.all(np.isfinite(finding.details.get(f"{k}_ci95", [np.nan])))}
    return Suggestion(
        term=finding.kind, params=dict(finding.params), ci95=ci,
        chi2_per_dof_before=before, chi2_per_dof_after=chi_after,
        p_value=float(np.exp(logp)), log_p=logp,
        significant=bool(logp < np.log(alpha) and (falls or clears) and not rises), why=why,
        evidence=[finding.kind] if finding.significant else [], fit=after,
        apply={"model": ctx.spec.text(), "args": args}, action="cut",
        error_after={} if after is None
        else _error_after(after, psd_after if psd_after is not None
                          else _not_computed("the PSD part"), td_after),
        held_by=held_by, held_reason=held_reason)


def _unresolved_terms(ctx: _Context) -> list[int]:
    """Indices of the given model's terms that may be dropped: an amplitude whose 95 %
    interval reaches zero, in a term the user did not ask for by name. The default model's
    terms (:data:`~imunoise.analysis.default_model.DEFAULT_MODEL`) are the coefficients every
    datasheet quotes, reported as an upper bound when unresolved; a term with a parameter the
    user held was asked for; filters have no amplitude; a regressor is the user's record."""
    out = []
    for i, (entry, tf) in enumerate(zip(ctx.spec.entries, ctx.base.terms, strict=True)):
        term = get_term(entry.name)
        if entry.name in DEFAULT_MODEL or entry.fixed or term.kind == "filter" \
                or term.role == "regressor":
            continue
        if not term.resolved(term.amplitude, tf.ci95.get(term.amplitude)):
            out.append(i)
    return out


def _removal(ctx: _Context, index: int, alpha: float) -> Suggestion:
    """Term ``index`` of the given model dropped and the rest refitted, exactly as ``imunoise
    fit --model`` fits the remaining model (its ``apply.model``).

    The term's amplitude interval reaches zero, so the record shows no more than an upper
    bound of it. It goes (``significant``) when the data do not need it: the rise of chi2
    without it, chi-square with the term's free parameters as degrees of freedom, has
    ``p >= alpha`` (``p_value``; Bonferroni over the candidates does not apply, a removal
    claims no effect), the chi2 per degree of freedom does not rise (the simpler model must
    not look worse to the user who applies it), and the PSD part does not rise beyond its
    noise."""
    entries = ctx.spec.entries
    entry, label = entries[index], ctx.spec.labels[index]
    spec = ModelSpec(entries[:index] + entries[index + 1:])
    before = ctx.base.chi2_per_dof
    k = len(get_term(entry.name).params) - len(entry.fixed)
    after = _fit_model(ctx, spec)
    tf = ctx.base.terms[index]
    amp = get_term(entry.name).amplitude
    bound = tf.ci95.get(amp, (float("nan"),) * 2)[1]
    why = (f"The record does not resolve {label}: its {amp} has a 95 % interval reaching "
           f"zero (upper bound {bound:.3g}).")
    if after is None:
        return Suggestion(term=entry.name, params=dict(tf.params), ci95=dict(tf.ci95),
                          chi2_per_dof_before=before, chi2_per_dof_after=float("nan"),
                          p_value=0.0, log_p=-np.inf, significant=False,
                          why=why + " The model without it could not be fitted.",
                          apply={"model": spec.text(), "args": []}, action="remove",
                          label=label)
    rise = max(float(after.misfit.chi2 - ctx.base.misfit.chi2), 0.0)
    logp = _chi2_logsf(rise, max(k, 1)) if rise > 0 else 0.0
    psd_after = _psd_after(ctx, after)
    rises = _parts_rise(ctx, after, psd_after)
    needed = logp < np.log(alpha)
    # a suggestion applied must not make the error the user watches larger: the chi2 per
    # degree of freedom of the simpler model may not exceed the given model's
    worse = bool(after.chi2_per_dof > before)
    why += (f" Without it chi2 rises by {rise:.3g} on {k} parameter(s) (p = "
            f"{np.exp(logp):.2g}) and chi2/dof goes from {before:.3g} to "
            f"{after.chi2_per_dof:.3g}.")
    if needed:
        why += " The curve needs it all the same: keep it."
    elif rises:
        why += " Dropping it raises a part of the error beyond its noise: keep it."
    elif worse:
        why += " Dropping it raises the chi2 per degree of freedom: keep it as an upper bound."
    return Suggestion(
        term=entry.name, params=dict(tf.params), ci95=dict(tf.ci95),
        chi2_per_dof_before=before, chi2_per_dof_after=after.chi2_per_dof,
        p_value=float(np.exp(logp)), log_p=logp,
        significant=bool(not needed and not rises and not worse), why=why, fit=after,
        apply={"model": spec.text(), "args": []}, action="remove", label=label,
        error_after=_error_after(after, psd_after))


def _swaps(spec: ModelSpec, base: FitResult,
           sensor_filter: tuple[str, dict[str, float]] | None,
           findings: Sequence[Finding] = (),
           psd: dict[str, Any] | None = None) -> list[tuple[int, str]]:
    """``(index, other term)`` for each term that may replace one of the given model's: each
    other kind of output filter, when the model fails (a filter the user held or the
    device's configuration states stays); a wandering resonance for each resonance whose
    peak the evidence finds moving (a significant ``resonance_drift`` finding); and an
    antiresonance for each resonance whose spectrum ``psd`` (the given model's
    ``error.psd``) misses on both sides of its peak in opposite directions, as zeros beside
    the poles leave it (:func:`_skirts_miss`)."""
    out: list[tuple[int, str]] = []
    if base.failures and sensor_filter is None:
        filters = [n for n, t in TERMS.items() if t.kind == "filter" and t.usable()]
        out += [(i, other) for i, entry in enumerate(spec.entries)
                if get_term(entry.name).kind == "filter" and not entry.fixed
                for other in filters if other != entry.name]
    for f in findings:
        i = f.details.get("term_index")
        if f.kind == "resonance_drift" and f.significant and isinstance(i, int) \
                and i < len(spec.entries) and spec.entries[i].name == "resonance":
            out.append((i, "wandering_resonance"))
    misses = (psd or {}).get("misses") or []
    for i, (name, params) in enumerate(base.params):
        if name == "resonance" and _skirts_miss(misses, float(params["f0"])):
            out.append((i, "antiresonance"))
    return out


SKIRT_SHARE = 0.05
"""Share of the PSD part's deviance each of a peak's two skirt misses carries before an
antiresonance is offered in the resonance's place."""


def _skirts_miss(misses: Sequence[dict[str, Any]], f0: float) -> bool:
    """Whether the PSD misses (``error.psd.misses``) hold, reaching into the octave either
    side of ``f0`` (Hz), a run centred below the peak and one centred above it in opposite
    directions, each with at least :data:`SKIRT_SHARE` of the deviance: the spectrum
    dipping on one side of the peak and standing out on the other, which no resonance's
    level or width makes."""
    sides: dict[str, set[str]] = {"under": set(), "over": set()}
    for m in misses:
        lo, hi = (float(v) for v in m["f_hz"])
        if float(m.get("deviance_share") or 0.0) < SKIRT_SHARE \
                or hi < f0 / 2.0 or lo > 2.0 * f0:
            continue
        sides["under" if np.sqrt(lo * hi) < f0 else "over"].add(str(m["direction"]))
    return any(u != o for u in sides["under"] for o in sides["over"])


@dataclass(frozen=True)
class _Weighed:
    """The evidence of a replacement's refit: its log p-value from the fall of the Allan
    chi2 (as that of ``extra`` parameters) and of the PSD part, whether the Allan chi2/dof
    falls, the refit's PSD part, and whether a part rises beyond its noise or the Allan
    part does not fall at all."""

    logp: float
    falls: bool
    psd_after: dict[str, Any] | None
    psd_logp: float
    rises: bool
    allan_up: bool

    def held_back(self, imitation: str | None) -> tuple[str, str]:
        """``(held_by, held_reason)`` of :class:`Suggestion`."""
        held_by, reason = _held_back(imitation, self.rises or self.allan_up)
        if self.allan_up and imitation is None:
            reason = "it does not lower the Allan chi2/dof."
        return held_by, reason

    def significant(self, alpha: float, imitation: str | None) -> bool:
        """The rules an added term meets: the evidence beyond ``alpha``, the Allan or the
        PSD part lower, no part higher beyond its noise, the solution identifiable."""
        return bool(self.logp < np.log(alpha) and (self.falls or self.psd_logp < 0.0)
                    and not self.rises and not self.allan_up and imitation is None)


def _weighed(ctx: _Context, after: FitResult, extra: int) -> _Weighed:
    """:class:`_Weighed` of a refit that replaces terms of the given model."""
    drop = float(ctx.base.misfit.chi2 - after.misfit.chi2)
    falls = bool(np.isfinite(after.chi2_per_dof) and after.chi2_per_dof < ctx.base.chi2_per_dof)
    sources = [_chi2_logsf(drop / _dispersion(after.chi2_per_dof, after.misfit.dof), extra)] \
        if falls and drop > 0 else []
    psd_after = _psd_after(ctx, after)
    psd_logp = _psd_logp(ctx, psd_after, extra)
    if psd_logp < 0.0:
        sources.append(psd_logp)
    rises = _parts_rise(ctx, after, psd_after)
    allan_up = not rises and not falls and bool(np.isfinite(after.chi2_per_dof))
    return _Weighed(_combined_logp(ctx, sources), falls, psd_after, psd_logp, rises, allan_up)


def _psd_clause(ctx: _Context, psd_after: dict[str, Any] | None) -> str:
    """`` and the PSD part from B to A`` where both parts are known, else nothing."""
    b, a = _deviance(ctx.psd_before), _deviance(psd_after)
    return "" if b is None or a is None else f" and the PSD part from {b:.3g} to {a:.3g}"


def _replaced(spec: ModelSpec, index: int, entry: Entry) -> ModelSpec:
    """``spec`` with its entry at ``index`` replaced by ``entry``."""
    return ModelSpec(spec.entries[:index] + (entry,) + spec.entries[index + 1:])


def _swap(ctx: _Context, index: int, new: str, alpha: float) -> Suggestion:
    """The given model's output filter (term ``index``) replaced by filter ``new`` and the
    model refitted, as ``imunoise fit --model apply.model`` fits it.

    The round that first adds a filter picks among the filter kinds by differences of the
    Allan chi2 of a few per cent, while an effect not yet modelled (a bench line, a
    resonance) dominates the misfit; once that is modelled a different filter can describe
    the shortest taus far better (ADIS16405 run 1 accel_z with its line and 10 Hz
    resonance: chi2/dof 21.5 with a one-pole low-pass, 5.0 with a Bartlett window). The
    two models are not nested and have the same number of parameters, so the chi2 drop is
    judged as that of one parameter (Bonferroni over the candidates), beside the fall of the
    PSD part; it is significant under the rules an added term meets: the chi2/dof falls,
    no part rises beyond its noise, the white level stays resolved, and (checked with the
    added terms) the hold-out part does not rise.

    A term that refines another (:attr:`~imunoise.analysis.terms.base.Term.replaces`: a
    wandering resonance for a resonance whose peak moves, an antiresonance for one whose
    skirts the spectrum refuses) comes with the shape the spectrum
    gives it (:mod:`imunoise.analysis.spectral_pins`: centre, width and wander held, the
    power left to the Allan refit), as a suggested resonance is held at its peak; the Allan
    curve alone barely tells a moving peak from a fixed one; an antiresonance (zeros beside a
    resonance's poles) likewise, its zeros from the spectrum. Its chi2 drop is judged as that
    of the parameters it adds (one: a wander's spread, the zeros' fa)."""
    old = ctx.spec.labels[index]
    before = ctx.base.chi2_per_dof
    label = f"{old} by {new}"
    refines = get_term(new).replaces is not None
    # the parameters a refinement adds (a wander: spread; zeros: fa)
    extra = len(get_term(new).params) - len(get_term(ctx.spec.names[index]).params) \
        if refines else 1
    shape: dict[str, float] = {}
    shape_ci: dict[str, _Interval] = {}
    if refines:
        pin = _refinement_pin(ctx, index, new)
        if pin is None:
            spec = _replaced(ctx.spec, index, Entry(new, {}))
            return _swap_not_offered(new, before, label, spec,
                                     f"The spectrum does not resolve {old}'s peak as a "
                                     f"{new}'s.")
        shape, shape_ci = pinned_of(pin.params), dict(pin.ci95)
    spec = _replaced(ctx.spec, index, Entry(new, shape))
    profiled = {i for i, n in enumerate(spec.names) if n == "white"} | {index}
    # a refinement starts from the given model's solution, its term's power where the term
    # it refines had it (from the smaller model the new term would start at zero, where its
    # log-amplitude has no gradient)
    start = None
    if refines:
        start = list(ctx.base.params)
        start[index] = (new, {**start[index][1], **shape})
    after = _fit_model(ctx, spec, profiled, start)
    if after is not None:
        # a different filter moves the background under a resonance: where the refit puts
        # one beside its spectral peak, it is held there as an appended one would be
        at_peaks = _held_at_peaks(ctx, spec, after, set(range(len(spec))), profiled)
        if at_peaks is not None:
            after, spec = at_peaks[0], at_peaks[1]
    if refines:
        why = get_term(new).refinement_reason(old, shape)
    else:
        why = f"The shortest taus may follow a {new} filter better than the model's {old}."
    if after is None:
        return _swap_not_offered(new, before, label, spec,
                                 why + " The model with it could not be fitted.")
    w = _weighed(ctx, after, extra)
    tf = after.terms[index]
    # a filter's reason is the sentence itself; a refinement's what the evidence showed
    why = (why + " " if refines else "") + (
        f"Replacing {old} by {'an' if new[0] in 'aeiou' else 'a'} {new}"
        f"{'' if refines else ' filter'} brings chi2/dof from "
        f"{before:.3g} to {after.chi2_per_dof:.3g}")
    why += _psd_clause(ctx, w.psd_after)
    why += (f" with {'one parameter' if extra == 1 else f'{extra} parameters'} more."
            if refines else " with as many parameters.")
    imitation = _imitation(ctx, after, index)
    held_by, held_reason = w.held_back(imitation)
    if held_reason:
        why += " " + held_reason[0].upper() + held_reason[1:]
    return Suggestion(
        # a held shape's interval is the spectrum's, as a pinned suggestion's is
        term=new, params=dict(tf.params), ci95={**tf.ci95, **shape_ci},
        chi2_per_dof_before=before,
        chi2_per_dof_after=after.chi2_per_dof, p_value=float(np.exp(w.logp)), log_p=w.logp,
        significant=w.significant(alpha, imitation),
        why=why, fit=after, apply={"model": spec.text(), "args": []}, action="replace",
        label=label, held_by=held_by, held_reason=held_reason,
        error_after=_error_after(after, w.psd_after))


BAND_PSD_FAILS = 3.0
"""The PSD part (deviance per bin) from which the spectrum's model of the resonance band is
tried: the part of a model that describes the spectrum is about 1."""


def wants_band_refit(base: FitResult, psd: dict[str, Any] | None) -> bool:
    """Whether the diagnosis tries the spectrum's model of the resonance band
    (:func:`_band_refit`): the given model holds a narrow resonance in the band only the
    Allan curve's shortest taus see (:data:`~imunoise.analysis.spectral_band.SHORT_TAU_BAND`)
    and misses the spectrum (its PSD part ``psd``, the given model's ``error.psd``, at least
    :data:`BAND_PSD_FAILS`)."""
    dev = _deviance(psd)
    return dev is not None and dev >= BAND_PSD_FAILS and any(
        n in RESONANT and float(ps["Q"]) >= NARROW_Q
        and float(ps["f0"]) >= SHORT_TAU_BAND * base.fs_hz for n, ps in base.params)


def _band_refit(ctx: _Context, alpha: float) -> Suggestion:
    """The model's resonances and output filter replaced by the spectrum's model of their
    band (:mod:`imunoise.analysis.spectral_band`: a wandering mode, two modes, a shelf, the
    filter), every parameter of those terms held at the spectrum's values, the white level
    and the long-tau terms refitted to the Allan curve as ``imunoise fit --model
    apply.model`` fits them. Judged as an added term is, its parameters counted as those
    the band's terms have beyond the given ones."""
    before = ctx.base.chi2_per_dof
    band = band_fit(ctx.x, ctx.fs_hz, ctx.base.params, ctx.starts, ctx.memo)
    label = "band from the spectrum"
    if band is None or band.structure == "as fitted":
        return _swap_not_offered("wandering_resonance", before, label, ctx.spec,
                                 "The spectrum offers no better model of the resonance band.")
    kept = [e for i, e in enumerate(ctx.spec.entries) if i not in band.replaced]
    spec = ModelSpec(tuple(kept) + tuple(Entry(n, dict(ps)) for n, ps in band.terms))
    first = len(kept)
    profiled = {i for i, n in enumerate(spec.names) if n == "white"}
    after = _fit_model(ctx, spec, profiled)
    lo = band.band_hz[0]
    why = (f"Above {lo:.3g} Hz the spectrum holds more than the Allan curve can part: fitted "
           f"to the spectrum there ({band.structure}), the band's terms miss it by a Whittle "
           f"deviance of {band.deviance_per_bin:.3g} per bin against "
           f"{band.given_deviance_per_bin:.3g} for the model's own terms refitted to it.")
    if after is None:
        return _swap_not_offered("wandering_resonance", before, label, spec,
                                 why + " The model with them could not be fitted.")
    extra = max(band.added, 1)
    w = _weighed(ctx, after, extra)
    why += f" Held in the model they bring chi2/dof from {before:.3g} to {after.chi2_per_dof:.3g}"
    why += _psd_clause(ctx, w.psd_after)
    why += f" with {extra} parameter{'' if extra == 1 else 's'} more."
    imitation = next((r for i in range(first, len(spec))
                      if (r := _imitation(ctx, after, i)) is not None), None)
    held_by, held_reason = w.held_back(imitation)
    if held_reason:
        why += " " + held_reason[0].upper() + held_reason[1:]
    main = next((i for i in range(first, len(spec))
                 if spec.names[i] == "wandering_resonance"), first)
    tf = after.terms[main]
    return Suggestion(
        # every parameter of the band is held at the spectrum's value: no interval is
        # stated (a held parameter's would be the value itself); the halves' values are
        # what the hold-out part compares
        term=spec.names[main], params=dict(tf.params), ci95={},
        chi2_per_dof_before=before, chi2_per_dof_after=after.chi2_per_dof,
        p_value=float(np.exp(w.logp)), log_p=w.logp,
        significant=w.significant(alpha, imitation),
        why=why, fit=after, apply={"model": spec.text(), "args": []}, action="replace",
        label=label, held_by=held_by, held_reason=held_reason,
        error_after=_error_after(after, w.psd_after))


def _swap_not_offered(new: str, before: float, label: str, spec: ModelSpec, why: str
                      ) -> Suggestion:
    """A swap that has no refit to judge it by: never significant, ``why`` says so."""
    return Suggestion(term=new, params={}, ci95={}, chi2_per_dof_before=before,
                      chi2_per_dof_after=float("nan"), p_value=1.0, log_p=0.0,
                      significant=False, why=why, apply={"model": spec.text(), "args": []},
                      action="replace", label=label)


def _refinement_pin(ctx: _Context, index: int, new: str) -> Any:
    """The spectrum's shape of term ``new`` in the place of the given model's term ``index``
    (the other terms as fitted, their peaks held), or None where the spectrum does not
    resolve it (:func:`imunoise.analysis.spectral_pins.pin_resonances`)."""
    model = list(ctx.base.params)
    _, params = model[index]
    start = {k: v for k, v in get_term(new).small_default.items() if k not in params}
    if "spread" in start:  # a wander of half the peak's width to start from
        start["spread"] = 0.5 * float(params["f0"]) / float(params["Q"])
    model[index] = (new, {**params, **start})
    held = {(i, k) for i in range(len(model)) if i != index for k in PINNED}
    try:
        pins = pin_resonances(ctx.x, ctx.fs_hz, model, held, ctx.starts, ctx.memo)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None
    return next((p for p in pins if p.index == index), None)


def _candidates(names: list[str], base: FitResult, filt: Finding | None, has_temperature: bool,
                sensor_filter: tuple[str, dict[str, float]] | None) -> list[str]:
    """The terms to try: every additive term not in the model (a repeatable one, such as a
    second Markov time constant or a second resonance, even if it is; a term that refines
    another only in its place, :func:`_swaps`), and the output
    filters when the shortest taus show one (only the device's own when its configuration
    states it); the filter the record's other channels measure
    (:mod:`imunoise.analysis.terms.chain_filter`) whenever they do."""
    candidates = [n for n, t in TERMS.items() if (n not in names or t.repeatable)
                  and t.kind == "additive" and t.replaces is None
                  and (t.needs_record != "temperature" or has_temperature)]
    if not any(get_term(n).kind == "filter" for n in names):
        filters = [n for n, t in TERMS.items() if t.kind == "filter" and t.usable()]
        if sensor_filter is not None:
            candidates.append(get_term(sensor_filter[0]).name)
        elif _filter_signature(base, filt):
            candidates += filters
        else:
            # a response the record's other channels measure is evidence of its own
            candidates += [n for n in filters if get_term(n).needs_record == "channels"]
    return candidates
