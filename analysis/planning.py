"""How long to record: the record length at which a parameter's 95 % interval reaches a target.

Two predictions, each with its assumption stated:

* ``"allan"`` (every term): the interval ``imunoise fit`` reports. The expected overlapping Allan
  curve of the model for a gap-free record of n samples (the model's exact Allan variance at
  the octave taus, with the number of terms such a record has) is fitted exactly as a measured
  one is; the estimates' covariance there is the model's (:func:`imunoise.analysis.misfit.
  avar_covariance`), so the interval of that fit is the interval a typical record of that
  length gives (to first order: the linearised interval, or the profile one where the
  parameter is weakly determined).
* ``"likelihood"`` (white noise, first-order Markov and rate random walk only): the Cramer-Rao
  bound of the exact Gaussian likelihood of the record (:func:`imunoise.analysis.likelihood.
  fisher_information`): the narrowest interval any unbiased estimator can give, reached by the
  block-likelihood fit.

The relative half-width of an interval ``[lo, hi]`` around a value ``v`` is
``(hi - lo) / (2 v)``; for a log-normal estimate with standard error s of ``ln v`` it is
``sinh(1.96 s)``. The record length is searched by bisection on a log scale (the width falls
roughly as ``n^-1/2`` for white noise, faster for slow terms, but not exactly so).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from imunoise.analysis.allan import tau_grid
from imunoise.analysis.terms import get_term, labels, model_avar, parse_model

Z95 = 1.959963984540054
MIN_SAMPLES = 1 << 8
MAX_SAMPLES = 1 << 34  # ~ 5.4 years at 100 Hz: beyond that a target is called unreachable
_BISECTIONS = 24  # on log2(n): 2^(34 - 8) / 2^24 leaves a factor of 1.00x


@dataclass(frozen=True)
class Target:
    """A wanted 95 % interval: parameter ``param`` of the model entry ``label`` within
    ``relative`` (e.g. 0.2 for +-20 %) of its value."""

    label: str
    param: str
    relative: float


@dataclass(frozen=True)
class Plan:
    """The record length (s) that reaches a target, or None when it cannot be reached."""

    target: Target
    value: float
    record_s: float | None
    method: str
    assumption: str

    def to_dict(self) -> dict:
        return {"term": self.target.label, "param": self.target.param,
                "target_relative_halfwidth": self.target.relative, "value": self.value,
                "record_s": self.record_s, "reachable": self.record_s is not None,
                "method": self.method, "assumption": self.assumption}


class _ExpectedCurve:
    """The expected overlapping Allan curve of a model: what ``fit_allan`` takes."""

    def __init__(self, model, fs_hz: float, n_samples: int) -> None:
        self.fs_hz = float(fs_hz)
        self.m = tau_grid(n_samples, "octave")
        self.tau_s = self.m / self.fs_hz
        self.n_terms = np.maximum(n_samples + 1 - 2 * self.m, 0)
        self.dev = np.sqrt(model_avar(model, self.tau_s, self.fs_hz))


def parse_targets(text: str, model) -> list[Target]:
    """``K=20%,B=10%`` (or ``random_walk.K=0.2``, ``gauss_markov#2.T=25%``) for ``model``.

    Raises ValueError naming the problem (an unknown or ambiguous parameter, a bad number).
    """
    spec = parse_model(model)
    names, labs = spec.names, spec.labels
    out = []
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        key, sep, value = item.partition("=")
        if not sep:
            raise ValueError(f"target {item!r}: write PARAM=X% (e.g. K=20%)")
        rel = _relative(value.strip(), item)
        label, dot, param = key.strip().rpartition(".")
        owners = [(lab, n) for lab, n in zip(labs, names, strict=True)
                  if (not dot or lab == label) and param in get_term(n).param_names]
        if not owners:
            raise ValueError(f"target {item!r}: no parameter {key.strip()!r} in the model "
                             f"({', '.join(labs)})")
        if len(owners) > 1:
            raise ValueError(f"target {item!r}: {param} is in {', '.join(o for o, _ in owners)};"
                             f" write TERM.{param}")
        out.append(Target(owners[0][0], param, rel))
    if not out:
        raise ValueError("no target given: e.g. --target K=20%")
    return out


def _relative(text: str, item: str) -> float:
    try:
        rel = float(text[:-1]) / 100.0 if text.endswith("%") else float(text)
    except ValueError:
        raise ValueError(f"target {item!r}: {text!r} is not a number or percentage") from None
    if not 0.0 < rel < 10.0 or not math.isfinite(rel):
        raise ValueError(f"target {item!r}: the relative half-width must be above 0 "
                         "(e.g. 20% or 0.2)")
    return rel


def _model_pairs(model) -> list[tuple[str, dict[str, float]]]:
    """``[(name, params)]`` with every parameter given (the fixed values of a spec)."""
    spec = parse_model(model)
    pairs = []
    for e in spec.entries:
        params = {**(e.start or {}), **e.fixed}
        missing = [p for p in get_term(e.name).param_names if p not in params]
        if missing:
            raise ValueError(f"{e.name}: give {', '.join(missing)} (e.g. {e.name}:"
                             f"{missing[0]}=...) to plan with this model")
        pairs.append((e.name, params))
    return pairs


def allan_halfwidths(model, fs_hz: float, n_samples: int) -> dict[tuple[str, str], float]:
    """Relative 95 % half-widths ``(hi - lo)/(2 v)`` of every parameter that ``imunoise fit``
    would report for a typical gap-free record of ``n_samples`` samples of ``model``."""
    from imunoise.analysis.fit import fit_allan

    pairs = _model_pairs(model)
    curve = _ExpectedCurve(pairs, fs_hz, n_samples)
    result = fit_allan(curve, [name for name, _ in pairs], start=pairs, intervals="jacobian")
    out = {}
    for lab, t in zip(labels([n for n, _ in pairs]), result.terms, strict=True):
        for p, (lo, hi) in t.ci95.items():
            v = t.params[p]
            out[(lab, p)] = (hi - lo) / (2.0 * v) if v > 0 else math.inf
    return out


def likelihood_halfwidths(model, fs_hz: float, n_samples: int) -> dict[tuple[str, str], float]:
    """Relative 95 % half-widths at the Cramer-Rao bound of the exact Gaussian likelihood
    (``sinh(1.96 sd(ln v))``); the model must be one the likelihood supports."""
    from imunoise.analysis.likelihood import fisher_information, supports

    pairs = _model_pairs(model)
    names = [n for n, _ in pairs]
    if not supports(names):
        raise ValueError("the exact likelihood covers white, gauss_markov and random_walk "
                         "only; use the Allan method")
    keys = [(i, p) for i, (n, params) in enumerate(pairs) for p in params]
    info = fisher_information(pairs, fs_hz, n_samples, keys)
    cov = np.linalg.pinv(info)
    labs = labels(names)
    return {(labs[i], p): math.sinh(Z95 * math.sqrt(max(float(cov[j, j]), 0.0)))
            for j, (i, p) in enumerate(keys)}


def plan(model, fs_hz: float, targets: Sequence[Target], method: str = "allan"
         ) -> list[Plan]:
    """Record length (s) at which each target's 95 % interval reaches its relative half-width.

    Args:
        model: terms with every parameter given, e.g. ``"white:N=3e-4,random_walk:K=2e-5"``
            (SI units of the channel).
        fs_hz: sampling rate of the planned record (Hz).
        targets: from :func:`parse_targets`.
        method: ``"allan"`` (the interval of ``imunoise fit``) or ``"likelihood"`` (the
            Cramer-Rao bound of the exact likelihood).
    """
    widths = {"allan": allan_halfwidths, "likelihood": likelihood_halfwidths}[method]
    pairs = _model_pairs(model)
    values = {(lab, p): v for lab, (_, params) in zip(labels([n for n, _ in pairs]), pairs,
                                                       strict=True) for p, v in params.items()}
    cache: dict[int, dict[tuple[str, str], float]] = {}

    def width(n: int, key: tuple[str, str]) -> float:
        if n not in cache:
            try:
                cache[n] = widths(pairs, fs_hz, n)
            except ValueError:  # too short for the model's free parameters
                cache[n] = {}
        return cache[n].get(key, math.inf)

    assumption = _assumption(pairs, fs_hz, method)
    out = []
    for tg in targets:
        key = (tg.label, tg.param)
        lo, hi = math.log2(MIN_SAMPLES), math.log2(MAX_SAMPLES)
        steps = _BISECTIONS
        if method == "likelihood":
            # each evaluation factorises a dense covariance: start from the Allan fit's answer
            # (the bound is never far from it) and bisect within a factor of 16 either way
            (guide,) = plan(pairs, fs_hz, [tg], "allan")
            if guide.record_s is not None:
                centre = math.log2(guide.record_s * fs_hz)
                lo, hi = max(lo, centre - 4.0), min(hi, centre + 4.0)
                steps = 10
        if width(int(2.0**hi), key) > tg.relative:
            if hi < math.log2(MAX_SAMPLES):
                hi = math.log2(MAX_SAMPLES)
            if width(int(2.0**hi), key) > tg.relative:
                out.append(Plan(tg, values[key], None, method, assumption))
                continue
        for _ in range(steps):
            mid = 0.5 * (lo + hi)
            if width(int(2.0**mid), key) > tg.relative:
                lo = mid
            else:
                hi = mid
        out.append(Plan(tg, values[key], 2.0**hi / fs_hz, method, assumption))
    return out


def _assumption(pairs, fs_hz: float, method: str) -> str:
    model = ", ".join(f"{n} " + " ".join(f"{k}={v:.4g}" for k, v in p.items())
                      for n, p in pairs)
    how = ("intervals as imunoise fit reports them (Allan fit, octave taus)"
           if method == "allan" else
           "the Cramer-Rao bound of the exact Gaussian likelihood (the narrowest possible)")
    return (f"one gap-free record at {fs_hz:g} Hz of a sensor that follows {model} "
            f"(SI units), stationary; {how}")


def time_to_target(current: Mapping[tuple[str, str], float], record_s: float,
                   targets: Sequence[Target], model, fs_hz: float) -> dict[tuple[str, str],
                                                                          float | None]:
    """For a recording under way: the further time (s) until each target is reached, from
    the plan for the fitted model (0 when the current interval already meets it)."""
    out: dict[tuple[str, str], float | None] = {}
    for p in plan(model, fs_hz, targets):
        key = (p.target.label, p.target.param)
        if current.get(key, math.inf) <= p.target.relative:
            out[key] = 0.0
        else:
            out[key] = None if p.record_s is None else max(0.0, p.record_s - record_s)
    return out
