"""Diagnosis: which physical effect is the model missing?

Given a channel and a model, the model is fitted to the overlapping Allan curve; then every
term of the vocabulary that the model lacks is added in turn and the model refitted. The
misfit of the fit (``chi2``: the whitened, correlation-aware sum of squared standardised
residuals of :mod:`imunoise.analysis.misfit`) falls when the term is right. Under the hypothesis
that
the term is absent, the fall is approximately chi-square distributed with as many degrees of
freedom as the term has parameters (a likelihood-ratio test on the decorrelated misfit).

Evidence the Allan curve cannot give (:mod:`imunoise.analysis.evidence`) joins in: a spectral line
supports ``sinusoid``, correlation with the temperature record supports ``temperature``, a
steady slope supports ``rate_ramp``. Each candidate's p-value is the smaller of its sources'
(Bonferroni over the sources) and the candidates are ranked by it; a candidate is
``significant`` when its p-value, Bonferroni-corrected for the number of candidates, is below
``alpha``. The ranking follows the p-values (kept in log form, as strong effects give values
far below the floating-point range). So on data the model fully explains, nothing is
flagged with probability at least ``1 - alpha``. Outliers, gaps, a changing noise level and
the shortest taus a sensor's filter pulls below the model are reported alongside: they are
not noise terms to add, but they are why a model can look wrong.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import special

from imunoise.analysis import distributions as dist
from imunoise.analysis import evidence
from imunoise.analysis.default_model import DEFAULT_MODEL
from imunoise.analysis.evidence.finding import Finding, family_p
from imunoise.analysis.evidence.resonance_drift import MIN_Q as DRIFT_MIN_Q
from imunoise.analysis.evidence.transients import holds_zero
from imunoise.analysis.fit import FitResult, fit_series
from imunoise.analysis.jobs import JobMap, serial_map
from imunoise.analysis.model_error import (
    NOISE_SD,
    HoldoutHalves,
    fit_half,
    holdout_halves,
    holdout_part,
    measured_psd,
    psd_parts,
    right_model_limit,
    time_domain_part,
)
from imunoise.analysis.spectral_pins import PINNED, pin_resonances, pinned_of
from imunoise.analysis.terms import (
    TERMS,
    Entry,
    ModelSpec,
    TermError,
    get_term,
    model_psd,
    parse_model,
)
from imunoise.analysis.terms.gauss_markov import MIN_T_SAMPLES
from imunoise.core.series import ChannelSeries

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


def _times(n: int, fs_hz: float, t0_s: float) -> np.ndarray:
    return t0_s + np.arange(n) / fs_hz


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
HOLDOUT_CHECKS = 3
"""Significant suggestions whose hold-out part is computed (best first) before giving up:
each costs two fits on the halves."""


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


def _sensor_filter(fit: FitResult, alpha: float) -> Finding | None:
    """The shortest taus the fit set aside because they lie below every sum of terms (a
    filter's signature), or None."""
    used = getattr(fit, "used", None)
    if used is None or bool(np.all(used)):
        return None
    aside = ~np.asarray(used, dtype=bool)
    z = np.asarray(fit.z)[aside]
    tau = np.asarray(fit.tau_s)[aside]
    if not bool(np.all(z < 0)):
        return None  # measured above the model there: a missing term, which the refits test
    zmax = float(np.max(np.abs(z)))
    p = family_p(float(2.0 * dist.norm.sf(zmax)), int(np.size(fit.z)))
    why = (f"The Allan deviation at tau = {tau.min():.3g} .. {tau.max():.3g} s lies "
           f"below every sum of noise terms (|z| up to "
           f"{zmax:.1f}): the sensor's anti-aliasing or decimation filter averages the white "
           f"noise over a few samples. Until an output filter term (moving_average, "
           f"bartlett, lowpass) is in the model, these taus are left out of the parameter "
           f"estimates but still count in chi2/dof.")
    return Finding("sensor_filter", None, zmax, "max |z|", p, alpha, {},
                   {"tau_s": [float(tau.min()), float(tau.max())]}, why,
                   {"taus_set_aside": [float(t) for t in tau]})


_FILTER_Z = 3.0
"""A shortest tau this many standard scores below the model is an output filter's mark."""


def _filter_signature(fit: FitResult, finding: Finding | None) -> bool:
    """Whether the shortest taus lie below the model, as a sensor's output filter makes them
    (then the filter terms are candidates; otherwise their refits would be wasted)."""
    z = np.asarray(fit.z)
    return finding is not None or bool(z.size and z[0] < -_FILTER_Z)


def _in_band(fit: FitResult, line_finding: Finding, index: int) -> bool:
    """Whether the refitted line's frequency (term ``index``) lies in the band the line
    search covered."""
    f = fit.terms[index].params["f"]
    lo, hi = line_finding.details.get("f_searched_hz", (np.inf, -np.inf))
    return bool(lo <= f <= hi)


def _logp(p: float) -> float:
    return float(np.log(max(p, 1e-300)))


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


def _fold(spec: ModelSpec, fixed: dict | None) -> ModelSpec:
    """``spec`` with the parameters held by ``fixed`` (keyed by model index or term name, its
    first occurrence) written into its entries."""
    entries = list(spec.entries)
    for key, params in (fixed or {}).items():
        idx = key if isinstance(key, int) else spec.names.index(key) \
            if key in spec.names else None
        if idx is None or not 0 <= idx < len(entries):
            raise TermError(f"fixed parameters given for {key!r}, which is not in the model "
                            f"({', '.join(spec.names)})")
        e = entries[idx]
        entries[idx] = Entry(e.name, {**e.fixed, **{k: float(v) for k, v in params.items()}},
                             e.start)
    return parse_model(ModelSpec(tuple(entries)).text()) if entries else spec


@dataclass
class _Context:
    """What every candidate's refit shares."""

    x: np.ndarray
    fs_hz: float
    starts: np.ndarray
    temp_at: np.ndarray | None
    memo: dict
    base: FitResult
    spec: ModelSpec
    by_term: dict[str, Finding]
    n_candidates: int
    sensor_filter: tuple[str, dict[str, float]] | None = None
    time_origin_s: float = 0.0
    psd_est: Any = None
    nperseg: int = 256
    psd_before: dict[str, Any] | None = None
    job_map: JobMap = serial_map
    profile_added: bool = True
    """Whether a candidate's refit profiles the added term's weakly determined parameters
    (the white level's always are); the lookahead's round reports none of them."""


_Interval = tuple[float, float]


def _refit(ctx: _Context, term: str
           ) -> tuple[FitResult | None, ModelSpec, dict[str, float], dict[str, _Interval]]:
    """The model with ``term`` appended, fitted exactly as ``imunoise fit --model`` fits it
    (its ``apply.model``): ``(fit or None, model, parameters the evidence pinned, their
    intervals where the evidence gives them)``."""
    pinned: dict[str, float] = {}
    pinned_ci: dict[str, _Interval] = {}
    if ctx.sensor_filter is not None and term == ctx.sensor_filter[0]:
        # the device's configuration states the filter: it is not fitted
        pinned = dict(ctx.sensor_filter[1])
    f_ev = ctx.by_term.get(term)
    if get_term(term).role == "line" and f_ev is not None and f_ev.significant \
            and "f" in f_ev.params:
        # The PSD pins the frequency far better than the Allan curve can.
        pinned = {"f": float(f_ev.params["f"])}
        pinned_ci = {k: (float(lo), float(hi)) for k, (lo, hi)
                     in f_ev.details.get("ci95", {}).items() if k in pinned}
    after, spec = _fit_appended(ctx, term, pinned)
    imitates = term == "resonance" and _imitation(ctx, after) is not None
    if term == "resonance" and after is not None and (imitates or _psd_rises(ctx, after)):
        # The Allan refit put the resonance where the spectrum has no such peak (ADIS16405
        # run 3 gyro_z: 18.0 Hz with Q 1e4 beside a measured peak at 19.8 Hz, the PSD part
        # 2112 -> 3827), or let it take the white noise's place (run 5 gyro_z: chi2/dof
        # 1.77e4 -> 1.04e3 with the white level traded to zero): the spectrum's centre and
        # width are held instead, where that raises no PSD part (and, for the second, gives
        # the white noise back). Where the Allan refit is consistent with the spectrum it
        # stands: held at the peak, a resonance may follow the Allan curve worse (run 1
        # accel_x: 2029 against 1054 for a lowpass filter, a different first round)
        pin = _spectrum_pin(ctx, after, own_model=not imitates)
        if pin is not None:
            shape = pinned_of(pin.params)
            again, spec_again = _fit_appended(ctx, term, shape)
            if again is not None and not _psd_rises(ctx, again) \
                    and not (imitates and _imitation(ctx, again) is not None):
                after, spec, pinned, pinned_ci = again, spec_again, shape, dict(pin.ci95)
    elif term == "resonance" and after is not None:
        at_peaks = _held_at_peaks(ctx, spec, after, {len(ctx.spec)}, _fit_profiled(ctx, spec))
        if at_peaks is not None:
            after, spec, pins = at_peaks
            pin = pins[len(ctx.spec)]
            pinned, pinned_ci = pinned_of(pin.params), dict(pin.ci95)
    return after, spec, pinned, pinned_ci


def _fit_profiled(ctx: _Context, spec: ModelSpec) -> set[int]:
    """The terms whose intervals a candidate's refit reports (:func:`_fit_appended`)."""
    reported = {i for i, n in enumerate(spec.names) if n == "white"}
    if ctx.profile_added:
        reported.add(len(ctx.spec))
    return reported


def _held_at_peaks(ctx: _Context, spec: ModelSpec, fit: FitResult, which: set[int],
                   profile_terms: set[int]) -> tuple[FitResult, ModelSpec, dict[int, Any]] | None:
    """A refit with its free resonances among ``which`` (model indices) held at the
    spectrum's peaks (:mod:`imunoise.analysis.spectral_pins`), or None where it stands as
    fitted: ``(refit, its model, the pins by index)``.

    The Allan curve sees a resonance as a bump and leaves its f0 and Q to absorb misfit
    elsewhere: ADIS16405 run 1 accel_z with a Bartlett filter and its 0.57 Hz line puts a
    line at 10.5 Hz (Q 1644) where the spectrum shows a peak of Q 11.8 [10.2, 13.6] that the
    term follows exactly (deviance per dof 1.00). Held there, the PSD part falls from 6.5 to
    3.3 while the Allan chi2/dof moves from 5.33 to 5.25. A resonance is held at its peak
    where the refit put f0 or Q outside the peak's 95 % interval, the held refit lowers the
    PSD part by more than its standard deviation, and it raises the Allan part by less than
    one of its own (a resonance held at a peak that the Allan curve contradicts, such as a
    drifting one, stays as the Allan fit put it), or, where it raises the Allan part more,
    when it still lowers the given model's Allan part beyond its noise and lowers the two
    parts together further than the free refit does (:func:`_joint_change`): ADIS16405 run 3
    accel_z with a moving average and its 0.54 Hz line takes a hump at 13.9 Hz (Q 0.5) from
    the Allan curve, chi2/dof 15.3 -> 6.06 with the PSD part 4.50 -> 4.87, where the
    spectrum's peak at 9.87 Hz (Q 6.4) gives 9.18 and 3.08: both parts fall."""
    held = {(i, k) for i, e in enumerate(spec.entries) for k in e.fixed}
    try:
        pins = pin_resonances(ctx.x, ctx.fs_hz, fit.params, held, ctx.starts, ctx.memo)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None
    off = {p.index: p for p in pins if p.index in which and any(
        not p.ci95[k][0] <= fit.terms[p.index].params[k] <= p.ci95[k][1] for k in p.ci95)}
    if not off:
        return None
    entries = list(spec.entries)
    for i, p in off.items():
        e = entries[i]
        entries[i] = Entry(e.name, {**e.fixed, **pinned_of(p.params)}, e.start)
    spec_held = ModelSpec(tuple(entries))
    again = _fit_model(ctx, spec_held, profile_terms)
    if again is None:
        return None
    part_free, part_held = _psd_after(ctx, fit), _psd_after(ctx, again)
    if not _lowers(_deviance(part_free), _deviance(part_held),
                   (part_held or {}).get("bins", 0) / PSD_BIN_CORRELATION):
        return None
    if again.chi2_per_dof > fit.chi2_per_dof + _part_sd(fit.chi2_per_dof, again.misfit.dof) \
            and not (_lowers(ctx.base.chi2_per_dof, again.chi2_per_dof, again.misfit.dof)
                     and _joint_change(ctx, again, part_held) < _joint_change(ctx, fit, part_free)):
        return None
    return again, spec_held, off


def _joint_change(ctx: _Context, after: FitResult, psd_after: dict[str, Any] | None) -> float:
    """The change of the Allan and the PSD part from the given model's fit to ``after``, each
    in standard deviations of the given model's part (:func:`_part_sd`), summed: negative
    when the two fall together. A part not computed counts as unchanged."""
    change = (after.chi2_per_dof - ctx.base.chi2_per_dof) \
        / _part_sd(ctx.base.chi2_per_dof, after.misfit.dof)
    before_psd, after_psd = _deviance(ctx.psd_before), _deviance(psd_after)
    if before_psd is not None and after_psd is not None:
        dof = (psd_after or {}).get("bins", 0) / PSD_BIN_CORRELATION
        change += (after_psd - before_psd) / _part_sd(before_psd, dof)
    return float(change)


def _psd_rises(ctx: _Context, after: FitResult) -> bool:
    """Whether a refit raises the PSD part beyond its noise."""
    part = _psd_after(ctx, after)
    return _rises(_deviance(ctx.psd_before), _deviance(part),
                  (part or {}).get("bins", 0) / PSD_BIN_CORRELATION)


def _fit_model(ctx: _Context, spec: ModelSpec, profile_terms: set[int] | None = None,
               start: list[tuple[str, dict[str, float]]] | None = None) -> FitResult | None:
    """``spec`` fitted to the channel exactly as ``imunoise fit --model`` fits it (None where
    it cannot be fitted); ``profile_terms``: the terms whose intervals are profiled (None:
    every term's); ``start``: the one starting point, ``[(term, params)]`` in model order
    (None: the fit's own search)."""
    needs = any(get_term(n).needs_record == "temperature" for n in spec.names)
    try:
        return fit_series(ctx.x, ctx.fs_hz, spec, segment_starts=ctx.starts,
                          temperature=ctx.temp_at if needs else None, memo=ctx.memo,
                          intervals="jacobian", profile_terms=profile_terms, start=start)[0]
    except (ValueError, np.linalg.LinAlgError):
        return None


def _fit_appended(ctx: _Context, term: str, pinned: dict[str, float]
                  ) -> tuple[FitResult | None, ModelSpec]:
    spec = ModelSpec(ctx.spec.entries + (Entry(term, pinned),))
    # the suggestion reports the appended term's intervals; the white level's tells whether
    # the term took its place (_imitation)
    return _fit_model(ctx, spec, _fit_profiled(ctx, spec)), spec


def _spectrum_pin(ctx: _Context, after: FitResult, own_model: bool = True) -> Any:
    """The spectrum's f0 and Q of the resonance just appended to the model, or None where the
    spectrum does not resolve its peak (:mod:`imunoise.analysis.spectral_pins`); the model's
    other resonances stay as fitted. The other terms are the refit's, or with ``own_model``
    false the given model's fit (a refit that traded the white noise away leaves the peak
    no floor to stand on)."""
    new = len(ctx.spec)
    held = {(i, k) for i, t in enumerate(after.terms) if i != new for k in PINNED}
    model = after.params if own_model else list(ctx.base.params) + [after.params[new]]
    try:
        pins = pin_resonances(ctx.x, ctx.fs_hz, model, held, ctx.starts, ctx.memo)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError):
        return None
    return next((p for p in pins if p.index == new), None)


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


