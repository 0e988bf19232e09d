"""The common result type of every evidence test."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass
class Finding:
    """The outcome of one evidence test on one channel.

    Attributes:
        kind: which test: ``"spectral_line"``, ``"line_power"``, ``"temperature"``,
            ``"nonstationarity"``, ``"drift"``, ``"resonance_drift"``, ``"outliers"``,
            ``"held_samples"`` or ``"gaps"``.
        term: the model term (docs/terms.md vocabulary) this evidence supports, or ``None`` when
            the effect is not a noise term (outliers, gaps, warm-up of the noise level).
        statistic: the test statistic (its meaning is given by ``statistic_name``).
        statistic_name: short name of the statistic, e.g. ``"t"``, ``"chi2"``, ``"max |z|"``.
        p_value: probability of a statistic at least this extreme when the effect is absent,
            already corrected for the number of places searched (bins, windows, samples).
        alpha: the significance level the test was run at.
        significant: ``p_value < alpha``.
        params: estimated size of the effect, SI units (e.g. ``{"A": ..., "f": ...}``).
        range: where the evidence shows, e.g. ``{"f_hz": [lo, hi]}`` or ``{"tau_s": [lo, hi]}``
            or ``{"t_s": [lo, hi]}``.
        why: one or two plain sentences for a person.
        details: further numbers (lists of lines, outlier indices, per-window levels).
    """

    kind: str
    term: str | None
    statistic: float
    statistic_name: str
    p_value: float
    alpha: float
    params: dict[str, float] = field(default_factory=dict)
    range: dict[str, list[float]] = field(default_factory=dict)
    why: str = ""
    details: dict[str, Any] = field(default_factory=dict)

    @property
    def significant(self) -> bool:
        return bool(self.p_value < self.alpha)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready form (plain floats, lists)."""
        return {
            "kind": self.kind,
            "term": self.term,
            "statistic": float(self.statistic),
            "statistic_name": self.statistic_name,
            "p_value": float(self.p_value),
            "alpha": float(self.alpha),
            "significant": self.significant,
            "params": {k: float(v) for k, v in self.params.items()},
            "range": {k: [float(a) for a in v] for k, v in self.range.items()},
            "why": self.why,
            "details": self.details,
        }


def family_p(p_single: float, n_tests: int) -> float:
    """Family-wise p-value of the smallest of ``n_tests`` single p-values (Sidak correction)."""
    p_single = float(min(max(p_single, 0.0), 1.0))
    n = max(int(n_tests), 1)
    # -expm1(n*log1p(-p)) keeps precision for tiny p where 1-(1-p)^n would round to 0.
    return float(-np.expm1(n * np.log1p(-p_single))) if p_single < 1.0 else 1.0
