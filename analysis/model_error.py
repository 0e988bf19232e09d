"""The parts of a model's error beside the Allan chi2/dof, each about 1 (or unremarkable) when
the model describes the sensor (CONTRACT.md ``error.psd``, ``error.holdout``,
``error.time_domain`` and the ``psd`` block).

- PSD: the measured log-frequency PSD (:func:`imunoise.analysis.psd.log_psd`, the segment
  length ``analyze`` uses) against the estimator's expected value under the model
  (:func:`imunoise.analysis.psd_model.expected_log_psd`): Whittle deviance per bin
  ``mean(nu (r - 1 - ln r))``, ``r = psd/model``, and the share of bins outside their 95 %
  chi-square interval (5 % expected).
  ``misses`` says where the measured PSD leaves the model's band and what share of the
  deviance each run of points carries (:func:`imunoise.analysis.psd_model.psd_misses`).
- Hold-out: the record cut into two halves at its middle sample; the model's terms (the
  user's held parameters held) fitted on each half, from the whole record's solution (no
  starting-value search, linearised intervals: the two fits cost about one), and each half's
  model with every parameter held evaluated on the other half (a fully given model,
  :func:`imunoise.analysis.fit.fit_allan`). The part is the mean of the two chi2/dof.
  ``changed`` names the parameters whose two values differ beyond their intervals: in log
  scale, ``z = |ln a - ln b| / sqrt(se_a^2 + se_b^2)`` with ``se`` from each 95 % interval,
  widened by the misfit of the taus the parameter rests on in that half
  (``FitResult.dispersion_of``: a half that misses its long taus keeps its white level's
  interval), above the two-sided Bonferroni level 5 % over the parameters compared. An amplitude
  resolved on one half whose interval reaches zero on the other is compared on the linear
  scale (:func:`_vanished_z`); one that reaches zero on both is not compared. Parameters
  whose change shows only jointly (a white level and a filter's taps, estimated from the
  same points) are then named one at a time by :func:`_jointly_changed` (``"test":
  "joint"``), and, where the halves do not predict each other, those each half's curve
  refuses at the other half's value by :func:`_profile_changed` (``"test": "profile"``).
  ``changes_free`` is the prediction with the named parameters fitted on the half
  predicted. ``joint_difference`` reports the parameters none of these named where they
  still differ taken together beyond their intervals (:func:`_joint_difference`).
  ``misses`` (also in ``changes_free``), where the halves do not predict each other: the
  tau ranges where each half leaves the other half's band, and the parameters the predicting
  half left unresolved (:func:`_misses`).
- Time domain: the step and warm-up test of :func:`imunoise.analysis.evidence.transients`
  under the fitted model; its statistic (largest standardised contrast of block means) and
  Monte Carlo p-value over every split and time constant.

A part that cannot be computed is ``None`` in its value with a ``reason``.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from imunoise.analysis import chain_shape
from imunoise.analysis.distributions import norm
from imunoise.analysis.jobs import JobMap, serial_map
from imunoise.analysis.psd import PsdEstimate, default_nperseg, log_psd
from imunoise.analysis.psd_model import expected_log_psd, psd_misses, psd_z, whittle_part
from imunoise.analysis.terms import TermError, get_term, labels, parse_model

Model = Sequence[tuple[str, dict[str, float]]]

_Z95 = 1.959963984540054

HOLDOUT_ALPHA = 0.05
"""Family level over the parameters compared between the halves."""

NOISE_SD = 3.0
"""A part "rises beyond its noise" when it grows by more than this many of its standard
deviations: a part ``c`` per degree of freedom is a non-central chi-square over ``dof`` with
non-centrality ``dof (c - 1)``, standard deviation ``sqrt((4 c - 2)/dof)`` (``sqrt(2/dof)``
for a right model)."""


def right_model_limit(dof: float) -> float:
    """The largest part per degree of freedom a right model shows over ``dof`` degrees of
    freedom: 1 plus :data:`NOISE_SD` of its standard deviations ``sqrt(2/dof)``."""
    return 1.0 + NOISE_SD * math.sqrt(2.0 / max(float(dof), 1.0))

TIME_DOMAIN_TEST = ("bias step or warm-up: largest standardised contrast of block means "
                    "under the fitted model (max |z|), Monte Carlo p over every split and "
                    "time constant")


def _bounds(n: int, segment_starts: np.ndarray | None) -> np.ndarray:
    starts = np.zeros(1, dtype=np.int64) if segment_starts is None else np.asarray(
        segment_starts, dtype=np.int64)
    return np.append(starts, n)


def measured_psd(values: np.ndarray, fs_hz: float, segment_starts: np.ndarray | None = None
                 ) -> tuple[PsdEstimate, int]:
    """The log-frequency PSD of a channel as ``analyze`` computes it, and its segment length."""
    x = np.asarray(values, dtype=np.float64)
    longest = int(np.max(np.diff(_bounds(x.size, segment_starts)))) if x.size else 0
    nperseg = default_nperseg(longest)
    return log_psd(x, fs_hz, segment_starts=segment_starts, ci=0.95, nperseg=nperseg), nperseg


def psd_parts(model: Model, est: PsdEstimate, fs_hz: float, nperseg: int | None
              ) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(psd block, error.psd)`` of a model against a measured estimate (``nperseg``: its
    segment length, None for the streaming estimate's own)."""
    block: dict[str, Any] = {"f_hz": est.f_hz, "psd": est.psd, "dof": est.dof,
                             "ci_low": est.ci_low, "ci_high": est.ci_high}
    try:
        expected = expected_log_psd([(n, p) for n, p in model
                                     if get_term(n).role != "regressor"], est, fs_hz, nperseg)
    except ValueError as exc:
        nan = np.full(len(est.f_hz), np.nan)
        return ({**block, "model_psd": nan, "z": nan},
                {"deviance_per_bin": None, "bins": 0, "outside_95": None, "reason": str(exc)})
    block["model_psd"] = expected
    block["z"] = psd_z(est.psd, est.dof, expected)
    whittle = whittle_part(est.psd, est.dof, expected)
    if whittle is None:
        return block, {"deviance_per_bin": None, "bins": 0, "outside_95": None,
                       "reason": "fewer than 5 usable PSD points"}
    return block, {**whittle, "misses": psd_misses(est.f_hz, est.psd, est.dof, expected,
                                                   block["z"])}