def _psd_after(ctx: _Context, after: FitResult | None) -> dict[str, Any] | None:
    """The PSD part of a refit, computed once per model (a resonance held at its peak is
    judged by it and then reported with it)."""
    if ctx.psd_est is None or after is None:
        return None
    key = ("psd part", tuple((n, tuple(sorted(p.items()))) for n, p in after.params))
    if key not in ctx.memo:
        ctx.memo[key] = psd_parts(after.params, ctx.psd_est, ctx.fs_hz, ctx.nperseg)[1]
    return dict(ctx.memo[key])


def _psd_logp(ctx: _Context, part: dict[str, Any] | None, k: int) -> float:
    """Log p-value of the fall of the PSD deviance with ``k`` added parameters (0 when it
    does not fall), the fall divided by the larger model's dispersion
    (:func:`_dispersion` of its deviance per bin, as :func:`_lr_logp` does the Allan
    chi2's)."""
    b, a = _deviance(ctx.psd_before), _deviance(part)
    if not _lowers(b, a, part["bins"] / PSD_BIN_CORRELATION if part else 1.0):
        return 0.0
    dof = part["bins"] / PSD_BIN_CORRELATION
    return _chi2_logsf((b - a) * dof / _dispersion(a, dof), k)


def _not_computed(what: str) -> dict[str, Any]:
    return {"reason": f"{what} is not computed for every suggestion"}


