"""The tests a diagnosis judges refits by: likelihood ratios, chi-square tails, and whether
a part of the error rises or falls beyond its noise."""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import special

from imunoise.analysis import distributions as dist
from imunoise.analysis.fit import FitResult
from imunoise.analysis.model_error import NOISE_SD, right_model_limit


def _z_range(before: FitResult, after: FitResult) -> tuple[float, float] | None:
    """Tau range where adding the term improved the standardised residuals most."""
    zb = dict(zip(np.round(before.tau_s, 12), before.z, strict=True))
    gain = np.array([zb.get(round(float(t), 12), 0.0) ** 2 - z**2
                     for t, z in zip(after.tau_s, after.z, strict=True)])
    if gain.size == 0 or gain.max() <= 1.0:
        return None
    sel = after.tau_s[gain > max(1.0, 0.25 * gain.max())]
    return float(sel.min()), float(sel.max())


def _dispersion(per_dof: float | None, dof: float) -> float:
    """The scale a likelihood-ratio drop is divided by (:func:`_lr_logp`): the larger
    model's misfit per degree of freedom ``per_dof`` over ``dof`` degrees of freedom, divided
    by the most a right model shows (:func:`right_model_limit`), where that exceeds 1; else
    1. The misfit of a right model is itself
    noisy (a chi2/dof of 1.5 over 14 degrees of freedom is 1.3 of its standard deviations
    above 1): only misfit beyond that range scales the test."""
    if per_dof is None or not np.isfinite(per_dof):
        return 1.0
    return max(1.0, float(per_dof) / right_model_limit(dof))


def _lr_logp(before: FitResult, after: FitResult, k: int) -> float:
    """Natural log of the p-value of the chi2 drop from ``before`` to ``after`` with ``k``
    added parameters (log form: strong effects give p-values below the float range).

    The drop is divided by the larger model's dispersion (:func:`_dispersion`), a
    quasi-likelihood test: a model that misses the curve by a factor ``c`` per degree of
    freedom leaves misfit that any ``k`` more parameters absorb in proportion to ``c``.
    ADIS16405 run 2 accel_x with a Markov term and a low-pass (chi2/dof 1236) takes
    quantization from chi2 14836 to 13653 while its chi2/dof rises to 1241, p = 1e-97
    unscaled and 0.14 scaled. A model whose misfit lies within a right model's range is
    judged as before."""
    return _chi2_logsf((before.misfit.chi2 - after.misfit.chi2)
                       / _dispersion(after.chi2_per_dof, after.misfit.dof), k)


PSD_BIN_CORRELATION = 2.0
"""The fall of the PSD deviance summed over the points is divided by this before its
chi-square test: neighbouring log-frequency points share Hann bins and are not independent
(conservative; their dof already allow for the merge)."""


def _chi2_logsf(drop: float, k: int) -> float:
    """``ln P(chi2_k > drop)``, with the tail's leading terms where scipy underflows."""
    if not np.isfinite(drop) or drop <= 0:
        return 0.0
    logp = float(dist.chi2.logsf(drop, k))
    if np.isfinite(logp):
        return logp
    # Far in the tail scipy returns -inf; the tail's leading terms keep the ranking meaningful,
    # including its charge for each added parameter:
    # ln P(chi2_k > x) ~ -x/2 + (k/2 - 1) ln(x/2) - ln Gamma(k/2).
    return -0.5 * drop + (0.5 * k - 1.0) * float(np.log(0.5 * drop)) \
        - float(special.gammaln(0.5 * k))


def _logp(p: float) -> float:
    return float(np.log(max(p, 1e-300)))


def _part_sd(before: float, dof: float) -> float:
    """Standard deviation of a part (see :data:`NOISE_SD`)."""
    return float(np.sqrt((4.0 * max(before, 1.0) - 2.0) / max(dof, 1.0)))


def _rises(before: float | None, after: float | None, dof: float) -> bool:
    """Whether a part grew beyond its noise (see :data:`NOISE_SD`)."""
    if before is None or after is None or not (np.isfinite(before) and np.isfinite(after)):
        return False
    return after > before + NOISE_SD * _part_sd(before, dof)


def _lowers(before: float | None, after: float | None, dof: float) -> bool:
    """Whether a part fell by more than one of its standard deviations: a fall within its
    noise lowers nothing (a part far above 1 moves by more than a right model's chi-square
    spread between two fits of the same misfit)."""
    if before is None or after is None or not (np.isfinite(before) and np.isfinite(after)):
        return False
    return after < before - _part_sd(before, dof)


def _deviance(part: dict[str, Any] | None) -> float | None:
    return None if not part else part.get("deviance_per_bin")
