"""What a fit returns: the fitted terms with their intervals, and the misfit of the model
to the measured Allan curve.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np
import scipy.linalg

from imunoise.analysis.misfit import Misfit
from imunoise.analysis.terms import (
    ModelSpec,
    get_term,
    labels,
    model_avar,
)


class CurveLike(Protocol):
    """What the fit needs from an Allan curve (``imunoise.analysis.allan.AllanCurve`` provides
    it; read-only, as its frozen dataclass)."""

    @property
    def fs_hz(self) -> float: ...
    @property
    def tau_s(self) -> np.ndarray: ...
    @property
    def m(self) -> np.ndarray: ...
    @property
    def dev(self) -> np.ndarray: ...
    @property
    def n_terms(self) -> np.ndarray: ...


ModelLike = Sequence[str] | Sequence[tuple[str, dict[str, float]]] | str | ModelSpec


@dataclass
class TermFit:
    """One fitted term: parameters (SI) and their 95 % intervals."""

    term: str
    params: dict[str, float]
    ci95: dict[str, tuple[float, float]]

    def to_dict(self) -> dict[str, Any]:
        return {"term": self.term, "params": dict(self.params),
                "ci95": {k: [float(a), float(b)] for k, (a, b) in self.ci95.items()}}


@dataclass
class FitResult:
    """A fitted model and how well it explains the measured Allan curve.

    Attributes:
        terms: fitted terms in model order (``temperature`` included when fitted upstream).
        fs_hz: sampling rate, Hz.
        tau_s, m, n_terms: the curve's averaging times (s), factors, number of differences.
        avar_measured: measured Allan variance (units^2).
        avar_fit: model Allan variance at ``tau_s``.
        term_avar: per-term model Allan variance at ``tau_s`` (for plotting).
        misfit: z per tau, chi2 and the rest (:class:`imunoise.analysis.misfit.Misfit`).
        failures: ``failures`` entries of the JSON documents (docs/json.md).
        param_cov: covariance of the log-parameters (order of :attr:`free_params`).
        free_params: ``(term index, parameter name)`` of each fitted parameter.
    """

    terms: list[TermFit]
    fs_hz: float
    tau_s: np.ndarray
    m: np.ndarray
    n_terms: np.ndarray
    avar_measured: np.ndarray
    avar_fit: np.ndarray
    term_avar: list[np.ndarray]
    misfit: Misfit
    failures: list[dict]
    param_cov: np.ndarray
    free_params: list[tuple[int, str]] = field(default_factory=list)
    used: np.ndarray | None = None
    """Taus the parameters rest on (failing shortest taus are set aside)."""
    _dispersions: np.ndarray | None = field(default=None, repr=False, compare=False)
    """:meth:`dispersion_of` of each free parameter (order of :attr:`free_params`), computed
    on first use; a reordering of the terms keeps the order of :attr:`free_params`."""

    @property
    def params(self) -> list[tuple[str, dict[str, float]]]:
        """The model as ``[(term, params)]``, usable as a starting point of a refit."""
        return [(t.term, dict(t.params)) for t in self.terms]

    def in_canonical_order(self) -> FitResult:
        """This fit with interchangeable repeated terms ordered by their first shape
        parameter, ascending (a resonance's f0, a line's f, a Markov term's T).

        Two entries of a repeatable term that hold the same parameters at the same values
        (``resonance,resonance``) describe the same model whichever solution the solver put
        in which entry, and different fits of one model can put them either way round: on
        ADIS16405 run 1 gyro_z the whole record's fit puts its 10.4 Hz resonance first, a
        half's fit its 19.5 Hz one. Ordered, a label (``resonance#2``, the higher one) names
        the same component on every fit of the model, as the hold-out part's changed
        parameters and a model written back from the JSON need. Nothing else changes: the
        model, its misfit and intervals are the same."""
        free = set(self.free_params)
        groups: dict[tuple[Any, ...], list[int]] = {}
        for i, t in enumerate(self.terms):
            if get_term(t.term).repeatable:
                held = tuple(sorted((k, v) for k, v in t.params.items() if (i, k) not in free))
                groups.setdefault((t.term, held), []).append(i)
        order = list(range(len(self.terms)))
        for at in groups.values():
            shape = next(p.name for p in get_term(self.terms[at[0]].term).params if p.is_scale)
            for slot, i in zip(at, sorted(at, key=lambda i: self.terms[i].params[shape]),
                               strict=True):
                order[slot] = i
        if order == sorted(order):
            return self
        moved = {old: new for new, old in enumerate(order)}
        return replace(self, terms=[self.terms[i] for i in order],
                       term_avar=[self.term_avar[i] for i in order],
                       free_params=[(moved[i], k) for i, k in self.free_params],
                       _dispersions=self._dispersions)

    @property
    def labels(self) -> list[str]:
        """Each term's label in model order: its name, ``name#K`` for the K-th of a repeated
        term (the grammar of :mod:`imunoise.analysis.terms.spec`)."""
        return labels([t.term for t in self.terms])

    @property
    def ci95(self) -> list[dict[str, tuple[float, float]]]:
        return [t.ci95 for t in self.terms]

    @property
    def chi2_per_dof(self) -> float:
        return self.misfit.chi2_per_dof

    @property
    def z(self) -> np.ndarray:
        return self.misfit.z

    @property
    def max_abs_z(self) -> float:
        return self.misfit.max_abs_z

    def dispersion_of(self, index: int, param: str) -> float:
        """How much wider than its linearised interval the interval of parameter ``param`` of
        term ``index`` is, in variance: the fit's chi2/dof, or less where the taus the
        parameter rests on fit better than the curve as a whole; at least 1.

        The misfit of a parameter's taus is the mean of the squared residuals over the taus
        the fit used, each weighted by the parameter's Fisher information there, both in the
        metric of the chi2: the standardised residuals ``z`` and the sensitivities of the
        standardised log Allan variance to the log-parameter (:func:`log_sensitivities`),
        whitened by the Cholesky factor of the estimates' correlation over increasing tau.
        A model that misses its long taus says nothing about the white level, estimated at
        the shortest ones, whose interval the chi2/dof would widen all the same: ADIS16405
        run 2 accel_y's first half misses at 2.6-41 s (chi2/dof 2.51) and its white level's
        taus give 1.0. The value never exceeds the chi2/dof: a weighted mean over the few
        taus a parameter rests on is noisy (a right model's random walk reaches 2.4 at
        chi2/dof 1.34), and a parameter whose own taus fit worse than the whole keeps the
        whole's widening. A parameter the fit holds, or one no tau is sensitive to, gets the
        chi2/dof (at least 1)."""
        whole = max(1.0, float(self.chi2_per_dof))
        if (index, param) not in self.free_params:
            return whole
        if self._dispersions is None:
            self._dispersions = self._local_dispersions(whole)
        return float(self._dispersions[self.free_params.index((index, param))])

    def _local_dispersions(self, whole: float) -> np.ndarray:
        used = np.flatnonzero(np.ones(self.tau_s.size, bool) if self.used is None
                              else np.asarray(self.used))
        # in the chi2's own metric: residuals and sensitivities whitened by the Cholesky
        # factor of the estimates' correlation, taus in increasing order, so that each
        # whitened value is what its tau adds to the shorter ones (a misfit can lie in the
        # pattern of correlated neighbours, each |z| small)
        corr = np.asarray(self.misfit.corr, dtype=np.float64)[np.ix_(used, used)]
        jitter = 1e-9 * max(float(np.max(np.abs(np.diag(corr)), initial=0.0)), 1e-300)
        try:
            chol = np.linalg.cholesky(corr + jitter * np.eye(used.size))
        except np.linalg.LinAlgError:
            return np.full(len(self.free_params), whole)
        e2 = scipy.linalg.solve_triangular(chol, np.asarray(self.misfit.z)[used], lower=True) ** 2
        out = np.full(len(self.free_params), whole)
        for n, s in enumerate(log_sensitivities(self, self.free_params)):
            if not np.all(np.isfinite(s[used])):
                continue
            w = scipy.linalg.solve_triangular(chol, s[used], lower=True) ** 2
            if float(w.sum()) > 0.0:
                out[n] = max(1.0, min(whole, float(w @ e2) / float(w.sum())))
        return out

    def model_avar(self, tau_s: np.ndarray | float) -> np.ndarray:
        """Model Allan variance at any ``tau_s`` (the fitted noise terms; temperature, removed
        upstream, contributes nothing)."""
        tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
        return model_avar([(t.term, t.params) for t in self.terms
                           if get_term(t.term).role != "regressor"], tau, self.fs_hz)

    def term_avar_at(self, tau_s: np.ndarray | float) -> dict[str, np.ndarray]:
        """Per-term Allan variance at ``tau_s`` keyed ``term`` (``term#2`` for repeats)."""
        tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
        return {key: _term_avar(t.term, t.params, tau, self.fs_hz)
                for key, t in zip(self.labels, self.terms, strict=True)}

    def allan_dict(self, ci_low: np.ndarray | None = None, ci_high: np.ndarray | None = None
                   ) -> dict[str, list[float]]:
        """The JSON ``allan`` block (docs/json.md; deviations, not variances)."""
        adev = np.sqrt(self.avar_measured)
        return {"tau_s": self.tau_s.tolist(), "adev": adev.tolist(),
                "ci_low": (ci_low if ci_low is not None else adev).tolist(),
                "ci_high": (ci_high if ci_high is not None else adev).tolist(),
                "model_adev": np.sqrt(self.avar_fit).tolist(),
                "z": self.misfit.z.tolist()}


def _term_avar(name: str, params: dict[str, float], tau: np.ndarray, fs: float) -> np.ndarray:
    term = get_term(name)
    if term.role == "regressor":
        return np.zeros_like(tau)
    return term.avar(tau, fs, **params)


_LOG_STEP = 1e-4
"""Step of the log-parameters in :func:`log_sensitivities`."""


def log_sensitivities(fit: FitResult, params: Sequence[tuple[int, str]]) -> list[np.ndarray]:
    """For each ``(term index, parameter)``, the change of each tau's standardised log Allan
    variance per unit change of the log-parameter: ``d ln avar / d ln p`` at the fitted model
    times ``sqrt(nu / 2)`` (``nu`` the estimate's degrees of freedom, so that one unit is one
    standard deviation of ``ln avar``). Central differences, one-sided where a step leaves the
    parameter's range; NaN where neither step can be taken."""
    fitted = [(t.term, dict(t.params)) for t in fit.terms
              if get_term(t.term).role != "regressor"]
    position = {n: p for p, n in enumerate(
        n for n, t in enumerate(fit.terms) if get_term(t.term).role != "regressor")}
    scale = np.sqrt(np.asarray(fit.misfit.nu, dtype=np.float64) / 2.0)

    def ln_avar(model: list[tuple[str, dict[str, float]]]) -> np.ndarray | None:
        try:
            avar = model_avar(model, fit.tau_s, fit.fs_hz)
        except (ValueError, ArithmeticError):  # TermError is a ValueError: out of range
            return None
        return np.log(np.maximum(avar, 1e-300)) if np.all(np.isfinite(avar)) else None

    def moved(index: int, param: str, step: float) -> list[tuple[str, dict[str, float]]]:
        trial = [(name, dict(p)) for name, p in fitted]
        trial[position[index]][1][param] *= float(np.exp(step))
        return trial

    mid = ln_avar(fitted)
    out = []
    for index, param in params:
        d = np.full(fit.tau_s.size, np.nan)
        if index in position:
            up = ln_avar(moved(index, param, _LOG_STEP))
            down = ln_avar(moved(index, param, -_LOG_STEP))
            if up is not None and down is not None:
                d = (up - down) / (2.0 * _LOG_STEP)
            elif up is not None and mid is not None:
                d = (up - mid) / _LOG_STEP
            elif down is not None and mid is not None:
                d = (mid - down) / _LOG_STEP
        out.append(d * scale)
    return out