def _error_after(after: FitResult, psd: dict[str, Any] | None,
                 time_domain: dict[str, Any] | None = None) -> dict[str, Any]:
    """A suggestion's ``error_after``: the refit's Allan part, its PSD part as given, and the
    time-domain part where computed (a part left out says so; the hold-out part is filled in
    for the suggestions checked)."""
    return {"chi2_per_dof": after.chi2_per_dof, "max_abs_z": float(after.max_abs_z),
            "psd": psd, "holdout": _not_computed("the hold-out part"),
            "time_domain": time_domain if time_domain is not None
            else _not_computed("the time-domain part")}


def _parts_rise(ctx: _Context, after: FitResult, psd_after: dict[str, Any] | None) -> bool:
    """Whether a refit raises the Allan or the PSD part beyond its noise."""
    return _rises(ctx.base.chi2_per_dof, after.chi2_per_dof, after.misfit.dof) \
        or _rises(_deviance(ctx.psd_before), _deviance(psd_after),
                  (psd_after or {}).get("bins", 0) / PSD_BIN_CORRELATION)


def _imitation(ctx: _Context, after: FitResult | None, index: int | None = None
               ) -> str | None:
    """Why the refit's solution is not identifiable in the sampled band (one term doing
    another's part), or None: a resonance whose peak does not lie below the Nyquist
    frequency (its centre plus half its bandwidth at or above it) is a rising spectrum, not
    a resonance; a refit that leaves the white level unresolved where the given model
    resolved it has traded the white noise to zero for the new term (at ``index``: by
    default the term appended). A Markov term at its shortest time is judged with the
    other candidates (:func:`_markov_beside_a_filter`)."""
    if after is None:
        return None
    added = after.terms[len(ctx.spec) if index is None else index]
    nyquist = 0.5 * ctx.fs_hz
    if added.term == "resonance":
        f0, q = float(added.params["f0"]), float(added.params["Q"])
        if f0 * (1.0 + 0.5 / q) >= nyquist:
            return (f"its peak ({f0:.4g} Hz, half-bandwidth {0.5 * f0 / q:.3g} Hz) does not lie "
                    f"below the Nyquist frequency {nyquist:g} Hz")
    white = get_term("white")
    for tb, ta in zip(ctx.base.terms, after.terms, strict=False):
        if tb.term == "white" and white.resolved("N", tb.ci95.get("N")) \
                and not white.resolved("N", ta.ci95.get("N")):
            return "the refit trades the white-noise level to zero for it"
    return None


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
    if falls and not regressor:
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
        if imitation is None:
            held_reason = "it does not lower the Allan chi2/dof."
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
    (index, name))``), or a hold-out half of the given model
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
    return _suggest(ctx, what, alpha)


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
    # no longer find a transient, and the Allan part must not rise beyond its noise.
    td_after: dict[str, Any] | None = None
    clears = False
    if after is not None:
        td_after = time_domain_part(series.values, ctx.fs_hz, after.params,
                                    series.segment_starts, units)
        p_after = td_after.get("p")
        clears = bool(p_after is not None and p_after >= alpha
                      and not _rises(before, chi_after, after.misfit.dof))
        if clears and not falls:
            why += (f" The cut record shows no transient (time-domain p {p_after:.2g}) and "
                    f"the Allan part stays within its noise.")
    names = ("t_s", "size") if step else ("tau_s", "amplitude")
    ci = {k: (float(finding.details[f"{k}_ci95"][0]), float(finding.details[f"{k}_ci95"][1]))
          for k in names if np.all(np.isfinite(finding.details.get(f"{k}_ci95", [np.nan])))}
    return Suggestion(
        term=finding.kind, params=dict(finding.params), ci95=ci,
        chi2_per_dof_before=before, chi2_per_dof_after=chi_after,
        p_value=float(np.exp(logp)), log_p=logp,
        significant=bool(logp < np.log(alpha) and (falls or clears)), why=why,
        evidence=[finding.kind] if finding.significant else [], fit=after,
        apply={"model": ctx.spec.text(), "args": args}, action="cut",
        error_after={} if after is None
        else _error_after(after, _not_computed("the PSD part"), td_after))


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
           findings: Sequence[Finding] = ()) -> list[tuple[int, str]]:
    """``(index, other term)`` for each term that may replace one of the given model's: each
    other kind of output filter, when the model fails (a filter the user held or the
    device's configuration states stays), and a wandering resonance for each resonance whose
    peak the evidence finds moving (a significant ``resonance_drift`` finding)."""
    out: list[tuple[int, str]] = []
    if base.failures and sensor_filter is None:
        filters = [n for n, t in TERMS.items() if t.kind == "filter"]
        out += [(i, other) for i, entry in enumerate(spec.entries)
                if get_term(entry.name).kind == "filter" and not entry.fixed
                for other in filters if other != entry.name]
    refinements = {t.replaces: n for n, t in TERMS.items() if t.replaces is not None}
    for f in findings:
        i = f.details.get("term_index")
        if f.kind == "resonance_drift" and f.significant and isinstance(i, int) \
                and i < len(spec.entries) and spec.entries[i].name in refinements:
            out.append((i, refinements[spec.entries[i].name]))
    return out


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
    wandering resonance for a resonance whose peak moves) comes with the shape the spectrum
    gives it (:mod:`imunoise.analysis.spectral_pins`: centre, width and wander held, the
    power left to the Allan refit), as a suggested resonance is held at its peak; the Allan
    curve alone barely tells a moving peak from a fixed one. It has one parameter more, and
    its chi2 drop is judged as that of one parameter."""
    old = ctx.spec.labels[index]
    before = ctx.base.chi2_per_dof
    label = f"{old} by {new}"
    refines = get_term(new).replaces is not None
    shape: dict[str, float] = {}
    shape_ci: dict[str, _Interval] = {}
    if refines:
        pin = _refinement_pin(ctx, index, new)
        if pin is None:
            spec = _replaced(ctx.spec, index, Entry(new, {}))
            return _swap_not_offered(new, before, label, spec,
                                     f"The spectrum does not resolve a wander of {old}'s peak.")
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
        why = (f"The peak of {old} moves through the record; a {new} averages it over the "
               f"centre frequencies it visits (spread {shape['spread']:.2g} Hz from the "
               f"spectrum).")
    else:
        why = f"The shortest taus may follow a {new} filter better than the model's {old}."
    if after is None:
        return _swap_not_offered(new, before, label, spec,
                                 why + " The model with it could not be fitted.")
    drop = float(ctx.base.misfit.chi2 - after.misfit.chi2)
    falls = bool(np.isfinite(after.chi2_per_dof) and after.chi2_per_dof < before)
    sources = [_chi2_logsf(drop / _dispersion(after.chi2_per_dof, after.misfit.dof), 1)] \
        if falls and drop > 0 else []
    psd_after = _psd_after(ctx, after)
    psd_logp = _psd_logp(ctx, psd_after, 1)
    if psd_logp < 0.0:
        sources.append(psd_logp)
    logp = _combined_logp(ctx, sources)
    tf = after.terms[index]
    # a filter's reason is the sentence itself; a refinement's what the evidence showed
    why = (why + " " if refines else "") + (
        f"Replacing {old} by a {new}{'' if refines else ' filter'} brings chi2/dof from "
        f"{before:.3g} to {after.chi2_per_dof:.3g}")
    psd_b, psd_a = _deviance(ctx.psd_before), _deviance(psd_after)
    if psd_b is not None and psd_a is not None:
        why += f" and the PSD part from {psd_b:.3g} to {psd_a:.3g}"
    why += " with one parameter more." if refines else " with as many parameters."
    imitation = _imitation(ctx, after, index)
    rises = _parts_rise(ctx, after, psd_after)
    allan_up = not rises and not falls and bool(np.isfinite(after.chi2_per_dof))
    held_by, held_reason = _held_back(imitation, rises or allan_up)
    if allan_up and imitation is None:
        held_reason = "it does not lower the Allan chi2/dof."
    if held_reason:
        why += " " + held_reason[0].upper() + held_reason[1:]
    return Suggestion(
        # a held shape's interval is the spectrum's, as a pinned suggestion's is
        term=new, params=dict(tf.params), ci95={**tf.ci95, **shape_ci},
        chi2_per_dof_before=before,
        chi2_per_dof_after=after.chi2_per_dof, p_value=float(np.exp(logp)), log_p=logp,
        significant=bool(logp < np.log(alpha) and (falls or psd_logp < 0.0)
                         and not rises and not allan_up and imitation is None),
        why=why, fit=after, apply={"model": spec.text(), "args": []}, action="replace",
        label=label, held_by=held_by, held_reason=held_reason,
        error_after=_error_after(after, psd_after))


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
    kinds = [n for n, t in TERMS.items() if t.kind == "filter"]
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
    suggestion is another filter with as many parameters that explains the curve no better.

    A moving average of 1.2 taps, a Bartlett window of 1.1 and a single pole near a quarter of
    the rate bend the shortest taus alike; which one a record's last bits favour changed from
    run to run of one ADIS16405 accelerometer, so that six nights of one part gave three term
    sets for one filter. Where the data do not tell them apart (the top filter's chi2 lies
    less than the test's drop below the other's, scaled and judged with one degree of freedom
    as in :func:`_simplest_first`), the same one is named on every record.
    """
    terms = _significant_additions(suggestions)
    first = next((s for s in suggestions if s.significant), None)
    if not terms or first is not terms[0] or get_term(first.term).kind != "filter":
        return suggestions
    order = list(TERMS)
    k_top = len(get_term(first.term).params)
    ties = [s for s in terms[1:] if get_term(s.term).kind == "filter"
            and len(get_term(s.term).params) == k_top
            and order.index(s.term) < order.index(first.term)]
    for other in sorted(ties, key=lambda s: order.index(s.term)):
        drop, p = _further_drop(first, other, 1)
        if p < alpha:
            continue
        other.why += (f" It comes before {first.term}, an output filter that explains the "
                      f"curve no better (its further chi2 drop {max(drop, 0.0):.3g}, "
                      f"p = {p:.2g}).")
        return [other] + [s for s in suggestions if s is not other]
    return suggestions


