"""Evidence gathered on the given model before any term is tried: the sensor filter, spectral
lines, resonance drift, transients and the PSD baseline."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from imunoise.analysis import distributions as dist
from imunoise.analysis import evidence
from imunoise.analysis.evidence.finding import Finding, family_p
from imunoise.analysis.evidence.resonance_drift import MIN_Q as DRIFT_MIN_Q
from imunoise.analysis.fit import FitResult
from imunoise.analysis.model_error import measured_psd, psd_parts, time_domain_part
from imunoise.analysis.psd_model import grid_gains
from imunoise.analysis.terms import TERMS, get_term, model_psd


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
    findings.append(evidence.held_samples(segments, fs_hz, alpha=alpha, units=units))
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
        spectrum = evidence.line_spectrum(segments, fs_hz)
    except ValueError:
        spectrum = None  # too short for a spectrum: no line to search or compare
    if spectrum is not None:
        try:
            # the fitted model's own shape (a filter's notches) is no line, nor is a line it
            # already holds: a further sinusoid needs a further line
            by_term["sinusoid"] = evidence.spectral_lines(
                segments, fs_hz, alpha=alpha, units=units,
                model_psd=lambda f: model_psd(base.params, f, fs_hz, continuous_only=True),
                exclude_hz=held_lines, spectrum=spectrum)
        except ValueError:
            pass
    held = [(tf.term, float(tf.params["f"]), float(tf.params["A"]), tf.ci95.get("A"))
            for tf in base.terms if tf.term.split("#")[0] in TERMS
            and get_term(tf.term.split("#")[0]).role == "line"
            and "f" in tf.params and "A" in tf.params]
    if held and spectrum is not None:
        # the Allan curve lumps lines a few tens of per cent apart: the spectrum parts them
        lines_found = by_term["sinusoid"].details.get("lines", []) if "sinusoid" in by_term \
            else []
        findings.append(evidence.line_powers(segments, fs_hz, held, alpha=alpha, units=units,
                                             found=lines_found, spectrum=spectrum))
    if "rate_ramp" not in names:
        by_term["rate_ramp"] = evidence.drift(t_rate, x, alpha=alpha, units=units)
    if temperature is not None and "temperature" not in names:
        by_term["temperature"] = evidence.temperature_correlation(
            t_rate, x, temperature[0], temperature[1], alpha=alpha, units=units)
    findings.extend(by_term.values())
    return findings, by_term, filt


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
    findings, :func:`_psd_baseline`, the time-domain part, the cascade gains its PSD part
    computed)``, the gains for :func:`imunoise.analysis.psd_model.adopt_grid_gains` in the
    process that forks the next workers."""
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
    return cuts, baseline, time_domain, grid_gains()
