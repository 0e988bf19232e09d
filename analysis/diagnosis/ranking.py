"""The ranking of a round's suggestions: the simplest explanation first, a filter re-chosen where
two describe the curve alike, and a weak line that comes with the term that resolves it."""

from __future__ import annotations

from typing import Any

import numpy as np

from imunoise.analysis import distributions as dist
from imunoise.analysis.diagnosis.candidates import (
    _markov_beside_a_filter,
    _remedy,
    _removal,
    _replaced,
    _unresolved_terms,
)
from imunoise.analysis.diagnosis.context import (
    _Context,
    _error_after,
    _fit_model,
    _fit_profiled,
    _imitation,
    _parts_rise,
    _psd_after,
)
from imunoise.analysis.diagnosis.result import Suggestion
from imunoise.analysis.diagnosis.statistics import (
    PSD_BIN_CORRELATION,
    _chi2_logsf,
    _deviance,
    _dispersion,
    _lowers,
    _rises,
)
from imunoise.analysis.evidence.finding import Finding
from imunoise.analysis.fit import FitResult
from imunoise.analysis.model_error import HoldoutHalves
from imunoise.analysis.terms import TERMS, Entry, ModelSpec, get_term, parse_model


def _second_job(shared: tuple[_Context, list[Suggestion], float, str,
                              HoldoutHalves | dict[str, Any] | None, list[Any]],
                step: str) -> Any:
    """One job of the diagnosis's second map, once the candidates are ranked: the ranked
    suggestions with the next spectral line joined to the top term (``"line"``,
    :func:`_with_next_line`), or the given model's ``error.holdout`` from its halves' fits
    (``"holdout"``, :meth:`HoldoutHalves.part`)."""
    ctx, suggestions, alpha, units, halves, half_fits = shared
    if step == "line":
        return _with_next_line(ctx, suggestions, alpha, units)
    assert isinstance(halves, HoldoutHalves)  # only asked for when set up
    return halves.part(half_fits, job_map=ctx.job_map)


RECHOSEN_FILTER_EXCESS = 0.5
"""Share of the plain addition's misfit excess (chi2/dof - 1) that a term added with another
filter may leave (:func:`_filter_rechosen`)."""


def _filter_job(shared: tuple[_Context, ModelSpec], item: tuple[int, str]
                ) -> FitResult | None:
    """The model ``shared[1]`` with its filter at ``item[0]`` replaced by ``item[1]``,
    fitted (a job of :func:`_filter_rechosen`)."""
    ctx, spec = shared
    index, new = item
    swapped = _replaced(spec, index, Entry(new, {}))
    return _fit_model(ctx, swapped, _fit_profiled(ctx, swapped))