def streaming_psd_part(model: Model, est: PsdEstimate, fs_hz: float
                       ) -> tuple[np.ndarray | None, dict[str, Any]]:
    """``(expected PSD or None, error.psd)`` of a model against the live service's streaming
    log-PSD estimate (:func:`psd_parts` with the estimate's own segment lengths)."""
    block, part = psd_parts(model, est, fs_hz, None)
    expected = np.asarray(block["model_psd"], dtype=np.float64)
    return (expected if np.isfinite(expected).any() else None), part


def _half(x: np.ndarray, bounds: np.ndarray, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Samples ``a..b`` and their gap-free segment starts (relative to ``a``)."""
    inner = bounds[(bounds > a) & (bounds < b)] - a
    return x[a:b], np.concatenate(([0], inner)).astype(np.int64)


def _log_se(ci: tuple[float, float] | None) -> float | None:
    if ci is None:
        return None
    lo, hi = float(ci[0]), float(ci[1])
    if not (lo > 0 and hi > lo and math.isfinite(hi)):
        return None
    return (math.log(hi) - math.log(lo)) / (2.0 * _Z95)


def _vanished_z(a: float, b: float, ci_a: tuple[float, float] | None,
                ci_b: tuple[float, float] | None) -> float | None:
    """z of an amplitude resolved on one half and consistent with zero on the other (its
    interval reaches 0), on the linear scale: the resolved value's standard error from the
    side of its interval facing zero, the vanished one's from its upper end taken as 1.96
    standard errors above zero (wider than its two-sided interval gives). None unless exactly
    one interval reaches zero."""
    if ci_a is None or ci_b is None:
        return None
    lo_a, hi_a = float(ci_a[0]), float(ci_a[1])
    lo_b, hi_b = float(ci_b[0]), float(ci_b[1])
    if not all(math.isfinite(v) for v in (lo_a, hi_a, lo_b, hi_b)):
        return None
    if lo_a > 0.0 >= lo_b:
        value, lo, other, other_hi = a, lo_a, b, hi_b
    elif lo_b > 0.0 >= lo_a:
        value, lo, other, other_hi = b, lo_b, a, hi_a
    else:
        return None
    se_value, se_other = (value - lo) / _Z95, other_hi / _Z95
    if se_value <= 0.0 or se_other <= 0.0:
        return None
    return max(value - other, 0.0) / math.hypot(se_value, se_other)


def _shape_distance(a: Any, b: Any) -> float:
    """How far apart two fitted terms of one name are in their shape parameters (log scale)."""
    amp = get_term(a.term).amplitude
    keys = [k for k in a.params if k != amp and k in b.params]
    return float(sum(abs(math.log(max(a.params[k], 1e-300)) - math.log(max(b.params[k], 1e-300)))
                     for k in keys))


def _pairs(fit_a: Any, fit_b: Any) -> list[int]:
    """For each term of ``fit_a``, the index of the same term in ``fit_b``. Repeats of a term
    (two resonances) are paired by their shape parameters, not by their order: a half's fit
    may hold the 20 Hz peak in its first resonance and the other half in its second."""
    out = list(range(len(fit_a.terms)))
    names = [t.term for t in fit_a.terms]
    for name in set(names):
        idx = [i for i, n in enumerate(names) if n == name]
        if len(idx) < 2 or len(idx) > 6:
            continue
        best = min(itertools.permutations(idx),
                   key=lambda perm: sum(_shape_distance(fit_a.terms[i], fit_b.terms[j])
                                        for i, j in zip(idx, perm, strict=True)))
        for i, j in zip(idx, best, strict=True):
            out[i] = j
    return out


def _paired_terms(fit_a: Any, fit_b: Any) -> list[tuple[str, int, int]]:
    """``(label, index in fit_a, index in fit_b)`` of each term the halves' fits share
    (:func:`_pairs`), the temperature regression left out (it is not carried into halves)."""
    names = [t.term for t in fit_a.terms]
    return [(label, i, j) for label, i, j in zip(labels(names), range(len(names)),
                                                  _pairs(fit_a, fit_b), strict=True)
            if get_term(names[i]).role != "regressor"]


def _fit_half(shared: tuple[Any, ...], k: int) -> HalfFit:
    """Half ``k``'s fit, its resonance shapes (f0, Q) from its own spectrum, by model index
    (:func:`imunoise.analysis.spectral_pins.pin_resonances`; None where that spectrum cannot
    be fitted), and the other half's chi2/dof under its model. Held shapes are measured too:
    a resonance the model holds at one frequency (as the diagnosis writes it) can still move
    between the halves, and that is a finding about the sensor. The prediction is made here,
    where the half's filter shapes are remembered from its fit (the halves have the same
    taus): in another process it costs a filtered model's shapes again, a quarter of a
    second for a Bartlett filter with a resonance on a 1.4 h half."""
    from imunoise.analysis.fit import fit_series
    from imunoise.analysis.spectral_pins import pin_resonances

    halves, fs_hz, spec, fixed, fitted = shared
    h, starts = halves[k]
    with chain_shape.using_half(k):
        fit = fit_series(h, fs_hz, spec, segment_starts=starts, fixed=fixed, start=fitted,
                         intervals="jacobian")[0]
        if _start_misled(fit, fitted):
            cold = fit_series(h, fs_hz, spec, segment_starts=starts, fixed=fixed,
                              intervals="jacobian")[0]
            if cold.misfit.chi2 < fit.misfit.chi2:
                fit = cold
        fit = fit.in_canonical_order()
    other, other_starts = halves[1 - k]
    predicts: Prediction | Exception
    try:
        with chain_shape.using_half(1 - k):
            predicts = _prediction(other, other_starts, fs_hz, fit, frozenset(), {})
    except _HALF_ERRORS as exc:
        predicts = exc
    try:
        with chain_shape.using_half(k):
            pins = pin_resonances(h, fs_hz, fit.params, set(), starts)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return HalfFit(fit, None, predicts)
    return HalfFit(fit, {p.index: p for p in pins}, predicts)


def _start_misled(half: Any, whole: Any) -> bool:
    """Whether a half's fit from the whole record's solution misses its half far worse than
    the whole record's fit misses the whole: by more than three standard deviations of a
    chi2/dof over the half's degrees of freedom, scaled by the whole's chi2/dof where above 1
    (a half has half the data, so a misfit costs it no more per degree of freedom than the
    whole). A single solve from a start with a term at its bound can wander off: ADIS16405
    run 5 accel_x with white, B, K, a Bartlett filter, a Markov term at zero and the 0.47 Hz
    line reaches chi2/dof 6554 on each half from the whole record's solution (the filter
    traded for the Markov term), 115 and 138 from the full starting-value search."""
    return float(half.chi2_per_dof) > max(float(whole.chi2_per_dof), 1.0) \
        * right_model_limit(half.misfit.dof)


Recheck = Callable[[int, int, str, float], float | None]
"""``(half, term index, parameter, value) -> rise of that half's chi2`` when the parameter is
held at the value and the rest refitted (None when the refit fails)."""

Rechecks = Callable[[Sequence[tuple[int, int, str, float]]], list[float | None]]
""":data:`Recheck` of each ``(half, term index, parameter, value)``, in that order."""


def _changed(fit_a: Any, fit_b: Any, shapes: Sequence[dict[int, Any]] = ({}, {}),
             recheck: Recheck | None = None) -> list[dict[str, Any]]:
    """Parameters fitted on both halves whose values differ beyond their intervals. A
    resonance's f0, Q and power come from each half's spectrum where both spectra resolve
    its peak (``shapes``; ``"source": "psd"``). An amplitude that vanished on one half is
    named only if that half's data also refuse the near end of the other half's interval
    (``recheck``): flicker and random walk trade places on a half's few long-tau points, so
    one of them can reach zero while the half's curve is the other's."""
    from imunoise.analysis.spectral_pins import PINNED

    pairs = []
    vanished: dict[int, tuple[int, int, str, Any, Any]] = {}
    for label, i, j in _paired_terms(fit_a, fit_b):
        ta, tb = fit_a.terms[i], fit_b.terms[j]
        pa, pb = shapes[0].get(i), shapes[1].get(j)
        for k in ta.params:
            a, b = float(ta.params[k]), float(tb.params[k])
            ca, cb, source = ta.ci95.get(k), tb.ci95.get(k), "allan"
            if pa is not None and pb is not None and k in PINNED:
                a, b, ca, cb, source = pa.params[k], pb.params[k], pa.ci95[k], pb.ci95[k], "psd"
            elif pa is not None and pb is not None and k == "sigma":
                # the peak's power: the spectrum tells it apart from the terms that bend the
                # Allan curve at the same taus
                a, b, ca, cb, source = pa.params[k], pb.params[k], pa.sigma_ci95, \
                    pb.sigma_ci95, "psd"
            sa, sb = _log_se(ca), _log_se(cb)
            if sa is None or sb is None or sa == 0.0 and sb == 0.0:
                z = _vanished_z(a, b, ca, cb)
                if z is not None:
                    pairs.append((f"{label}.{k}", a, b, z, source))
                    vanished[len(pairs) - 1] = (i, j, k, ca, cb)
                continue  # held, or no estimate on a half
            if source == "allan":
                # a half whose fit misses the taus a parameter rests on has a wider interval
                # for it than it reports
                sa *= math.sqrt(fit_a.dispersion_of(i, k))
                sb *= math.sqrt(fit_b.dispersion_of(j, k))
            z = abs(math.log(a) - math.log(b)) / math.hypot(sa, sb)
            pairs.append((f"{label}.{k}", a, b, z, source))
    if not pairs:
        return []
    crit = float(norm.isf(HOLDOUT_ALPHA / (2.0 * len(pairs))))
    out = [{"param": p, "values": [a, b], "z": z, "source": src}
           for n, (p, a, b, z, src) in enumerate(pairs)
           if z > crit and (n not in vanished or recheck is None
                            or _refused(recheck, fits=(fit_a, fit_b), at=vanished[n],
                                        crit=crit))]
    named = {str(c["param"]) for c in out}
    return out + _jointly_changed(fit_a, fit_b, named, crit)


def _refused(recheck: Recheck, fits: tuple[Any, Any], at: tuple[int, int, str, Any, Any],
             crit: float) -> bool:
    """Whether the half where an amplitude vanished refuses the near end of the other half's
    interval: held there, its chi2 (scaled by the misfit of the taus the amplitude rests on,
    ``FitResult.dispersion_of``) rises beyond ``crit^2``."""
    i, j, k, ca, cb = at
    resolved_a = float(ca[0]) > 0.0
    half, index, near = (1, j, float(ca[0])) if resolved_a else (0, i, float(cb[0]))
    rise = recheck(half, index, k, near)
    if rise is None:
        return True  # no refit to judge by: the intervals alone decide
    return rise / fits[half].dispersion_of(index, k) > crit * crit


def _jointly_changed(fit_a: Any, fit_b: Any, named: set[str], crit: float
                     ) -> list[dict[str, Any]]:
    """Parameters that changed between the halves seen through their correlations.

    A white level and a filter's taps are estimated from the same short-tau points, so each
    one's own interval is wide while their joint difference is not: the halves can differ
    beyond their intervals with no parameter doing so on its own (ADIS16405 run 5 gyro_x:
    white.N -0.4 %, marginal z 2.0, yet the other half's model misses its shortest tau by
    z 5). The log-parameter differences ``d`` of the well-determined parameters (linearised
    standard error below 0.5 on both halves, not yet named) have covariance
    ``S = D_a S_a D_a + D_b S_b D_b``, each half's covariance scaled by the misfit of the taus
    each parameter rests on (``D`` the square roots of ``FitResult.dispersion_of``; amplitudes
    whose interval reaches zero on a half are left out).
    Only when ``d' S^-1 d`` exceeds the chi-square level ``HOLDOUT_ALPHA`` are parameters
    named, one at a time: the parameter's change estimated with the others held equal
    (``z = (S^-1 d)_p / sqrt((S^-1)_pp)``) is named when beyond ``crit``, and is then left
    out, so the next is judged with the named ones free to differ."""
    from imunoise.analysis.distributions import chi2

    keys, diff, cov = _joint_differences(fit_a, fit_b, named)
    idx = list(range(len(keys)))
    out: list[dict[str, Any]] = []
    while idx:
        s = cov[np.ix_(idx, idx)]
        try:
            prec = np.linalg.inv(s)
        except np.linalg.LinAlgError:
            break
        dd = diff[idx]
        if not float(dd @ prec @ dd) > float(chi2.isf(HOLDOUT_ALPHA, len(idx))):
            break
        z = (prec @ dd) / np.sqrt(np.maximum(np.diag(prec), 1e-300))
        best = int(np.argmax(np.abs(z)))
        if not abs(float(z[best])) > crit:
            break
        name, a, b = keys[idx[best]]
        out.append({"param": name, "values": [a, b], "z": abs(float(z[best])),
                    "source": "allan", "test": "joint"})
        del idx[best]
    return out


def _joint_differences(fit_a: Any, fit_b: Any, named: set[str]
                       ) -> tuple[list[tuple[str, float, float]], np.ndarray, np.ndarray]:
    """``(keys, d, S)`` of :func:`_jointly_changed`: each well-determined parameter not in
    ``named`` as ``(label.param, value a, value b)``, the halves' log-parameter differences
    and their covariance (each half's scaled by the misfit of the taus each parameter rests
    on, ``FitResult.dispersion_of``)."""
    rows_a = {k: n for n, k in enumerate(fit_a.free_params)}
    rows_b = {k: n for n, k in enumerate(fit_b.free_params)}
    keys, ia, ib, d = [], [], [], []
    for label, i, j in _paired_terms(fit_a, fit_b):
        for k in fit_a.terms[i].params:
            name = f"{label}.{k}"
            if name in named or (i, k) not in rows_a or (j, k) not in rows_b:
                continue
            a, b = float(fit_a.terms[i].params[k]), float(fit_b.terms[j].params[k])
            # an amplitude at its bound has a vanishing Jacobian column: no covariance
            if not (a > 0.0 and b > 0.0) or _log_se(fit_a.terms[i].ci95.get(k)) is None \
                    or _log_se(fit_b.terms[j].ci95.get(k)) is None:
                continue
            keys.append((name, a, b))
            ia.append(rows_a[(i, k)])
            ib.append(rows_b[(j, k)])
            d.append(math.log(a) - math.log(b))
    if not keys:
        return [], np.zeros(0), np.zeros((0, 0))
    cov_a = _scaled_cov(fit_a, ia)
    cov_b = _scaled_cov(fit_b, ib)
    sd_a, sd_b = np.sqrt(np.abs(np.diag(cov_a))), np.sqrt(np.abs(np.diag(cov_b)))
    keep = np.flatnonzero(np.isfinite(sd_a) & np.isfinite(sd_b) & (sd_a > 0) & (sd_b > 0)
                          & (sd_a < 0.5) & (sd_b < 0.5))
    cov = (cov_a + cov_b)[np.ix_(keep, keep)]
    return [keys[n] for n in keep], np.asarray(d)[keep], cov


def _scaled_cov(fit: Any, rows: Sequence[int]) -> np.ndarray:
    """The covariance of the log-parameters in ``rows`` (of ``fit.free_params``), each
    parameter's standard deviation widened by the misfit of the taus it rests on."""
    d = np.sqrt([fit.dispersion_of(*fit.free_params[r]) for r in rows])
    return np.asarray(fit.param_cov)[np.ix_(rows, rows)] * np.outer(d, d)