def _evidence(x: np.ndarray, fs_hz: float, starts: np.ndarray, segments: list[np.ndarray],
              t_rate: np.ndarray, base: FitResult, names: list[str],
              temperature: tuple[np.ndarray, np.ndarray] | None, alpha: float, units: str,
              time_origin_s: float = 0.0
              ) -> tuple[list[Finding], dict[str, Finding], Finding | None]:
    """What the record shows beside the Allan curve: ``(findings, the findings that support
    a term keyed by it, the sensor-filter finding or None)``. Each test runs at the family
    level; the per-candidate Bonferroni comes in :func:`_suggest`. ``time_origin_s``: the
    first sample's time on the scale of ``--split`` (see :func:`diagnose`)."""
    findings: list[Finding] = []
    findings.append(evidence.outliers(segments, fs_hz, alpha=alpha, units=units))
    findings.append(evidence.gaps(starts, x.size, fs_hz))
    findings.append(evidence.noise_level_windows(
        segments, fs_hz, alpha=alpha, exclude=evidence.outlier_indices(segments, alpha),
        units=units))
    findings.extend(_resonance_drifts(segments, fs_hz, base, alpha, time_origin_s))
    filt = _sensor_filter(base, alpha)
    if filt is not None:
        findings.append(filt)
    by_term: dict[str, Finding] = {}
    held_lines = [float(p["f"]) for n, p in base.params
                  if get_term(n).role == "line" and "f" in p]
    try:
        # the fitted model's own shape (a filter's notches) is no line, nor is a line it
        # already holds: a further sinusoid needs a further line
        by_term["sinusoid"] = evidence.spectral_lines(
            segments, fs_hz, alpha=alpha, units=units,
            model_psd=lambda f: model_psd(base.params, f, fs_hz, continuous_only=True),
            exclude_hz=held_lines)
    except ValueError:
        pass
    if "rate_ramp" not in names:
        by_term["rate_ramp"] = evidence.drift(t_rate, x, alpha=alpha, units=units)
    if temperature is not None and "temperature" not in names:
        by_term["temperature"] = evidence.temperature_correlation(
            t_rate, x, temperature[0], temperature[1], alpha=alpha, units=units)
    findings.extend(by_term.values())
    return findings, by_term, filt


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


