"""Composite noise-model fit to a measured Allan curve, with honest intervals and misfit.

The model's Allan variance is the sum of its terms' (:mod:`imunoise.analysis.terms`). The fit works
on
``ln(avar)`` at every tau of the curve:

1. Starting values without hand-picked tau windows: the linear terms (white, quantization,
   bias instability, random walk, ramp) are linear in their squared parameters, so a
   non-negative least-squares solve on the relative residuals, weighted by each estimate's
   degrees of freedom, gives them all at once. Each Gauss-Markov term adds a grid search over
   its correlation time T (the amplitude stays linear); a sinusoid starts from the strongest
   spectral line when the caller supplies one (see :func:`find_line`), else from a grid in f;
   several sinusoids start at as many lines (:func:`series_lines`).
2. Generalised least squares on ``ln(avar)`` with parameters in log form (positivity): the
   residuals are whitened with the covariance of the log estimates across taus computed from
   the model itself (:func:`imunoise.analysis.misfit.avar_covariance`), corrected for the
   chi-square law
   of each estimate (mean ``psi(nu/2) - ln(nu/2)``, variance ``psi'(nu/2)``). The covariance is
   computed for the starting model, the fit solved, and the covariance recomputed for the
   result.
3. 95 % intervals from the whitened Jacobian (``(J^T J)^-1`` in log-parameter space,
   so intervals are asymmetric and positive); the misfit (chi2 per degree of freedom, z per
   tau, failing tau ranges) from :func:`imunoise.analysis.misfit.misfit`.

``temperature`` is not part of the Allan fit: :func:`regress_temperature` removes it from the
series first (see :func:`fit_series`).
"""

from __future__ import annotations

from imunoise.analysis.fit.result import CurveLike, FitResult, ModelLike, TermFit
from imunoise.analysis.fit.series import (
    find_line,
    fit_series,
    regress_temperature,
    series_line,
    series_lines,
)
from imunoise.analysis.fit.solve import fit_allan

__all__ = [
    "CurveLike",
    "find_line",
    "fit_allan",
    "fit_series",
    "FitResult",
    "ModelLike",
    "regress_temperature",
    "series_line",
    "series_lines",
    "TermFit",
]