def _filter_rechosen(ctx: _Context, suggestions: list[Suggestion], alpha: float
                     ) -> list[Suggestion]:
    """The suggestions with, before the first significant one where it adds a term to a
    model that has an output filter, that term added with the filter replaced by another
    kind when the other describes the model with the term markedly better.

    The round that added the filter chose its kind while a line or a resonance dominated the
    misfit; once the new term is there the shortest taus may follow another filter far
    better (ADIS16405 run 1 accel_x: a one-pole low-pass chosen first, then its 0.56 Hz line
    and 10 Hz resonance, chi2/dof 55.3; a moving average in the low-pass's place, 11.5).
    Offered as a separate replacement, that fix would cost the user a round of its own. The
    combined suggestion is offered where the other filter's refit lies below the plain
    addition's by more than the test's drop (its chi2 drop scaled by the dispersion, one
    degree of freedom, Bonferroni over the filters tried, at ``alpha``), lowers its chi2/dof
    beyond noise and leaves at most :data:`RECHOSEN_FILTER_EXCESS` of the plain addition's
    excess over 1, raises no part of the error beyond the given model's, leaves the white
    level resolved and does not raise the PSD part beyond the plain addition's; it is
    checked against the hold-out part like any addition, the plain addition next in line.
    A filter the user held or the device's configuration states stays.

    The share keeps a filter that only stands in for a term still missing from being
    swapped in: on the ADIS16405 accelerometers, with the bench line added before the 10 Hz
    resonance, a one-pole low-pass takes part of the resonance's bump and leaves 73-81 % of
    the moving average's excess (six channels), a choice the next round undid, and a
    Bartlett window against a moving average of about one tap 52-68 % (three); where the
    new term made the old filter wrong, the other left 2-43 % (eleven; run 1 accel_x 19 %)."""
    top = next((s for s in suggestions if s.significant), None)
    if top is None or top.action != "add" or top.fit is None or top.apply.get("args") \
            or ctx.sensor_filter is not None or get_term(top.term).kind == "filter":
        return suggestions
    spec = parse_model(str(top.apply["model"]))
    kinds = [n for n, t in TERMS.items() if t.kind == "filter" and t.usable()]
    trials = [(i, other) for i, e in enumerate(spec.entries[:len(ctx.spec)])
              if get_term(e.name).kind == "filter" and not e.fixed
              for other in kinds if other != e.name]
    if not trials:
        return suggestions
    fits = ctx.job_map(_filter_job, (ctx, spec), trials)
    done = [(f, t) for f, t in zip(fits, trials, strict=True)
            if f is not None and np.isfinite(f.chi2_per_dof)]
    if not done:
        return suggestions
    after, (index, new) = min(done, key=lambda ft: ft[0].misfit.chi2)
    drop = float(top.fit.misfit.chi2 - after.misfit.chi2)
    scaled = drop / _dispersion(after.chi2_per_dof, after.misfit.dof)
    logp = _chi2_logsf(scaled, 1) + float(np.log(len(trials))) if drop > 0 else 0.0
    psd_after = _psd_after(ctx, after)
    psd_top = top.error_after.get("psd")
    if not (logp < np.log(alpha)
            and _lowers(top.chi2_per_dof_after, after.chi2_per_dof, after.misfit.dof)
            and after.chi2_per_dof - 1.0 < RECHOSEN_FILTER_EXCESS * (top.chi2_per_dof_after - 1.0)
            and not _parts_rise(ctx, after, psd_after)
            and not _rises(_deviance(psd_top), _deviance(psd_after),
                           (psd_after or {}).get("bins", 0) / PSD_BIN_CORRELATION)
            and _imitation(ctx, after) is None):
        return suggestions
    old = ctx.spec.labels[index]
    combined_spec = _replaced(spec, index, Entry(new, {}))
    why = (f"With it, a {new} filter in {old}'s place describes the shortest taus better: "
           f"chi2/dof {top.chi2_per_dof_after:.3g} -> {after.chi2_per_dof:.3g}"
           f"{_psd_change(psd_top, psd_after)} with as many parameters, so the two changes "
           f"are applied together.")
    return _before_top(ctx, suggestions, top, combined_spec, after, psd_after, why,
                       f"{top.term}, {old} by {new}", list(top.evidence))


def _psd_change(before: dict[str, Any] | None, after: dict[str, Any] | None) -> str:
    """`` and the PSD part from B to A`` for a suggestion's text, or nothing where either
    part is not computed."""
    b, a = _deviance(before), _deviance(after)
    return "" if b is None or a is None else f" and the PSD part from {b:.3g} to {a:.3g}"


def _before_top(ctx: _Context, suggestions: list[Suggestion], top: Suggestion,
                spec: ModelSpec, after: FitResult, psd_after: dict[str, Any] | None,
                why: str, label: str, evidence: list[str]) -> list[Suggestion]:
    """The suggestions with, just before ``top``, ``top``'s term applied together with a
    further change: the model ``spec``, fitted as ``after``. Its parameters are the
    refit's, those ``top`` held keep ``top``'s intervals; ``why`` follows ``top``'s text."""
    added = len(ctx.spec)
    tf = after.terms[added]
    held = spec.entries[added].fixed
    combined = Suggestion(
        term=top.term, params=dict(tf.params),
        ci95={**tf.ci95, **{k: v for k, v in top.ci95.items() if k in held}},
        chi2_per_dof_before=top.chi2_per_dof_before, chi2_per_dof_after=after.chi2_per_dof,
        p_value=top.p_value, log_p=top.log_p, significant=True, why=f"{top.why} {why}",
        evidence=evidence, fit=after, apply={"model": spec.text(), "args": []},
        action="add", label=label, error_after=_error_after(after, psd_after))
    at = suggestions.index(top)
    return suggestions[:at] + [combined] + suggestions[at:]