def _resonance_drifts(segments: list[np.ndarray], fs_hz: float, base: FitResult, alpha: float,
                      time_origin_s: float) -> list[Finding]:
    """Whether each resonance of the fitted model keeps its frequency through the record
    (:func:`imunoise.analysis.evidence.resonance_drift`), the p-values Bonferroni-corrected
    over the model's resonances. A resonance without a peak (Q below
    :data:`~imunoise.analysis.evidence.resonance_drift.MIN_Q`, a hump) is not tested."""
    model = base.params
    at = [i for i, (n, p) in enumerate(model) if n == "resonance" and 0 < p["f0"] < fs_hz / 2
          and p["Q"] >= DRIFT_MIN_Q]
    out = []
    for i in at:
        rest_psd = functools.partial(model_psd, [t for k, t in enumerate(model) if k != i],
                                     fs_hz=fs_hz, continuous_only=True)
        found = evidence.resonance_drift(segments, fs_hz, model[i][1]["f0"], model[i][1]["Q"],
                                         alpha=alpha, rest_psd=rest_psd, tests=len(at),
                                         t0_s=time_origin_s)
        found.details["term_index"] = i
        out.append(found)
    return out


def _candidates(names: list[str], base: FitResult, filt: Finding | None, has_temperature: bool,
                sensor_filter: tuple[str, dict[str, float]] | None) -> list[str]:
    """The terms to try: every additive term not in the model (a repeatable one, such as a
    second Markov time constant or a second resonance, even if it is; a term that refines
    another only in its place, :func:`_swaps`), and the output
    filters when the shortest taus show one (only the device's own when its configuration
    states it)."""
    candidates = [n for n, t in TERMS.items() if (n not in names or t.repeatable)
                  and t.kind == "additive" and t.replaces is None
                  and (t.needs_record != "temperature" or has_temperature)]
    if not any(get_term(n).kind == "filter" for n in names):
        if sensor_filter is not None:
            candidates.append(get_term(sensor_filter[0]).name)
        elif _filter_signature(base, filt):
            candidates += [n for n, t in TERMS.items() if t.kind == "filter"]
    return candidates