def _joint_difference(fit_a: Any, fit_b: Any, named: set[str]) -> dict[str, Any] | None:
    """The halves' difference in the parameters none of the tests named, where it exceeds
    their intervals taken together: ``{"params", "chi2", "dof", "p"}`` when ``d' S^-1 d``
    (:func:`_joint_differences`) lies beyond the chi-square level ``HOLDOUT_ALPHA``, else
    None. Several parameters can each differ by one or two of their standard errors, none
    beyond its own level, and the halves still differ as a whole (ADIS16405 run 2 accel_y:
    chi2 16.7 over 7 parameters, p 0.02, the largest single z 1.9): a finding that names
    no parameter."""
    from imunoise.analysis.distributions import chi2

    keys, diff, cov = _joint_differences(fit_a, fit_b, named)
    if not keys:
        return None
    try:
        q = float(diff @ np.linalg.solve(cov, diff))
    except np.linalg.LinAlgError:
        return None
    if not (math.isfinite(q) and q > float(chi2.isf(HOLDOUT_ALPHA, len(keys)))):
        return None
    return {"params": [k for k, _, _ in keys], "chi2": q, "dof": len(keys),
            "p": float(chi2.sf(q, len(keys)))}


def _profile_changed(fit_a: Any, fit_b: Any, named: Sequence[dict[str, Any]],
                     rises: Rechecks) -> list[dict[str, Any]]:
    """Parameters whose change shows in the curves themselves, where the intervals do not
    show it: called only when the halves do not predict each other (the hold-out part
    beyond its noise).

    Each half's interval of an amplitude near its bound, widened by that half's misfit, is
    wide on the log scale; the curve can still refuse the other half's value. For each
    parameter not yet named, ``R_a`` is the rise of half a's chi2 with the parameter held at
    half b's value and the rest refitted, ``R_b`` the converse, each divided by the misfit of
    the taus the parameter rests on in that half (``FitResult.dispersion_of``). Where each
    half's chi2 is quadratic in the parameter, the smallest summed rise over one shared
    value is ``1 / (1/R_a + 1/R_b)``: a chi-square with one degree of freedom when the
    parameter did not change. It is named (``"test":
    "profile"``) beyond the Bonferroni level over the parameters compared. ADIS16405 run 3
    accel_z warms up in its first hour: the random walk is 5.9e-4 on the first half, 1.6e-4
    on the second, and held there the first half's chi2 rises by 99 (z 3.2 against the
    level 2.73 over the 8 parameters that differ); its intervals alone give z 2.6 (level
    2.81). As the combination is below either rise, half b is
    refitted only for the parameters whose ``R_a`` exceeds the level."""
    done = {str(c["param"]) for c in named}
    compared = []
    for label, i, j in _paired_terms(fit_a, fit_b):
        for k in fit_a.terms[i].params:
            a, b = float(fit_a.terms[i].params[k]), float(fit_b.terms[j].params[k])
            if a != b:  # a held parameter has one value
                compared.append((f"{label}.{k}", i, j, k, a, b))
    if not compared:
        return []
    crit = float(norm.isf(HOLDOUT_ALPHA / (2.0 * len(compared))))
    todo = [c for c in compared if c[0] not in done]

    def scaled(rise: float | None, fit: Any, index: int, param: str) -> float:
        # 0 for a half that does not mind the other's value (or cannot be refitted)
        return rise / fit.dispersion_of(index, param) if rise is not None and rise > 0.0 \
            else 0.0

    first = [scaled(r, fit_a, i, k)
             for r, (_, i, _, k, _, _) in zip(rises([(0, i, k, b) for _, i, _, k, _, b in todo]),
                                              todo, strict=True)]
    beyond = [(c, r) for c, r in zip(todo, first, strict=True) if r > crit * crit]
    second = [scaled(r, fit_b, j, k)
              for r, ((_, _, j, k, _, _), _) in zip(
                  rises([(1, j, k, a) for (_, _, j, k, a, _), _ in beyond]), beyond,
                  strict=True)]
    out: list[dict[str, Any]] = []
    for ((name, _, _, _, a, b), r_a), r_b in zip(beyond, second, strict=True):
        if r_b <= 0.0:
            continue
        z = math.sqrt(1.0 / (1.0 / r_a + 1.0 / r_b))
        if z > crit:
            out.append({"param": name, "values": [a, b], "z": z, "source": "allan",
                        "test": "profile"})
    return out


