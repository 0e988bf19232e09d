"""Statistics over many recordings of many units: replicates pooled, outliers, growth, limits.

Noise coefficients are scale quantities (a deviation, a density): their estimates are close to
log-normal and their intervals close to symmetric in log. Everything here therefore works on
``log(value)`` with the standard error taken from the 95 % interval,
``se = (log(hi) - log(lo)) / (2 * 1.95996)``, and maps results back with ``exp``.

* :func:`pool_replicates`: several recordings of one unit pooled. Cochran's Q test says
  whether the recordings agree within their intervals (``Q = sum w_i (x_i - x_fixed)^2`` with
  ``w_i = 1 / se_i^2``, chi-square with ``k - 1`` degrees of freedom under agreement;
  W. G. Cochran, Biometrics 10, 1954); ``I^2 = max(0, (Q - (k-1)) / Q)`` is the share of the
  spread that the intervals do not explain (Higgins and Thompson, Stat. Med. 21, 2002). The
  pooled value is the random-effects mean of DerSimonian and Laird (Control. Clin. Trials 7,
  1986): the night-to-night variance ``tau^2 = max(0, (Q - (k-1)) / (S1 - S2/S1))``
  (``S1 = sum w``, ``S2 = sum w^2``) is added to every recording's variance before weighting.
  When the recordings agree it equals the inverse-variance mean; when they do not, its
  interval widens to the spread between nights instead of claiming a precision no single
  night supports.
* :func:`robust_outliers`: the modified z-score of Iglewicz and Hoaglin (1993),
  ``M_i = 0.6745 (x_i - median) / MAD``, on log values; ``|M| > 3.5`` is an outlier. The
  median and MAD are not moved by the outlier itself, unlike a mean and a standard deviation.
* :func:`grew`: the latest recording's interval lies wholly above the earliest one's.
* :func:`limit_verdict`: pass, fail, or marginal when the interval straddles the limit.

A value whose interval reaches zero (or is missing) carries no standard error and is left
out of pooling and outlier tests; the callers say so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from imunoise.analysis import distributions as dist

Z95 = float(dist.norm.ppf(0.975))
"""Two-sided 95 % normal quantile (1.95996)."""
OUTLIER_M = 3.5
"""Modified z-score beyond which a unit is an outlier (Iglewicz and Hoaglin)."""
MIN_POPULATION = 5
"""Fewest units for an outlier test: below it the median and MAD mean little."""
AGREEMENT_ALPHA = 0.05
"""Recordings of a unit disagree when Cochran's Q has a p-value below this."""


def log_se(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Standard error of ``log(value)`` from a 95 % interval; NaN where the interval is missing
    or reaches zero."""
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        se = (np.log(hi) - np.log(lo)) / (2.0 * Z95)
    return np.where((lo > 0) & (hi > lo) & np.isfinite(se), se, np.nan)


@dataclass(frozen=True)
class Pooled:
    """Pooled estimate of one coefficient over ``k`` recordings of one unit."""

    value: float
    lo95: float
    hi95: float
    k: int
    tau2: float
    """Night-to-night variance of log(value) beyond the intervals (0 when they agree)."""
    q: float
    """Cochran's Q."""
    p_value: float
    """P(Q at least this large | the recordings measure one value); NaN for k < 2."""
    i2: float
    """Share of the spread beyond what the intervals explain (0 to 1)."""

    @property
    def agree(self) -> bool | None:
        """True when the recordings agree (p >= AGREEMENT_ALPHA); None for one recording."""
        return None if self.k < 2 else bool(self.p_value >= AGREEMENT_ALPHA)

    def to_dict(self) -> dict:
        return {"value": self.value, "ci95": [self.lo95, self.hi95], "recordings": self.k,
                "cochran_q": self.q, "p_value": self.p_value, "i2": self.i2,
                "between_runs_log_sd": float(np.sqrt(self.tau2)), "agree": self.agree,
                "test": "Cochran's Q (chi-square, k-1 dof) on log values",
                "pooling": "random effects (DerSimonian-Laird) on log values"}


def pool_replicates(values: np.ndarray, lo95: np.ndarray, hi95: np.ndarray) -> Pooled | None:
    """Pooled estimate of recordings of one unit (random effects, see the module notes), or
    None when no recording has a usable interval."""
    v = np.asarray(values, dtype=np.float64)
    se = log_se(lo95, hi95)
    ok = (v > 0) & np.isfinite(v) & np.isfinite(se) & (se > 0)
    if not ok.any():
        return None
    x, s = np.log(v[ok]), se[ok]
    w = 1.0 / s**2
    fixed = float(np.sum(w * x) / np.sum(w))
    k = int(ok.sum())
    q = float(np.sum(w * (x - fixed) ** 2))
    p = float(dist.chi2.sf(q, k - 1)) if k >= 2 else float("nan")
    i2 = max(0.0, (q - (k - 1)) / q) if k >= 2 and q > 0 else 0.0
    s1, s2 = float(np.sum(w)), float(np.sum(w**2))
    tau2 = max(0.0, (q - (k - 1)) / (s1 - s2 / s1)) if k >= 2 else 0.0
    w_re = 1.0 / (s**2 + tau2)
    mean = float(np.sum(w_re * x) / np.sum(w_re))
    se_pool = float(np.sqrt(1.0 / np.sum(w_re)))
    return Pooled(value=float(np.exp(mean)), lo95=float(np.exp(mean - Z95 * se_pool)),
                  hi95=float(np.exp(mean + Z95 * se_pool)), k=k, tau2=tau2, q=q, p_value=p,
                  i2=i2)


def robust_outliers(values: np.ndarray, threshold: float = OUTLIER_M
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Modified z-scores of positive values (on log scale) and the outlier flags.

    With fewer than :data:`MIN_POPULATION` finite positive values, or a MAD of zero, every
    score is NaN and nothing is flagged."""
    v = np.asarray(values, dtype=np.float64)
    ok = (v > 0) & np.isfinite(v)
    m = np.full(v.shape, np.nan)
    if ok.sum() < MIN_POPULATION:
        return m, np.zeros(v.shape, bool)
    x = np.log(v[ok])
    med = float(np.median(x))
    mad = float(np.median(np.abs(x - med)))
    if mad <= 0:
        return m, np.zeros(v.shape, bool)
    m[ok] = 0.6745 * (x - med) / mad
    return m, np.abs(np.nan_to_num(m)) > threshold


def grew(first: tuple[float, float], last: tuple[float, float]) -> bool:
    """True when the later 95 % interval ``(lo, hi)`` lies wholly above the earlier one."""
    return bool(np.isfinite(last[0]) and np.isfinite(first[1]) and last[0] > first[1])


def limit_verdict(value: float, lo95: float, hi95: float, maximum: float | None = None,
                  minimum: float | None = None) -> str:
    """``"pass"``, ``"fail"`` or ``"marginal"`` (the interval straddles a limit) for a value
    against an upper and/or lower limit; ``"unresolved"`` without a value."""
    if not np.isfinite(value):
        return "unresolved"
    lo = lo95 if np.isfinite(lo95) else value
    hi = hi95 if np.isfinite(hi95) else value
    verdict = "pass"
    if maximum is not None:
        if lo > maximum:
            return "fail"
        if hi > maximum:
            verdict = "marginal"
    if minimum is not None:
        if hi < minimum:
            return "fail"
        if lo < minimum:
            verdict = "marginal"
    return verdict
