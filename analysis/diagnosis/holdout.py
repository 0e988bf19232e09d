"""How a round's suggestions are judged by the hold-out part, and the lookahead to a pair of terms
where neither is significant alone."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from imunoise.analysis.diagnosis.context import _Context, _parts_rise
from imunoise.analysis.diagnosis.result import Diagnosis, Suggestion
from imunoise.analysis.diagnosis.statistics import _deviance, _lr_logp, _rises
from imunoise.analysis.model_error import holdout_part, right_model_limit
from imunoise.analysis.terms import get_term

HOLDOUT_CHECKS = 3
"""Significant suggestions whose hold-out part is computed (best first) before giving up:
each costs two fits on the halves."""


def _pair(ctx: _Context, suggestions: list[Suggestion], holdout_before: dict[str, Any],
          alpha: float, next_round: Callable[[str, frozenset[str]], Diagnosis]
          ) -> Suggestion | None:
    """Two terms that describe the record together where neither is significant alone, or
    None.

    A greedy round judges one term at a time. Where the model fails, a term with strong
    evidence can lower the Allan and PSD parts and still predict the other half worse,
    because the terms already in the model take other roles in each half until a second
    missing term is there too. So, when the given model fails and no suggestion is
    significant, the strongest term held back by the hold-out part is applied tentatively
    and the next round tried on it, with the candidates this round found strong evidence for
    (a resonance that takes the line's place alone moves to another peak once the line is
    modelled; terms without evidence here are not tried, which keeps the lookahead to a few
    refits). The pair is suggested when, against the given model, its chi2 drop passes the
    likelihood-ratio test with both terms' parameters (Bonferroni over the pairs tried), its
    chi2/dof falls, no part rises beyond its noise, and its hold-out part does not rise and,
    where the given model does not predict the other half, falls: the rules a single term
    meets. ``apply.model`` adds both.
    """
    b = holdout_before.get("chi2_per_dof")
    if b is None or any(s.significant for s in suggestions) or not ctx.base.failures:
        return None
    first = next((s for s in suggestions if s.action == "add" and s.fit is not None
                  and s.log_p < np.log(alpha) and s.held_by == "holdout"), None)
    if first is None:
        return None
    strong = frozenset(s.term for s in suggestions
                       if s.action == "add" and s.log_p < np.log(alpha))
    try:
        then = next_round(str(first.apply["model"]), strong)
    except (ValueError, np.linalg.LinAlgError):
        return None
    before = ctx.base.chi2_per_dof
    tried = ctx.n_candidates * max(len(then.suggestions), 1)
    dof = float(ctx.base.misfit.dof)
    found = None
    for second in [s for s in then.suggestions if s.significant and s.action == "add"
                   and s.fit is not None][:HOLDOUT_CHECKS]:
        after, psd_after = second.fit, second.error_after.get("psd")
        assert after is not None  # the list holds refits only
        k = len(get_term(first.term).params) + len(get_term(second.term).params)
        logp = min(0.0, _lr_logp(ctx.base, after, k) + float(np.log(tried)))
        if not (logp < np.log(alpha) and after.chi2_per_dof < before
                and not _parts_rise(ctx, after, psd_after)):
            continue
        holdout = holdout_part(ctx.x, ctx.fs_hz, second.apply["model"], after, ctx.starts,
                               job_map=ctx.job_map, by_curves=False)
        ho = holdout.get("chi2_per_dof")
        if ho is not None and _holdout_worse(holdout_before, holdout, dof, True) is None:
            found = second, after, psd_after, logp, holdout, float(ho)
            break
    if found is None:
        return None
    second, after, psd_after, logp, holdout, ho = found
    first_ho = (first.error_after.get("holdout") or {}).get("chi2_per_dof")
    psd_b, psd_a = _deviance(ctx.psd_before), _deviance(psd_after)
    psd_txt = "" if psd_b is None or psd_a is None else \
        f", the PSD part from {psd_b:.3g} to {psd_a:.3g}"
    why = (f"{first.term} alone brings chi2/dof from {before:.3g} to "
           f"{first.chi2_per_dof_after:.3g} but predicts the other half worse (hold-out part "
           f"{b:.3g} -> {first_ho if first_ho is None else f'{first_ho:.3g}'}): the terms "
           f"already in the model take other roles in each half. With {second.term} as well "
           f"(the strongest term of the next round that does) the model brings chi2/dof "
           f"from {before:.3g} to {after.chi2_per_dof:.3g}{psd_txt} and the hold-out part "
           f"from {b:.3g} to {ho:.3g}: the two are added together.")
    tf = after.terms[len(ctx.spec)]
    return Suggestion(
        term=first.term, params=dict(tf.params), ci95=dict(tf.ci95),
        chi2_per_dof_before=before, chi2_per_dof_after=after.chi2_per_dof,
        p_value=float(np.exp(logp)), log_p=logp, significant=True, why=why,
        evidence=sorted(set(first.evidence) | set(second.evidence)), fit=after,
        apply=dict(second.apply), action="add", label=f"{first.term} and {second.term}",
        error_after={**second.error_after, "holdout": holdout})


def _holdout_worse(before: dict[str, Any], after: dict[str, Any], dof: float, claims: bool
                   ) -> str | None:
    """Why a suggestion's hold-out part ``after`` judges it worse than the given model's
    ``before`` (a clause), or None where it does not: the part rises beyond its noise, or,
    for a suggestion that ``claims`` something new (an addition or a replacement) where the
    given model's part lies beyond a right model's limit, does not fall. The prediction with
    the parameters the part names as changed fitted on each half (``changes_free``) is
    judged the same way where both parts give it. A plain part that cannot be computed
    judges nothing."""
    b, a = before.get("chi2_per_dof"), after.get("chi2_per_dof")
    if b is None or a is None:
        return None
    b_free = (before.get("changes_free") or {}).get("chi2_per_dof")
    a_free = (after.get("changes_free") or {}).get("chi2_per_dof")
    for was, now, how in ((b, a, "the model fitted on one half predicting the other"),
                          (b_free, a_free, "the changes it names fitted on each half")):
        if was is None or now is None:
            continue
        need_fall = claims and was > right_model_limit(dof)
        if _rises(was, now, dof) or need_fall and now >= was:
            return (f"it does not {'lower' if need_fall else 'keep'} the hold-out part "
                    f"({how}: chi2/dof {was:.3g} -> {now:.3g}).")
    return None


def _check_holdout(ctx: _Context, suggestions: list[Suggestion], before: dict[str, Any]
                   ) -> dict[str, Any]:
    """The given model's hold-out part (``before``, passed through); and a significant term
    suggestion is demoted when it raises the hold-out part beyond its noise, or, where the
    given model's hold-out part is itself beyond its noise (the model does not predict the
    other half), when it does not lower it. A fall within one standard deviation counts: the
    part's spread is taken from the Allan fit's dof, which is smaller than the two
    predictions' (nothing is fitted in them), and demanding a full standard deviation
    demoted a true second Markov term whose hold-out part fell from 2.2 to 1.5
    (tests/analysis/test_repeated_terms.py). Where the part names parameters that changed
    between the halves, the prediction with those fitted on each half (``changes_free``) is
    judged the same way: a changed resonance can dominate the plain part so that a term that
    predicts the other half worse passes unseen (ADIS16405 run 1 accel_y, its 10 Hz
    resonance moving by 0.4 Hz between the halves: a Markov term with the 0.46 Hz line
    takes the plain part from 67.9 to 67.9 and the part with the changes fitted from 3.21
    to 6.12). Checked best first, at most
    :data:`HOLDOUT_CHECKS` of them; the first significant suggestion left is the one to
    apply. Where every one checked fails, the significant suggestions after them are not
    significant either: unchecked, they would be applied on the Allan and PSD parts alone
    (ADIS16405 run 3 gyro_z: behind three that failed, a wandering resonance taking the Allan
    part from 3.6 to 2.5 raised the loop's PSD and hold-out parts, 66.6 to 69.3 and 5.40 to
    5.57)."""
    dof = float(ctx.base.misfit.dof)
    checked = 0
    for s in suggestions:
        if not s.significant or s.fit is None or s.apply.get("args"):
            if s.significant:
                break  # a cut comes first: it is judged by the time-domain part
            continue
        if before.get("chi2_per_dof") is None:
            break
        if checked >= HOLDOUT_CHECKS:
            # unchecked, it could not claim what the others failed to show
            s.held_reason = (f"its hold-out part was not computed (the {checked} better "
                             f"suggestions each failed it).")
            s.significant = False
            s.held_by = "holdout"
            s.why += f" Not significant: {s.held_reason}"
            continue
        checked += 1
        after = holdout_part(ctx.x, ctx.fs_hz, s.apply["model"], s.fit, ctx.starts,
                             job_map=ctx.job_map, by_curves=False)
        s.error_after["holdout"] = after
        # a removal claims nothing new: it only must not make the prediction worse
        reason = _holdout_worse(before, after, dof, s.action in ("add", "replace"))
        if reason is None:
            break
        s.held_reason = reason
        s.significant = False
        s.held_by = "holdout"
        s.why += f" Not significant: {s.held_reason}"
    suggestions.sort(key=lambda s: not s.significant)  # stable: the order among each kept
    return before
