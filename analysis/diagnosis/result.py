"""What a diagnosis returns: its suggestions and the diagnosis itself."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imunoise.analysis.evidence.finding import Finding
from imunoise.analysis.evidence.transients import holds_zero
from imunoise.analysis.fit import FitResult
from imunoise.analysis.terms import TERMS

DEFAULT_ALPHA = 0.05
"""Family-wise probability that a correctly specified model gets any significant suggestion."""


@dataclass
class Suggestion:
    """One candidate term, refitted.

    Attributes:
        term: the term added to the model.
        params: its parameters in the refitted model (SI units).
        ci95: their 95 % intervals: linearised in log-parameter space where the refit
            determines the parameter well, by profile likelihood where it does not (an
            amplitude near zero, a log-scale standard error above 0.5); every candidate is
            refitted, so only the added term and the white level are profiled (the white
            level alone in the lookahead's second round), and a weakly determined parameter
            of another term has none (``nan``).
        chi2_per_dof_before: misfit of the given model.
        chi2_per_dof_after: misfit with the term added (``nan`` when the refit failed).
        p_value: probability of evidence this strong were the term absent, Bonferroni-corrected
            for the number of candidates (and of evidence sources).
        log_p: natural log of ``p_value`` (keeps its order where ``p_value`` underflows).
        significant: ``p_value < alpha``.
        why: plain-words explanation: the effect, where it shows, the expected improvement.
        evidence: the evidence findings that support it (kinds).
        fit: the refitted model (not serialised). Its intervals are linearised; those of the
            added term and the white level are profiled where weakly determined, the other
            terms' weakly determined parameters have none (``nan``).
        apply: how to apply it: ``{"model": the full model specification, "args": extra
            command-line options of fit and diagnose}``; ``imunoise fit --model
            apply.model`` reports exactly ``chi2_per_dof_after``.
    """

    term: str
    params: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    chi2_per_dof_before: float
    chi2_per_dof_after: float
    p_value: float
    log_p: float
    significant: bool
    why: str
    evidence: list[str] = field(default_factory=list)
    fit: FitResult | None = None
    apply: dict[str, Any] = field(default_factory=dict)
    action: str = "add"
    """``"add"`` the term, ``"cut"`` the record (a bias step or warm-up: ``apply.args``),
    ``"remove"`` a term of the given model whose amplitude the record does not resolve
    (:func:`_removal`), or ``"replace"`` the model's output filter by another kind
    (:func:`_swap`; ``term`` is the new filter)."""
    label: str = ""
    """The removed term's label in the given model (``name#K`` for the K-th of a repeated
    name); for a pair of terms added together (:func:`_pair`), ``"X and Y"``; for a filter
    replaced, ``"OLD by NEW"``; for a term added with another filter in the model's filter's
    place (:func:`_filter_rechosen`), ``"TERM, OLD by NEW"``; empty otherwise."""
    held_by: str = ""
    """What keeps a suggestion whose evidence passes the test from being significant:
    ``"identifiability"``, ``"rise"`` (it raises a part beyond its noise, or does not lower
    the Allan chi2/dof at all) or ``"holdout"``;
    empty otherwise (not serialised: ``why`` says it, and :attr:`held_reason`)."""
    held_reason: str = ""
    """That reason in words (the sentence ``why`` ends with)."""
    error_after: dict[str, Any] = field(default_factory=dict)
    """The whole error object of the applied model (``chi2_per_dof``, ``max_abs_z``,
    ``psd``, ``holdout``, ``time_domain``; a part not computed for a suggestion is null with a
    ``reason``)."""

    def to_dict(self) -> dict[str, Any]:
        """A ``suggestions`` entry of the JSON (docs/json.md)."""
        def num(v: float) -> float | None:
            return float(v) if np.isfinite(v) else None

        term = TERMS.get(self.term)  # a cut (bias step, warm-up) is no term
        return {"term": self.term, "action": self.action,
                **({"label": self.label} if self.label else {}),
                "params": {k: num(v) for k, v in self.params.items()},
                "ci95": {k: [num(a), num(b)] for k, (a, b) in self.ci95.items()},
                # amplitudes whose interval reaches zero: no estimate, only an upper bound
                "unresolved": [k for k in self.params if (
                    not term.resolved(k, self.ci95.get(k)) if term is not None
                    else k == _CUT_SIZE.get(self.term) and holds_zero(self.ci95.get(k)))],
                "chi2_per_dof_before": num(self.chi2_per_dof_before),
                "chi2_per_dof_after": num(self.chi2_per_dof_after),
                "significant": bool(self.significant), "p_value": num(self.p_value),
                "log10_p": num(self.log_p / np.log(10.0)),
                "why": self.why, "evidence": list(self.evidence),
                "error_after": self.error_after,
                "apply": {"model": self.apply.get("model", ""),
                          "args": list(self.apply.get("args", []))}}


@dataclass
class Diagnosis:
    """The given model's fit, the ranked suggestions and every evidence finding."""

    fit: FitResult
    curve: Any
    suggestions: list[Suggestion]
    findings: list[Finding]
    alpha: float
    psd: dict[str, Any] | None = None
    """The ``psd`` block of the given model (measured PSD, ``model_psd``, ``z``)."""
    error_parts: dict[str, Any] = field(default_factory=dict)
    """The given model's ``psd``, ``holdout`` and ``time_domain`` parts of the error."""


_CUT_SIZE = {"bias_step": "size", "warmup": "amplitude"}
"""The signed size of each cut's transient: no measurement when its interval holds zero."""
