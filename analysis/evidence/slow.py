"""Slow effects on the bias: temperature sensitivity and drift.

Both are regressions of the slow (bin-averaged) rate on a regressor, temperature or time,
with the autocorrelation-aware test of :func:`imunoise.analysis.evidence.slowgrid.slow_regression`.
"""

from __future__ import annotations

import numpy as np

from imunoise.analysis import distributions as dist
from imunoise.analysis.evidence.finding import Finding
from imunoise.analysis.evidence.slowgrid import bin_means, slow_grid, slow_regression

_TARGET_BINS = 300


def _bin_width(duration_s: float, min_s: float) -> float:
    return max(duration_s / _TARGET_BINS, min_s)


def temperature_correlation(rate_t_s: np.ndarray, rate: np.ndarray, temp_t_s: np.ndarray,
                            temp_c: np.ndarray, alpha: float = 0.05,
                            units: str = "rad/s") -> Finding:
    """Does the slow rate follow the temperature record?

    Args:
        rate_t_s: sample times of the rate, seconds.
        rate: rate samples (or the residual after the fitted model's deterministic part),
            SI units.
        temp_t_s: temperature sample times, seconds, same time base (may be much slower).
        temp_c: temperature in degC.
        alpha: significance level.
        units: units of ``rate`` for the explanation.

    Returns:
        Finding of kind ``"temperature"`` with ``params["coef"]`` in units per degC and
        ``details`` holding the 95 % interval, the bin width and the AR(1) coefficient.
    """
    temp_t_s = np.asarray(temp_t_s, float)
    temp_c = np.asarray(temp_c, float)
    lo = max(float(rate_t_s[0]), float(temp_t_s[0]))
    hi = min(float(rate_t_s[-1]), float(temp_t_s[-1]))
    if temp_t_s.size < 2 or hi <= lo:
        return Finding("temperature", "temperature", 0.0, "t", 1.0, alpha,
                       why="the temperature record does not overlap the rate record")
    temp_dt = float(np.median(np.diff(temp_t_s)))
    bin_s = _bin_width(hi - lo, max(temp_dt, 1.0))
    edges = slow_grid(lo, hi, bin_s)
    yb, _ = bin_means(rate_t_s, rate, edges)
    xb, _ = bin_means(temp_t_s, temp_c, edges)
    span = float(np.nanmax(xb) - np.nanmin(xb)) if np.isfinite(xb).any() else 0.0
    if not np.isfinite(span) or span <= 0:
        return Finding("temperature", "temperature", 0.0, "t", 1.0, alpha,
                       details={"temp_span_c": 0.0},
                       why="the temperature did not change, so its effect cannot be measured")
    reg = slow_regression(xb, yb)
    half = dist.t.isf(0.025, max(reg.dof, 1)) * reg.slope_se
    ci = [reg.slope - half, reg.slope + half]
    details = {"coef_ci95": ci, "bin_s": bin_s, "block_slopes": reg.block_slopes, "n_bins": reg.n,
               "temp_span_c": span}
    if reg.p_value < alpha:
        why = (f"The slow bias follows the temperature: {reg.slope:.3g} {units}/degC over a "
               f"{span:.2g} degC swing (t = {reg.t:.1f} from the scatter between parts of "
               f"the record). Thermal sensitivity of the bias; it shows at averaging times "
               f"of {bin_s:.3g} s and longer.")
    else:
        why = (f"No significant dependence of the slow bias on temperature "
               f"({reg.slope:.3g} +- {half:.2g} {units}/degC over "
               f"{span:.2g} degC).")
    return Finding("temperature", "temperature", reg.t, "t", reg.p_value, alpha,
                   {"coef": reg.slope}, {"tau_s": [bin_s, hi - lo]}, why, details)


def drift(rate_t_s: np.ndarray, rate: np.ndarray, alpha: float = 0.05,
          units: str = "rad/s", hadamard_ratio: float | None = None) -> Finding:
    """A steady ramp of the bias beyond the slow wander of the noise.

    The slope of the bin-averaged rate against time is tested with AR(1) errors, which makes
    a random-walking or slowly correlated bias give no false drift. ``hadamard_ratio`` (Allan
    over Hadamard variance at the longest averaging time, when the caller has it) is quoted:
    a ramp raises the Allan variance as ``R^2 tau^2 / 2`` but leaves the Hadamard variance alone.

    Returns:
        Finding of kind ``"drift"`` with ``params["R"]`` in units per second.
    """
    t = np.asarray(rate_t_s, float)
    duration = float(t[-1] - t[0])
    bin_s = _bin_width(duration, 1.0)
    edges = slow_grid(float(t[0]), float(t[-1]), bin_s)
    yb, _ = bin_means(t, rate, edges)
    xb = 0.5 * (edges[:-1] + edges[1:])
    reg = slow_regression(xb, yb)
    half = dist.t.isf(0.025, max(reg.dof, 1)) * reg.slope_se
    details = {"R_ci95": [reg.slope - half, reg.slope + half],
               "bin_s": bin_s, "block_slopes": reg.block_slopes}
    if hadamard_ratio is not None:
        details["avar_over_hvar_longest_tau"] = float(hadamard_ratio)
    if reg.p_value < alpha:
        why = (f"The bias drifts steadily by {reg.slope:.3g} {units}/s ({reg.slope * duration:.3g} "
               f"{units} over the record), more than its random wander explains: a rate ramp "
               f"(warm-up, ageing or a slow temperature change). The Allan deviation rises "
               f"as tau at the longest averaging times, the Hadamard deviation does not.")
    else:
        why = f"No steady drift beyond the bias's random wander ({reg.slope:.3g} {units}/s)."
    return Finding("drift", "rate_ramp", reg.t, "t", reg.p_value, alpha, {"R": abs(reg.slope)},
                   {"tau_s": [duration / 10.0, duration]}, why, details)