@dataclass
class HoldoutHalves:
    """The two halves of a record and what their fits start from: the jobs of a hold-out
    part (:func:`fit_half` of ``k`` = 0, 1), which a caller may run among its own jobs and
    hand to :meth:`part`."""

    halves: list[tuple[np.ndarray, np.ndarray]]
    fs_hz: float
    spec: Any
    fixed: dict | None
    fitted: Any
    memo: dict = field(default_factory=dict)
    """The halves' Allan curves, computed once for the refits of :meth:`part`."""

    def shared(self) -> tuple[Any, ...]:
        """The context of :func:`fit_half`."""
        return (self.halves, self.fs_hz, self.spec, self.fixed, self.fitted)

    def part(self, done: Sequence[Any], by_curves: bool = True,
             job_map: JobMap = serial_map) -> dict[str, Any]:
        """``error.holdout`` from both halves' :func:`fit_half` results: each half's model
        predicting the other half, and the parameters that changed (``by_curves``: also
        those each half's curve refuses at the other's value, :func:`_profile_changed`,
        up to two refits of a half per parameter where the halves miss each other, run by
        ``job_map``). Where parameters changed, ``changes_free`` is the prediction with
        them fitted on the half predicted: what is left of the part once the findings are
        taken as findings."""
        failed = next((d for d in done if isinstance(d, Exception)), None)
        if failed is not None:
            return _unfitted(failed)
        fits = [d.fit for d in done]
        # half 0 as half 1's model predicts it, then half 1 as half 0's does
        predicted = [done[1].predicts, done[0].predicts]
        failed = next((c for c in predicted if isinstance(c, Exception)), None)
        if failed is not None:
            return _unfitted(failed)
        preds = [p for p in predicted if isinstance(p, Prediction)]
        chis = [p.chi2_per_dof for p in preds]
        recheck = functools.partial(self._held_rise, fits)
        changed = _changed(fits[0], fits[1], _shapes_of(done), recheck)
        if by_curves and float(np.mean(chis)) > right_model_limit(
                min(f.misfit.dof for f in fits)):
            def rises(items: Sequence[tuple[int, int, str, float]]) -> list[float | None]:
                return job_map(_held_rise_job, (self, fits), items) if items else []

            changed += _profile_changed(fits[0], fits[1], changed, rises)
        out = {"chi2_per_dof": float(np.mean(chis)), "parts": 2,
               "halves": [float(c) for c in chis], "changed": changed,
               "misses": _misses(preds, fits)}
        names = sorted({str(c["param"]) for c in changed})
        joint = _joint_difference(fits[0], fits[1], set(names))
        if joint is not None:
            out["joint_difference"] = joint
        if names:
            try:
                loose = job_map(_prediction_job, (self, fits, frozenset(names)), [0, 1])
            except _HALF_ERRORS:
                return out
            out["changes_free"] = {"chi2_per_dof": float(np.mean([p.chi2_per_dof
                                                                 for p in loose])),
                                   "halves": [p.chi2_per_dof for p in loose],
                                   "params": names, "misses": _misses(loose, fits)}
        return out

    def predicted(self, k: int, other: Any, free: frozenset[str] = frozenset()
                  ) -> Prediction:
        """Half ``k`` predicted by the other half's fitted model ``other``, every parameter
        held but those labelled in ``free`` (fitted on half ``k``)."""
        h, starts = self.halves[k]
        with chain_shape.using_half(k):
            return _prediction(h, starts, self.fs_hz, other, free, self.memo)

    def _held_rise(self, fits: Sequence[Any], half: int, index: int, param: str,
                   value: float) -> float | None:
        """Rise of half ``half``'s chi2 with ``param`` of term ``index`` held at ``value``."""
        from imunoise.analysis.fit import fit_series

        fixed = {i: dict(p) for i, p in (self.fixed or {}).items()}
        fixed.setdefault(index, {})[param] = float(value)
        h, starts = self.halves[half]
        try:
            # only chi2 is wanted: no profile intervals
            with chain_shape.using_half(half):
                held = fit_series(h, self.fs_hz, self.spec, segment_starts=starts,
                                  fixed=fixed, start=fits[half], intervals="jacobian",
                                  memo=self.memo, profile_terms=())[0]
        except _HALF_ERRORS:
            return None
        return max(0.0, float(held.misfit.chi2 - fits[half].misfit.chi2))