def _with_next_line(ctx: _Context, suggestions: list[Suggestion], alpha: float, units: str
                    ) -> list[Suggestion]:
    """The suggestions with, before the first significant one where it adds a term other
    than a line, that term added together with the spectrum's strongest line not yet in the
    model, when the two describe the record better than the term alone.

    A bench line too weak to bend the Allan curve while a larger misfit is still unmodelled
    becomes resolved once that misfit's term is there (ADIS16405 run 1 accel_y: with the 0.56 Hz
    line in the model its 1.69 Hz line refits to zero amplitude; with the 10 Hz resonance as
    well, 1.44e-3 m/s^2: chi2/dof 3.73 -> 3.18 and the PSD part 3.83 -> 2.70 against the
    resonance alone). Added one round later it would cost the user a round of its own. The line,
    held at the spectrum's frequency, is offered with the term where its amplitude is resolved,
    it lowers the term's Allan chi2/dof, lowers the Allan or the PSD part beyond the test
    (:func:`_line_logp`, at ``alpha``), raises neither part beyond the given model's nor the PSD
    part beyond the term's alone, and takes no other term's place; it is checked against the
    hold-out part like any addition, the term alone next in line. ``units``:
    the samples', for the text."""
    top = next((s for s in suggestions if s.significant), None)
    ev = ctx.by_term.get("sinusoid")
    if top is None or top.action != "add" or top.fit is None or top.apply.get("args") \
            or get_term(top.term).role == "line" or ev is None or not ev.significant \
            or "f" not in ev.params:
        return suggestions
    spec = parse_model(str(top.apply["model"]))
    line = len(spec.entries)
    spec_line = ModelSpec(spec.entries + (Entry("sinusoid", {"f": float(ev.params["f"])}),))
    after = _fit_model(ctx, spec_line, _fit_profiled(ctx, spec_line) | {line})
    if after is None or not np.isfinite(after.chi2_per_dof):
        return suggestions
    amp = after.terms[line]
    psd_after = _psd_after(ctx, after)
    psd_top = top.error_after.get("psd")
    if not (get_term("sinusoid").resolved("A", amp.ci95.get("A"))
            and after.chi2_per_dof < top.chi2_per_dof_after
            and _line_logp(top, after, psd_top, psd_after) < np.log(alpha)
            and not _parts_rise(ctx, after, psd_after)
            and not _rises(_deviance(psd_top), _deviance(psd_after),
                           (psd_after or {}).get("bins", 0) / PSD_BIN_CORRELATION)
            and _imitation(ctx, after) is None):
        return suggestions
    f_hz, a = float(amp.params["f"]), float(amp.params["A"])
    why = (f"With it, the spectrum's line at {f_hz:.4g} Hz is resolved (amplitude {a:.3g} "
           f"{units}): the two together bring chi2/dof from {top.chi2_per_dof_after:.3g} "
           f"(the term alone) to {after.chi2_per_dof:.3g}"
           f"{_psd_change(psd_top, psd_after)}, so both are added.")
    return _before_top(ctx, suggestions, top, spec_line, after, psd_after, why,
                       f"{top.label or top.term} and sinusoid",
                       sorted(set(top.evidence) | {"spectral_line"}))


def _line_logp(top: Suggestion, after: FitResult, psd_top: dict[str, Any] | None,
               psd_after: dict[str, Any] | None) -> float:
    """Log p-value of a line added to ``top``'s refit (:func:`_with_next_line`): the better
    of its Allan chi2 drop and its PSD deviance drop, each a likelihood-ratio test with the
    line's two parameters, the drop scaled by the larger model's dispersion and lowering the
    part beyond its noise (as :func:`_lr_logp` and :func:`_psd_logp`), Bonferroni over the
    two parts."""
    assert top.fit is not None  # an addition's refit
    sources = [0.0]
    dof = float(after.misfit.dof)
    if _lowers(top.chi2_per_dof_after, after.chi2_per_dof, dof):
        drop = float(top.fit.misfit.chi2 - after.misfit.chi2)
        sources.append(_chi2_logsf(drop / _dispersion(after.chi2_per_dof, dof), 2))
    b, a = _deviance(psd_top), _deviance(psd_after)
    bins = (psd_after or {}).get("bins", 0) / PSD_BIN_CORRELATION
    if b is not None and a is not None and _lowers(b, a, bins):
        sources.append(_chi2_logsf((b - a) * bins / _dispersion(a, bins), 2))
    return min(0.0, min(sources) + float(np.log(2.0)))


