"""The suggestion to take out the steps a record's channels take together
(:mod:`imunoise.analysis.common_steps`), judged by the rules every suggestion meets.

The steps are removed from the series before any fit, so the refit is another curve, not a
nested model: its Allan chi2 is no likelihood-ratio test of the given model's. The evidence is
the detection itself (a family-wise p-value over every boundary of the record, Bonferroni over
the steps removed from this channel and the diagnosis' candidates); the suggestion is
significant when that evidence passes ``alpha``, the Allan chi2/dof falls, the PSD part does not
rise beyond its noise, and the hold-out part does not rise beyond its noise (and falls where the
given model does not predict the other half): applying it lowers the error the fit reports. A
significant removal is ranked first: the data are corrected before the sensor's noise is
modelled.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from imunoise.analysis.common_steps import TERM, CommonSteps
from imunoise.analysis.diagnosis.holdout import _holdout_worse
from imunoise.analysis.diagnosis.result import Diagnosis, Suggestion
from imunoise.analysis.diagnosis.statistics import PSD_BIN_CORRELATION, _deviance, _rises
from imunoise.analysis.fit import FitResult


def _when(steps: CommonSteps, channel: str, units: str) -> str:
    """The steps removed from ``channel`` in words (at most six listed)."""
    own = steps.of(channel)
    told = ", ".join(f"{s.t_s:.0f} s ({s.sizes[channel]:+.3g} {units}, z {s.z[channel]:+.1f})"
                     for s in own[:6])
    more = f" and {len(own) - 6} more" if len(own) > 6 else ""
    return f"{told}{more}"


def steps_suggestion(diag: Diagnosis, steps: CommonSteps, channel: str, after: FitResult,
                     parts: dict[str, Any], model_text: str, units: str) -> Suggestion:
    """The ``common_steps`` suggestion for ``channel``: ``diag`` the given model's diagnosis
    on the series as recorded, ``after`` and ``parts`` (``psd``, ``holdout``,
    ``time_domain``) the same model's fit and error parts on the series with the steps taken
    out, ``model_text`` the given model's specification."""
    own = steps.of(channel)
    before = float(diag.fit.chi2_per_dof)
    chi_after = float(after.chi2_per_dof)
    n_tests = max(len(own), 1) * (len(diag.suggestions) + 1)
    log_p = min(0.0, min((s.log10_p for s in own), default=0.0) * math.log(10.0)
                + math.log(n_tests))
    evidence = log_p < math.log(diag.alpha)
    falls = bool(np.isfinite(chi_after)) and chi_after < before
    psd_before, psd_after = diag.error_parts.get("psd"), parts.get("psd")
    psd_rises = _rises(_deviance(psd_before), _deviance(psd_after),
                       (psd_after or {}).get("bins", 0) / PSD_BIN_CORRELATION)
    holdout_worse = _holdout_worse(diag.error_parts.get("holdout") or {},
                                   parts.get("holdout") or {}, float(diag.fit.misfit.dof),
                                   claims=True)
    group = ", ".join(steps.channels)
    why = (f"The channels {group} jump together {len(steps.steps)} time(s), and {len(own)} "
           f"of the jumps leave a lasting step on {channel}: at {_when(steps, channel, units)}. "
           f"A knock, a tilt or a weight put on the bench moves the bias of every axis at "
           f"once; the noise terms take such steps for random walk, differently in each part "
           f"of the record. Taking them out of {channel} brings chi2/dof from {before:.3g} to "
           f"{chi_after:.3g}")
    psd_b, psd_a = _deviance(psd_before), _deviance(psd_after)
    if psd_b is not None and psd_a is not None:
        why += f" and the PSD part from {psd_b:.3g} to {psd_a:.3g}"
    why += "."
    held_by, held_reason = "", ""
    if evidence and not falls:
        held_by, held_reason = "rise", "it does not lower the Allan chi2/dof."
    elif evidence and psd_rises:
        held_by, held_reason = "rise", "it raises the PSD part beyond its noise."
    elif evidence and holdout_worse is not None:
        held_by, held_reason = "holdout", holdout_worse
    if held_reason:
        why += f" Held back: {held_reason}"
    error_after = {"chi2_per_dof": chi_after, "max_abs_z": float(after.max_abs_z),
                   "psd": psd_after, "holdout": parts.get("holdout"),
                   "time_domain": parts.get("time_domain")}
    apply_model = f"{model_text},{TERM}" if model_text.strip() else TERM
    return Suggestion(
        term=TERM, params={}, ci95={}, chi2_per_dof_before=before,
        chi2_per_dof_after=chi_after, p_value=float(math.exp(log_p)), log_p=log_p,
        significant=bool(evidence and falls and not psd_rises and holdout_worse is None),
        why=why, evidence=[TERM], fit=after, apply={"model": apply_model, "args": []},
        held_by=held_by, held_reason=held_reason, error_after=error_after)


def ranked_in(suggestions: list[Suggestion], new: Suggestion) -> list[Suggestion]:
    """``suggestions`` with ``new`` in its place: first when significant (the record is
    corrected before the sensor's noise is modelled: the steps' test needs no noise model,
    and the terms fitted afterwards no longer take the steps for random walk), otherwise by
    the diagnosis' order (smallest p first)."""
    out = list(suggestions)
    at = 0 if new.significant else next((i for i, s in enumerate(out) if s.log_p > new.log_p),
                                        len(out))
    out.insert(at, new)
    return out