def _held_rise_job(shared: tuple[HoldoutHalves, Sequence[Any]],
                   item: tuple[int, int, str, float]) -> float | None:
    """:meth:`HoldoutHalves._held_rise` as a job of a job map."""
    setup, fits = shared
    return setup._held_rise(fits, *item)


def _prediction_job(shared: tuple[HoldoutHalves, Sequence[Any], frozenset[str]], k: int
                    ) -> Prediction:
    """:meth:`HoldoutHalves.predicted` of half ``k`` by the other half's fit, as a job."""
    setup, fits, free = shared
    return setup.predicted(k, fits[1 - k], free)


class Prediction(NamedTuple):
    """One half of the record under the other half's fitted model."""

    chi2_per_dof: float
    failures: list[dict[str, Any]]
    """The tau ranges where the half's Allan curve lies outside the model's band
    (:func:`imunoise.analysis.misfit.failures`)."""


def _prediction(h: np.ndarray, starts: np.ndarray, fs_hz: float, other: Any,
                free: frozenset[str], memo: dict) -> Prediction:
    """The samples ``h`` under the fitted model ``other``, every parameter held but those
    labelled in ``free``."""
    from imunoise.analysis.fit import fit_series

    given = [(t.term, dict(t.params)) for t in other.terms]
    names = labels([n for n, _ in given])
    held: dict[str | int, dict[str, float]] = {
        i: {k: v for k, v in p.items() if f"{label}.{k}" not in free}
        for i, ((_, p), label) in enumerate(zip(given, names, strict=True))}
    fit = fit_series(h, fs_hz, given, segment_starts=starts, fixed=held,
                     intervals="jacobian", memo=memo, profile_terms=())[0]
    return Prediction(float(fit.chi2_per_dof), list(fit.failures))