def _psd_baseline(x: np.ndarray, fs_hz: float, starts: np.ndarray, base: FitResult,
                  names: list[str]) -> tuple[Any, int, dict[str, Any] | None, dict[str, Any]]:
    """``(measured PSD or None, its segment length, the psd block, error.psd)`` of the given
    model, against which each candidate's PSD part is judged."""
    none = {"deviance_per_bin": None, "bins": 0, "outside_95": None}
    if "temperature" in names:
        return None, 256, None, {**none, "reason": "not computed under a temperature regression"}
    try:
        psd_est, nperseg = measured_psd(x, fs_hz, starts)
    except ValueError as exc:
        return None, 256, None, {**none, "reason": f"no PSD: {exc}"}
    psd_block, psd_before = psd_parts(base.params, psd_est, fs_hz, nperseg)
    return psd_est, nperseg, psd_block, psd_before


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


def diagnose(values: np.ndarray, fs_hz: float, model: str | list[str], *,
             segment_starts: np.ndarray | None = None, t0_s: float = 0.0,
             temperature: tuple[np.ndarray, np.ndarray] | None = None,
             units: str = "rad/s", alpha: float = DEFAULT_ALPHA,
             fixed: dict | None = None,
             sensor_filter: tuple[str, dict[str, float]] | None = None,
             transients: bool = True, time_origin_s: float = 0.0,
             holdout: bool = True, lookahead: bool = True,
             job_map: JobMap = serial_map) -> Diagnosis:
    """Fit ``model`` to a rate series and rank the terms it is missing.

    Args:
        values: rate samples (SI units), all gap-free segments concatenated.
        fs_hz: sampling rate in Hz.
        model: the model (a specification string such as ``"white,gauss_markov:T=100"`` or
            a list of names; see :func:`imunoise.analysis.terms.parse_model`).
        segment_starts: gap-free segment starts (``ChannelSeries.segment_starts``).
        t0_s: time of the first sample, seconds (same base as the temperature times).
        temperature: ``(times_s, degC)`` of the temperature record, any rate.
        units: units of ``values`` (for explanations).
        alpha: family-wise significance level over all candidates.
        fixed: parameters held fixed in the given model (see
        :func:`imunoise.analysis.fit.fit_allan`).
        sensor_filter: the output filter the device's configuration states, ``(term,
            params)`` (e.g. ``("bartlett", {"taps": 4})``); it is then the one filter
            offered, with those parameters held. Without it the filter terms are offered,
            fitted, when the shortest taus lie below the model.
        transients: test for a bias step and a warm-up against the fitted model
            (:func:`imunoise.analysis.evidence.transients`); their remedies are cuts of the record
            (``apply.args``: ``--split T``, ``--skip S``), so a caller that cannot cut (the
            live service) leaves them out.
        time_origin_s: the time of the first sample analysed on the scale step times are
            reported on, seconds (the command line passes its ``--skip``, so that a step's
            ``t_s`` counts from the start of the file, as ``--split`` does).
        holdout: compute the hold-out part (the model fitted on each half predicting the
            other) and require a significant term to lower it; it costs two fits per check.
        lookahead: where the model fails and the hold-out part holds back every term with
            strong evidence, try the strongest of them with the next round's term
            (:func:`_pair`); it costs a few more refits, in that situation only.
        job_map: how the independent jobs run (the candidates' refits, the hold-out halves,
            the profile intervals; see :mod:`imunoise.analysis.jobs`): one after the other
            by default; the command line forks workers. The result is the same.

    Returns:
        A :class:`Diagnosis` with suggestions best first.
    """
    return _diagnose(values, fs_hz, model, segment_starts=segment_starts, t0_s=t0_s,
                     temperature=temperature, units=units, alpha=alpha, fixed=fixed,
                     sensor_filter=sensor_filter, transients=transients,
                     time_origin_s=time_origin_s, holdout=holdout,
                     lookahead=lookahead, job_map=job_map)