def _significant_additions(suggestions: list[Suggestion]) -> list[Suggestion]:
    """The significant suggestions that add a term (no cut, removal or swap), in order."""
    return [s for s in suggestions if s.significant and s.fit is not None
            and s.action == "add" and not s.apply.get("args")]


def _further_drop(top: Suggestion, other: Suggestion, k: int) -> tuple[float, float]:
    """``(drop, p)``: how much lower ``top``'s refit chi2 lies than ``other``'s and the
    p-value of that drop for ``k`` parameters more, the drop scaled by ``top``'s dispersion
    (:func:`_dispersion`); p is 1 where ``top`` lies no lower."""
    assert top.fit is not None and other.fit is not None  # from _significant_additions
    drop = other.fit.misfit.chi2 - top.fit.misfit.chi2
    scaled = drop / _dispersion(top.chi2_per_dof_after, top.fit.misfit.dof)
    return drop, float(dist.chi2.sf(scaled, k)) if drop > 0 else 1.0


def _simplest_first(suggestions: list[Suggestion], alpha: float) -> list[Suggestion]:
    """Put a simpler significant term first when the top significant term explains the curve
    no better.

    Two terms can describe the same bump: a second-order resonance with Q near 0.5 has no
    spectral peak and bends the Allan curve much as a Gauss-Markov term does, with one
    parameter more. Ranked by their own p-values the richer one can come first by chance.
    The top term keeps its place only if its refit's chi2 lies significantly below the
    simpler term's (chi-square with the difference in parameters as degrees of freedom, at
    ``alpha``, the drop scaled as in :func:`_lr_logp`); otherwise the simplest such term
    goes first. Nor does it keep its place when it does not resolve the feature that names
    it (:meth:`Term.unresolved`: a resonance whose Q interval reaches its no-peak limit has
    shown no peak) and the term it then resembles (:attr:`Term.reduces_to`, a Gauss-Markov
    term) is significant too. Cuts of the record (bias step, warm-up) are refitted on other
    data and take no part.
    """
    def k_of(s: Suggestion) -> int:
        return len(get_term(s.term).params)

    terms = _significant_additions(suggestions)
    # the first significant suggestion is the one to apply; a cut there keeps its place
    first = next((s for s in suggestions if s.significant), None)
    if not terms or first is not terms[0]:
        return suggestions
    top = terms[0]
    top_term = get_term(top.term)
    unresolved = top_term.unresolved(top.params, top.ci95)
    for simpler in sorted((s for s in terms[1:] if k_of(s) < k_of(top)), key=k_of):
        drop, p = _further_drop(top, simpler, k_of(top) - k_of(simpler))
        if unresolved is not None and simpler.term == top_term.reduces_to:
            simpler.why += (f" It comes before {top.term}, whose fit lowers chi2 by "
                            f"{max(drop, 0.0):.3g} more with {k_of(top) - k_of(simpler)} "
                            f"parameter(s) more but {unresolved}.")
        elif p >= alpha:
            simpler.why += (f" It comes before {top.term}, which explains the curve no better "
                            f"with {k_of(top) - k_of(simpler)} parameter(s) more (its further "
                            f"chi2 drop {max(drop, 0.0):.3g}, p = {p:.2g}).")
        else:
            continue
        return [simpler] + [s for s in suggestions if s is not simpler]
    return suggestions