def _unresolved_by(predictor: Any, predicted: Any) -> list[dict[str, Any]]:
    """The parameters that the predicting half's fit does not resolve (its 95 % interval
    reaches zero) and the predicted half's does: ``{"param", "value", "ci95"}`` with the
    predicted half's value and interval. Such a parameter sits at or near zero in the model
    that predicts, while the half predicted shows it: a random walk that one half of a night
    cannot tell from flicker predicts the other half's long taus below what they measure."""
    out = []
    for label, i, j in _paired_terms(predictor, predicted):
        mine, theirs = predictor.terms[i], predicted.terms[j]
        for k in mine.params:
            ca, cb = mine.ci95.get(k), theirs.ci95.get(k)
            if ca is None or cb is None or k not in theirs.params:
                continue
            if float(ca[0]) <= 0.0 < float(cb[0]) and math.isfinite(float(cb[1])):
                out.append({"param": f"{label}.{k}", "value": float(theirs.params[k]),
                            "ci95": [float(cb[0]), float(cb[1])]})
    return out


def _misses(preds: Sequence[Prediction], fits: Sequence[Any]) -> list[dict[str, Any]]:
    """Where each half's curve lies outside the band of the other half's model: ``{"half",
    "by", "failures", "unresolved"}`` (halves counted from 1) for each prediction that fails
    somewhere, with the parameters the predicting half leaves unresolved
    (:func:`_unresolved_by`). Only where the halves do not predict each other (the part
    beyond a right model's limit): a right model's halves, each with its own estimation
    error, miss a single short tau of the other now and then (z 3.4 at 0.64 s on a
    simulated record whose part is 1.5)."""
    if not float(np.mean([p.chi2_per_dof for p in preds])) > right_model_limit(
            min(f.misfit.dof for f in fits)):
        return []
    out = []
    for k, pred in enumerate(preds):
        if pred.failures:
            out.append({"half": k + 1, "by": 2 - k, "failures": pred.failures,
                        "unresolved": _unresolved_by(fits[1 - k], fits[k])})
    return out


class HalfFit(NamedTuple):
    """What :func:`fit_half` gives for one half of the record."""

    fit: Any
    """The half's :class:`imunoise.analysis.fit.FitResult`, terms in canonical order."""
    shapes: dict[int, Any] | None
    """Its resonances' shapes from its own spectrum, by model index (None where that
    spectrum cannot be fitted)."""
    predicts: Prediction | Exception
    """The other half under this half's model, every parameter held; or the exception that
    says why it cannot be computed."""


_HALF_ERRORS = (ValueError, ArithmeticError, np.linalg.LinAlgError)
"""What a half that cannot be fitted raises (too short, no finite curve)."""


def _unfitted(exc: BaseException) -> dict[str, Any]:
    return {"chi2_per_dof": None, "parts": 2, "reason": f"a half cannot be fitted: {exc}"}


def fit_half(shared: tuple[Any, ...], k: int) -> HalfFit | Exception:
    """:func:`_fit_half`, or the exception that says why half ``k`` cannot be fitted (given
    back, not raised, so that it does not stop the other jobs of a job map)."""
    try:
        return _fit_half(shared, k)
    except _HALF_ERRORS as exc:
        return exc