def _diagnose(values: np.ndarray, fs_hz: float, model: str | list[str], *,
              segment_starts: np.ndarray | None, t0_s: float,
              temperature: tuple[np.ndarray, np.ndarray] | None, units: str, alpha: float,
              fixed: dict | None, sensor_filter: tuple[str, dict[str, float]] | None,
              transients: bool, time_origin_s: float, holdout: bool, lookahead: bool,
              job_map: JobMap, only: frozenset[str] | None = None,
              memo: dict | None = None) -> Diagnosis:
    """:func:`diagnose`, trying only the candidates named in ``only`` when it is given (the
    lookahead's next round: the terms the first round found strong evidence for); that round
    takes the given model's intervals linearised (its own are not reported) and shares the
    first round's ``memo`` of the series (its Allan curve and solutions)."""
    x = np.asarray(values, dtype=np.float64)
    starts = (np.asarray(segment_starts, dtype=np.int64) if segment_starts is not None
              else np.zeros(1, dtype=np.int64))
    base_spec = _fold(parse_model(model), fixed)
    names = base_spec.names
    t_rate = _times(x.size, fs_hz, t0_s)
    temp_at = None
    if temperature is not None:
        temp_at = np.interp(t_rate, np.asarray(temperature[0], float),
                            np.asarray(temperature[1], float))
    memo = {} if memo is None else memo
    base, curve = fit_series(x, fs_hz, base_spec, segment_starts=starts,
                             temperature=temp_at if "temperature" in names else None,
                             memo=memo, job_map=job_map,
                             intervals="profile" if only is None else "jacobian")
    base = base.in_canonical_order()  # labels of repeated terms as every fit gives them
    segments = [s for s in (x[a:b] for a, b in zip(starts, np.append(starts[1:], x.size),
                                                   strict=True)) if s.size]

    # the evidence and the transient and PSD tests read the base fit, not each other
    tests = _BaseTests(x, fs_hz, starts, segments, t_rate, base, names, temperature, alpha,
                       units, transients, time_origin_s)
    (findings, by_term, filt), (cuts, psd_baseline, time_domain) = job_map(
        _base_test, tests, ["evidence", "spectrum"])
    findings.extend(cuts)
    psd_est, nperseg, psd_block, psd_before = psd_baseline
    candidates = _candidates(names, base, filt, temperature is not None, sensor_filter)
    swaps = _swaps(base_spec, base, sensor_filter, findings) if only is None else []
    if only is not None:
        candidates = [c for c in candidates if c in only]
    parts: dict[str, Any] = {"psd": psd_before, "time_domain": time_domain}
    ctx = _Context(x, fs_hz, starts, temp_at, memo, base, base_spec, by_term,
                   len(candidates) + len(swaps) + len(cuts), sensor_filter, time_origin_s,
                   psd_est, nperseg, psd_before, job_map, profile_added=only is None)
    # the given model's hold-out halves are fitted beside the candidates' refits
    halves = holdout_halves(x, fs_hz, base_spec, base, starts) if holdout else None
    jobs: list[tuple[str, Any]] = [("term", c) for c in candidates]
    jobs += [("swap", w) for w in swaps]
    n_tried = len(jobs)
    if isinstance(halves, HoldoutHalves):
        jobs += [("half", 0), ("half", 1)]
    done = job_map(_first_job, (ctx, alpha, halves if isinstance(halves, HoldoutHalves)
                                else None), jobs)
    suggestions = _ranked(ctx, done[:n_tried], cuts, units, alpha)
    if only is None:
        suggestions = _filter_rechosen(ctx, suggestions, alpha)
    # the next line's refit and the given model's hold-out part need nothing of each other
    steps = (["line"] if only is None else []) + \
        (["holdout"] if isinstance(halves, HoldoutHalves) else [])
    second = dict(zip(steps, job_map(
        _second_job, (ctx, suggestions, alpha, units, halves, done[n_tried:]), steps),
        strict=True))
    suggestions = second.get("line", suggestions)
    if halves is None:
        parts["holdout"] = {"chi2_per_dof": None, "parts": 2, "reason": "not requested"}
    else:
        before = second.get("holdout", halves)
        assert isinstance(before, dict)
        parts["holdout"] = _check_holdout(ctx, suggestions, before)
        if lookahead:
            def next_round(spec_text: str, names: frozenset[str]) -> Diagnosis:
                return _diagnose(x, fs_hz, spec_text, segment_starts=starts, t0_s=t0_s,
                                 temperature=temperature, units=units, alpha=alpha,
                                 fixed=None, sensor_filter=sensor_filter, transients=False,
                                 time_origin_s=time_origin_s, holdout=False,
                                 lookahead=False, job_map=job_map, only=names,
                                 memo=memo)

            pair = _pair(ctx, suggestions, parts["holdout"], alpha, next_round)
            if pair is not None:
                suggestions.insert(0, pair)
    return Diagnosis(fit=base, curve=curve, suggestions=suggestions, findings=findings,
                     alpha=alpha, psd=psd_block, error_parts=parts)


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