def _first_filter_of_a_tie(suggestions: list[Suggestion], alpha: float) -> list[Suggestion]:
    """Put the first output filter in :data:`TERMS` order first when the top significant
    suggestion is a filter and the data do not tell it from the best-fitting filter with as
    many parameters.

    A moving average of 1.2 taps, a Bartlett window of 1.1 and a single pole near a quarter of
    the rate bend the shortest taus alike; which one a record's last bits favour changed from
    run to run of one ADIS16405 accelerometer, so that six nights of one part gave three term
    sets for one filter. Two filters fit alike unless the better one's chi2 lies below the
    other's by more than the test's drop, scaled and judged with one degree of freedom as in
    :func:`_simplest_first`, Bonferroni over the filters compared: the best is picked after
    the fact, so one comparison at ``alpha`` parts filters that differ by chance. The tie
    holds the best and every filter alike to one already in it: a moving average and a
    Bartlett window of about one tap are one shape, and which of the two cleared the best's
    test followed the record as before (ADIS16405 run 2 accel_y: against the low-pass the
    moving average p = 0.043 and the Bartlett window 0.057 alone; run 6 accel_x 0.022 and
    0.027, the two 1 % apart). The first tied filter in term order is named, the same one on
    every record the data do not decide. The filters compared are the plain additions: where
    the top suggestion adds a filter together with a line, another filter so named goes
    first alone and the line is left to the next round.
    """
    terms = _significant_additions(suggestions)
    first = next((s for s in suggestions if s.significant), None)
    if not terms or first is not terms[0] or get_term(first.term).kind != "filter":
        return suggestions
    k_top = len(get_term(first.term).params)
    # plain additions only: a filter added together with a line ("lowpass and sinusoid")
    # fits with a term more, so its chi2 cannot be set against a filter's alone
    filters = [s for s in terms if get_term(s.term).kind == "filter" and not s.label
               and len(get_term(s.term).params) == k_top]
    if len(filters) < 2:
        return suggestions
    compared = len(filters) - 1

    def chi2_of(s: Suggestion) -> float:
        return s.fit.misfit.chi2 if s.fit is not None else np.inf

    def alike(a: Suggestion, b: Suggestion) -> bool:
        better, worse = sorted((a, b), key=chi2_of)
        return _further_drop(better, worse, 1)[1] * compared >= alpha

    tied = [min(filters, key=chi2_of)]
    while more := [s for s in filters if s not in tied and any(alike(s, t) for t in tied)]:
        tied += more
    order = list(TERMS)
    choice = min(tied, key=lambda s: order.index(s.term))
    if choice.term == first.term:
        return suggestions
    alike_text = ", ".join(f"{s.term} {s.chi2_per_dof_after:.3g}"
                           for s in sorted(tied, key=chi2_of))
    choice.why += (f" It comes before {first.term}: the output filters with as many "
                   f"parameters fit alike (chi2/dof {alike_text}; each within the test's drop "
                   f"of another, Bonferroni over {compared}), and the first in term order is "
                   f"named.")
    return [choice] + [s for s in suggestions if s is not choice]


def _ranked(ctx: _Context, suggestions: list[Suggestion], cuts: list[Finding], units: str,
            alpha: float) -> list[Suggestion]:
    """The candidates' suggestions (:func:`_suggest`) and the cuts of the record when no term
    is significant, strongest evidence first (:func:`_simplest_first`)."""
    suggestions = _markov_beside_a_filter(list(suggestions), ctx.fs_hz)
    if not any(s.significant for s in suggestions):
        # the step and warm-up tests take the fitted model as the sensor's noise: only once
        # no term is missing is that a fair null (a model without its random walk sees
        # steps everywhere); until then they stay findings
        # one transient, one remedy: the shape that explains it better when both are found
        found = {f.kind for f in cuts if f.significant}
        suggestions += [_remedy(ctx, f, units, alpha) for f in cuts if f.significant
                        and f.details.get("better_explained_by") not in found]
    removals: list[Suggestion] = []
    if not any(s.significant for s in suggestions):
        # nothing is missing: a term the record does not resolve goes, the one the data
        # need least (the largest p of the chi2 rise without it) first
        removals = sorted((_removal(ctx, i, alpha) for i in _unresolved_terms(ctx)),
                          key=lambda s: -s.log_p)
    # Strongest evidence first: the likelihood-ratio p-value already charges a term for its
    # parameters, so a two-parameter Markov term does not win merely by being flexible.
    suggestions.sort(key=lambda s: (s.log_p, np.nan_to_num(s.chi2_per_dof_after, nan=np.inf)))
    return removals + _first_filter_of_a_tie(_simplest_first(suggestions, alpha), alpha)