def holdout_halves(values: np.ndarray, fs_hz: float, model: Any, fitted: Any,
                   segment_starts: np.ndarray | None = None, fixed: dict | None = None
                   ) -> HoldoutHalves | dict[str, Any]:
    """The :class:`HoldoutHalves` of :func:`holdout_part`, or its ``error.holdout`` when the
    model cannot be carried into halves."""
    x = np.asarray(values, dtype=np.float64)
    spec = parse_model(model)
    if any(get_term(n).role == "regressor" for n in spec.names):
        return {"chi2_per_dof": None, "parts": 2,
                "reason": "a temperature regression is not carried into the halves"}
    if any(get_term(n).needs_record == "channels" for n in spec.names):
        chain_shape.prepare_halves()  # here, not in each worker the halves' fits run in
    bounds = _bounds(x.size, segment_starts)
    mid = x.size // 2
    return HoldoutHalves([_half(x, bounds, 0, mid), _half(x, bounds, mid, x.size)], fs_hz,
                         spec, fixed, fitted)


def holdout_part(values: np.ndarray, fs_hz: float, model: Any, fitted: Any,
                 segment_starts: np.ndarray | None = None,
                 fixed: dict | None = None, job_map: JobMap = serial_map,
                 by_curves: bool = True) -> dict[str, Any]:
    """``error.holdout``: the model fitted on each half predicting the other half.

    ``model`` is the specification the user gave (held parameters stay held), ``fitted`` the
    whole record's :class:`imunoise.analysis.fit.FitResult` (the halves' fits start there).
    ``job_map`` runs the two halves' fits (:mod:`imunoise.analysis.jobs`; the same result
    whichever runs them); ``by_curves``: see :meth:`HoldoutHalves.part`.
    """
    setup = holdout_halves(values, fs_hz, model, fitted, segment_starts, fixed)
    if isinstance(setup, dict):
        return setup
    return setup.part(job_map(fit_half, setup.shared(), [0, 1]), by_curves, job_map)


def _shapes_of(done: Sequence[HalfFit]) -> list[dict[int, Any]]:
    """Both halves' resonance shapes, or none where one half's spectrum could not be fitted
    (the Allan fits' intervals judge the resonance then)."""
    shapes = [d.shapes for d in done]
    return [{}, {}] if any(s is None for s in shapes) else [dict(s or {}) for s in shapes]


def time_domain_part(values: np.ndarray, fs_hz: float, model: Model,
                     segment_starts: np.ndarray | None = None, units: str = "rad/s",
                     findings: Sequence[Any] | None = None) -> dict[str, Any]:
    """``error.time_domain``: the transient test under the fitted model (``findings``: the
    ``(step, warmup)`` findings when already computed)."""
    from imunoise.analysis import evidence

    if any(get_term(n).role == "regressor" for n, _ in model):
        return {"statistic": None, "p": None, "test": TIME_DOMAIN_TEST,
                "reason": "not computed under a temperature regression"}
    if findings is None:
        x = np.asarray(values, dtype=np.float64)
        b = _bounds(x.size, segment_starts)
        segments = [x[s:e] for s, e in zip(b[:-1], b[1:], strict=True) if e > s]
        findings = evidence.transients(segments, fs_hz, list(model), units=units)
    best = min(findings, key=lambda f: f.p_value)
    if not math.isfinite(float(best.statistic)) or best.statistic == 0.0:
        return {"statistic": None, "p": None, "test": TIME_DOMAIN_TEST,
                "reason": best.why or "record too short for the test"}
    return {"statistic": float(best.statistic), "p": float(best.p_value),
            "test": TIME_DOMAIN_TEST, "kind": best.kind}


def error_parts(values: np.ndarray, fs_hz: float, model: Any, fitted: Any,
                segment_starts: np.ndarray | None = None, fixed: dict | None = None,
                units: str = "rad/s", holdout: bool = True,
                transient_findings: Sequence[Any] | None = None,
                job_map: JobMap = serial_map
                ) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """``(psd block, {"psd", "holdout", "time_domain"})`` of a fitted model on a channel.

    ``job_map`` runs the hold-out halves' fits, the PSD part and the time-domain part side
    by side (:mod:`imunoise.analysis.jobs`; the same result whichever runs them), then the
    hold-out part's own jobs (see :func:`holdout_part`)."""
    setup: HoldoutHalves | dict[str, Any] = {"chi2_per_dof": None, "parts": 2,
                                             "reason": "not requested"}
    if holdout:
        setup = holdout_halves(values, fs_hz, model, fitted, segment_starts, fixed)
    jobs: list[tuple[str, int]] = [("half", 0), ("half", 1)] \
        if isinstance(setup, HoldoutHalves) else []
    jobs += [("psd", 0), ("time_domain", 0)]
    done = job_map(_part_job, _PartsContext(values, fs_hz, fitted.params, segment_starts,
                                            units, transient_findings, setup), jobs)
    block, psd = done[-2]
    parts: dict[str, Any] = {"psd": psd}
    parts["holdout"] = setup.part(done[:2], job_map=job_map) \
        if isinstance(setup, HoldoutHalves) else setup
    parts["time_domain"] = done[-1]
    return block, parts


@dataclass
class _PartsContext:
    """What the jobs of :func:`error_parts` read."""

    values: np.ndarray
    fs_hz: float
    params: Model
    segment_starts: np.ndarray | None
    units: str
    transient_findings: Sequence[Any] | None
    setup: HoldoutHalves | dict[str, Any]


def _part_job(ctx: _PartsContext, item: tuple[str, int]) -> Any:
    """One job of :func:`error_parts`: a hold-out half's :func:`fit_half`, the PSD part
    ``(psd block, error.psd)`` or the time-domain part."""
    kind, k = item
    if kind == "half":
        assert isinstance(ctx.setup, HoldoutHalves)  # halves are only asked for when set up
        return fit_half(ctx.setup.shared(), k)
    if kind == "time_domain":
        return time_domain_part(ctx.values, ctx.fs_hz, ctx.params, ctx.segment_starts,
                                ctx.units, ctx.transient_findings)
    try:
        est, nperseg = measured_psd(ctx.values, ctx.fs_hz, ctx.segment_starts)
        return psd_parts(ctx.params, est, ctx.fs_hz, nperseg)
    except ValueError as exc:
        return None, {"deviance_per_bin": None, "bins": 0, "outside_95": None,
                      "reason": f"no PSD: {exc}"}