@dataclass
class _BaseTests:
    """What the tests that follow the base fit read (:func:`_base_test`)."""

    x: np.ndarray
    fs_hz: float
    starts: np.ndarray
    segments: list[np.ndarray]
    t_rate: np.ndarray
    base: FitResult
    names: list[str]
    temperature: tuple[np.ndarray, np.ndarray] | None
    alpha: float
    units: str
    transients: bool  # the step and warm-up tests and the time-domain part asked for
    time_origin_s: float


def _base_test(t: _BaseTests, which: str) -> Any:
    """One of the two independent groups of tests on the base fit, as a job map calls it:
    ``"evidence"`` (:func:`_evidence`), or ``"spectrum"``: ``(the step and warm-up
    findings, :func:`_psd_baseline`, the time-domain part)``."""
    if which == "evidence":
        return _evidence(t.x, t.fs_hz, t.starts, t.segments, t.t_rate, t.base, t.names,
                         t.temperature, t.alpha, t.units, t.time_origin_s)
    cuts: list[Finding] = []
    if t.transients and "temperature" not in t.names:
        bounds = np.append(t.starts, t.x.size)
        longest = int(np.argmax(np.diff(bounds)))
        cuts = list(evidence.transients(t.segments, t.fs_hz, t.base.params, alpha=t.alpha,
                                        units=t.units,
                                        t0_s=t.time_origin_s + float(bounds[longest]) / t.fs_hz))
    baseline = _psd_baseline(t.x, t.fs_hz, t.starts, t.base, t.names)
    time_domain = time_domain_part(t.x, t.fs_hz, t.base.params, t.starts, t.units,
                                   cuts or None) if t.transients \
        else {"statistic": None, "p": None, "reason": "not requested"}
    return cuts, baseline, time_domain


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
    apply."""
    dof = float(ctx.base.misfit.dof)
    checked = 0
    for s in suggestions:
        if not s.significant or s.fit is None or s.apply.get("args"):
            if s.significant:
                break  # a cut comes first: it is judged by the time-domain part
            continue
        if checked >= HOLDOUT_CHECKS or before.get("chi2_per_dof") is None:
            break
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