def plain(value: Any) -> Any:
    """``value`` with numpy arrays and numbers as plain lists and floats, and non-finite
    numbers as None (strict JSON)."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return [plain(v) for v in value.tolist()]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return v if math.isfinite(v) else None
    return value


def parts_line(chi2_per_dof: float, parts: dict[str, Any]) -> str:
    """The parts of the error side by side, for the text output."""
    def num(x: Any) -> str:
        return "n/a" if x is None or not math.isfinite(float(x)) else f"{float(x):.3g}"

    def why(part: dict[str, Any]) -> str:
        # a part not computed says why
        return f" ({part['reason']})" if part.get("reason") else ""

    psd = parts.get("psd") or {}
    ho = parts.get("holdout") or {}
    td = parts.get("time_domain") or {}
    out = f"error: allan chi2/dof {num(chi2_per_dof)} | psd deviance/bin " \
          f"{num(psd.get('deviance_per_bin'))}"
    if psd.get("outside_95") is not None:
        out += f" ({100.0 * psd['outside_95']:.0f} % of {psd.get('bins')} bins outside 95 %)"
    elif psd.get("deviance_per_bin") is None:
        out += why(psd)
    out += f" | hold-out chi2/dof {num(ho.get('chi2_per_dof'))}"
    if (ho.get("changes_free") or {}).get("chi2_per_dof") is not None:
        out += f" ({num(ho['changes_free']['chi2_per_dof'])} with the changes below fitted)"
    elif ho.get("chi2_per_dof") is None:
        out += why(ho)
    if td.get("statistic") is None:
        out += f" | time domain n/a{why(td)}"
    else:
        out += f" | time domain max|z| {num(td.get('statistic'))} (p {num(td.get('p'))})"
    return "\n".join([out] + [f"  psd: {m}" for m in psd_miss_lines(psd)]
                     + [f"  finding: {f}" for f in holdout_findings(ho)])


PSD_MISS_SHARE = 0.05
"""A PSD miss is told in the text when its bins carry at least this share of the deviance."""

PSD_MISS_LINES = 4
"""At most this many PSD misses are told in the text (the largest shares)."""


def psd_miss_lines(psd: dict[str, Any]) -> list[str]:
    """The PSD part's misses (``error.psd.misses``) that make it large, as sentences: those
    carrying at least :data:`PSD_MISS_SHARE` of the deviance, at most
    :data:`PSD_MISS_LINES` of them, in frequency order."""
    misses = [m for m in psd.get("misses") or [] if m["deviance_share"] >= PSD_MISS_SHARE]
    told = sorted(sorted(misses, key=lambda m: -m["deviance_share"])[:PSD_MISS_LINES],
                  key=lambda m: m["f_hz"][0])
    out = []
    for m in told:
        out.append(f"{m['direction']} at {_span(*m['f_hz'])} Hz (max |z| {m['max_abs_z']:.3g}, "
                   f"{100.0 * m['deviance_share']:.0f} % of the deviance)")
    rest = len(psd.get("misses") or []) - len(told)
    if out and rest > 0:
        out[-1] += f"; {rest} smaller miss{'es' if rest > 1 else ''} not shown"
    return out


def holdout_findings(holdout: dict[str, Any]) -> list[str]:
    """The hold-out part's findings (``error.holdout``) as sentences: each parameter that
    changed between the halves, then a difference of the halves taken together."""
    out = []
    for c in holdout.get("changed") or []:
        a, b = c["values"]
        unit = _unit_of(str(c["param"]))
        src = " (from each half's spectrum)" if c.get("source") == "psd" else ""
        how = {"joint": ", the other parameters held equal",
               "profile": ", each half's curve held at the other's value"}.get(
                   str(c.get("test")), "")
        out.append(f"{c['param']} changed between the first and second half: "
                   f"{a:.4g} -> {b:.4g}{unit}{src} (z = {c['z']:.1f}{how})")
    joint = holdout.get("joint_difference")
    if joint:
        out.append(f"the halves differ in {', '.join(joint['params'])} taken together "
                   f"(chi2 {joint['chi2']:.1f} over {joint['dof']} parameters, "
                   f"p {joint['p']:.2g}), none beyond its own level")
    free = holdout.get("changes_free") or {}
    misses = free["misses"] if "misses" in free else holdout.get("misses") or []
    return out + [_miss_sentence(m, bool(free)) for m in misses]


_ORDINAL = {1: "first", 2: "second"}


def _span(a: float, b: float) -> str:
    """``a-b`` to three digits, or ``a`` alone where the two print alike."""
    return f"{a:.3g}" if f"{a:.3g}" == f"{b:.3g}" else f"{a:.3g}-{b:.3g}"


def _miss_sentence(miss: dict[str, Any], changes_fitted: bool) -> str:
    """One entry of ``misses`` as a sentence: where the half's curve leaves the other half's
    band, and what the predicting half did not resolve."""
    by, half = _ORDINAL.get(int(miss["by"]), str(miss["by"])), \
        _ORDINAL.get(int(miss["half"]), str(miss["half"]))
    where = "; ".join(f"{f['direction']} at tau {_span(*f['tau_s'])} s "
                      f"(max |z| {f['max_abs_z']:.1f})" for f in miss["failures"])
    text = (f"the {by} half's model{' with the changes fitted' if changes_fitted else ''} "
            f"misses the {half} half: {where}")
    for u in miss.get("unresolved") or []:
        lo, hi = u["ci95"]
        text += (f"; {u['param']} is not resolved on the {by} half (its interval reaches 0) "
                 f"but is {u['value']:.3g} [{lo:.3g}, {hi:.3g}]{_unit_of(str(u['param']))} "
                 f"on the {half}")
    return text


def _unit_of(param: str) -> str:
    """`` Hz``, `` s`` or `` samples`` for a parameter with that unit; nothing for one in the
    channel's units (the line names the parameter, whose unit the model table gives)."""
    label, _, name = param.rpartition(".")
    try:
        kind = get_term(label.split("#")[0]).param(name).kind
    except (KeyError, ValueError, TermError):
        return ""
    return f" {kind}" if kind in ("Hz", "s", "samples") else ""
