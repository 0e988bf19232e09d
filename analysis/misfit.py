"""How far a measured Allan curve lies from a noise model, honestly.

The overlapping Allan variance estimates at neighbouring taus share most of their data, so they
are correlated. For a model made of Gaussian noise terms (plus deterministic ramp and sinusoid)
this module computes the covariance matrix of the overlapping AVAR estimates at all taus of a
curve, from the model's spectrum:

With ``d_k^(m)`` the difference of two adjacent m-sample averages (``avar = E[d^2]/2``) and
``M`` the number of such differences, ``cov(avar_i, avar_j) = sum_k sum_l 2 gamma_ij(l-k)^2 /
(4 M_i M_j)`` where ``gamma_ij`` is the cross-covariance of the two difference sequences. By
Parseval ``sum_s gamma_ij(s)^2 = fs int S(f)^2 |H_i(f)|^2 |H_j(f)|^2 df`` (two-sided PSD S,
``|H_m|^2 = 4 sin^4(pi f m/fs)/(m^2 sin^2(pi f/fs))``), and the double sum is
``M_eff sum_s gamma^2`` with ``M_eff = min(M_i, M_j) - max(m_i, m_j)/2`` (exact for white noise,
where the end effect of the triangular count is m/2). The integral runs on a log-frequency grid;
where ``sin^4`` oscillates faster than the grid, it is averaged over each bin analytically
(products of the two filters through their Fourier series), so no resolution is lost at large
m. A deterministic sinusoid adds ``A^2 fs S(f0) |H_i H_j|^2(f0)``; a ramp adds
``R^2 tau_i tau_j cov(mean d_i, mean d_j)`` where the mean difference telescopes to the
difference of the averages at the two ends of the record.

From the covariance follow each estimate's equivalent degrees of freedom
``nu_i = 2 avar_i^2/C_ii``, the standardised residual ``z_i`` (normal score of the chi-square
probability of the measurement given the model) and ``chi2 = z^T R^-1 z`` with ``R`` the
correlation matrix, divided by the degrees of freedom left after the fit.
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from imunoise.analysis import distributions as dist
from imunoise.analysis.bin_average import SIN4, bin_avg_cos, sin4_table
from imunoise.analysis.terms import get_term, model_psd

Model = Sequence[tuple[str, dict[str, float]]]

_POINTS_PER_DECADE = 100
Z_CLIP = 1.0e4
"""Largest |z| reported (a measurement 1e4 standard scores from the model)."""


def _two_sided_psd(model: Model, u: np.ndarray, fs_hz: float) -> np.ndarray:
    """Two-sided PSD (units^2/Hz) of the model's Gaussian noise (its ``role == "noise"`` terms,
    seen through its output filter when it has one) at f = u fs."""
    noise = [(n, p) for n, p in model
             if get_term(n).role == "noise" or get_term(n).kind == "filter"]
    return 0.5 * model_psd(noise, u * fs_hz, fs_hz)


_P, _Q = np.meshgrid(np.arange(3), np.arange(3), indexing="ij")
_PQ_COEF = np.tile(0.5 * np.outer(SIN4, SIN4).ravel(), 2)


def _pair_sin4_both_fast(mi: float, mj: float, ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Bin average of sin^4(pi u mi) sin^4(pi u mj) through the product of Fourier series
    (all 18 cosine frequencies of the product evaluated at once)."""
    nus = np.concatenate([2.0 * (_P * mi + _Q * mj).ravel(), 2.0 * (_P * mi - _Q * mj).ravel()])
    x = np.pi * nus[:, None]
    with np.errstate(invalid="ignore", divide="ignore"):
        vals = (np.sin(x * ub) - np.sin(x * ua)) / (x * (ub - ua))
    vals[nus == 0] = 1.0
    return _PQ_COEF @ vals


@dataclass(frozen=True)
class _CovGrid:
    """The part of :func:`avar_covariance` that depends only on the averaging factors: the
    frequency bins, the bin-averaged ``sin^4`` factors and, for each pair of taus whose
    filters both oscillate within some bins, the correction of the product of their averages
    to the average of their product (``exact - f_i f_j`` on those bins)."""

    ua: np.ndarray
    ub: np.ndarray
    um: np.ndarray
    width: np.ndarray
    factors: np.ndarray
    pairs: tuple[tuple[int, int, np.ndarray, np.ndarray], ...]


_GRID_CACHE: OrderedDict[bytes, _CovGrid] = OrderedDict()
_GRID_CACHE_SIZE = 32
_GRID_LOCK = threading.Lock()


def _cov_grid(m: np.ndarray) -> _CovGrid:
    """:class:`_CovGrid` for the averaging factors ``m`` (float64), remembered by their values
    (every model fitted to one curve shares it)."""
    key = m.tobytes()
    with _GRID_LOCK:
        hit = _GRID_CACHE.get(key)
        if hit is not None:
            _GRID_CACHE.move_to_end(key)
            return hit
    n = len(m)
    u_lo = 1e-4 / max(m.max(), 1.0)
    edges = np.geomspace(u_lo, 0.5, int(math.log10(0.5 / u_lo) * _POINTS_PER_DECADE) + 2)
    ua, ub = edges[:-1], edges[1:]
    um = 0.5 * (ua + ub)
    width = ub - ua
    fast = width[None, :] * m[:, None] > 0.05
    factors = sin4_table(m[:, None], um, ua, ub)
    # where both filters oscillate within a bin, the two factors of equal or double m are
    # not independent: their product's exact average replaces the product of averages (for
    # larger ratios the cross terms of the Fourier series oscillate fast and average out)
    index = {float(v): k for k, v in enumerate(m)}
    pairs = []
    for i in range(n):
        for j in {i, index.get(2.0 * float(m[i]), i)}:
            both = fast[i] & fast[j]
            if not np.any(both):
                continue
            exact = _pair_sin4_both_fast(m[i], m[j], ua[both], ub[both])
            pairs.append((i, j, np.flatnonzero(both), exact - factors[i, both] * factors[j, both]))
    for a in (ua, ub, um, width, factors):
        a.setflags(write=False)
    grid = _CovGrid(ua, ub, um, width, factors, tuple(pairs))
    with _GRID_LOCK:
        _GRID_CACHE[key] = grid
        while len(_GRID_CACHE) > _GRID_CACHE_SIZE:
            _GRID_CACHE.popitem(last=False)
    return grid


def avar_covariance(model: Model, fs_hz: float, m: np.ndarray, n_terms: np.ndarray
                    ) -> np.ndarray:
    """Covariance matrix (units^4) of overlapping AVAR estimates at averaging factors ``m``
    (samples) with ``n_terms`` squared differences each, for data following ``model``.

    Terms without a spectrum of their own (``temperature``, removed by regression) are left
    out; a ramp and a sinusoid enter through their interaction with the Gaussian noise.
    """
    m = np.asarray(m, dtype=np.float64)
    n_terms = np.asarray(n_terms, dtype=np.float64)
    grid = _cov_grid(m)
    ua, ub, um, width, factors = grid.ua, grid.ub, grid.um, grid.width, grid.factors
    s2 = _two_sided_psd(model, um, fs_hz)
    # smooth part of S^2 |H_i|^2 |H_j|^2 du (without the sin^4 factors and 1/(m_i m_j)^2),
    # times 2 fs^2 for both signs of f and the change of variable f = u fs
    smooth = 2.0 * fs_hz**2 * s2 * s2 * 16.0 / np.sin(np.pi * um) ** 4 * width
    sum_gamma2 = (factors * smooth) @ factors.T
    for i, j, both, diff in grid.pairs:
        delta = float(np.sum(smooth[both] * diff))
        sum_gamma2[i, j] += delta
        if j != i:
            sum_gamma2[j, i] += delta
    sum_gamma2 /= np.outer(m * m, m * m)
    line, ramp = _deterministic_terms(model, fs_hz, m, n_terms, (ua, ub, um, s2))
    sum_gamma2 += line
    m_eff = np.minimum.outer(n_terms, n_terms) - 0.5 * np.minimum.outer(m, m)
    m_eff = np.maximum(m_eff, 1.0)
    return m_eff * sum_gamma2 / (2.0 * np.outer(n_terms, n_terms)) + ramp


def _h2(m: np.ndarray, u: float) -> np.ndarray:
    """|H_m(u)|^2 of the difference of two m-sample averages at u = f/fs."""
    return 4.0 * np.sin(np.pi * u * m) ** 4 / (m * m * math.sin(math.pi * u) ** 2)


def _deterministic_terms(model: Model, fs_hz: float, m: np.ndarray, n_terms: np.ndarray,
                         grid: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]
                         ) -> np.ndarray:
    """Covariance (units^4) added by a deterministic sinusoid and a deterministic ramp.

    Sinusoid: ``cov(d_k^2, d_l^2)`` gains ``4 s_k s_l gamma(l-k)``; summed, this is
    ``M_eff A^2 fs S(f0) |H_i H_j|^2(f0)`` in the same units as ``sum gamma^2`` (returned
    separately, see :func:`avar_covariance`). Ramp: each estimate gains ``R tau mean(d)``;
    the mean of the differences telescopes to ``(m/M)`` times the difference of the m-sample
    averages at the two ends of the record, whose variance ``D`` follows from the spectrum.
    """
    ua, ub, um, s2 = grid
    n = len(m)
    line = np.zeros((n, n))
    ramp = np.zeros((n, n))
    lines = [get_term(name).line(p) for name, p in model if get_term(name).role == "line"]
    for amp, f0 in lines:
        u0 = f0 / fs_hz
        s_n = float(_two_sided_psd(model, np.array([u0]), fs_hz)[0])
        h = _h2(m, u0)
        line += amp**2 * fs_hz * s_n * np.outer(h, h)
    r2 = sum(get_term(name).ramp_slope(p) ** 2 for name, p in model
             if get_term(name).role == "ramp")
    if r2 > 0:
        width = ub - ua
        d = np.empty(n)
        for i in range(n):
            span = float(n_terms[i] - 1 + m[i])  # distance between the two end averages
            sin2_span = 0.5 * (1.0 - bin_avg_cos(2.0 * span, ua, ub))
            fast = width * m[i] > 0.05
            sin2_m = np.where(fast, 0.5 * (1.0 - bin_avg_cos(2.0 * m[i], ua, ub)),
                              np.sin(np.pi * um * m[i]) ** 2)
            avg2 = sin2_m / (m[i] ** 2 * np.sin(np.pi * um) ** 2)
            d[i] = 2.0 * fs_hz * float(np.sum(s2 * avg2 * 4.0 * sin2_span * width))
            for amp, f0 in lines:
                u0 = f0 / fs_hz
                a2 = math.sin(math.pi * u0 * m[i]) ** 2 / (m[i] ** 2 * math.sin(
                    math.pi * u0) ** 2)
                d[i] += 0.5 * amp**2 * a2 * 4.0 * math.sin(math.pi * u0 * span) ** 2
        tau = m / fs_hz
        mean_sd = m / n_terms * np.sqrt(d)
        ramp = r2 * np.outer(tau * mean_sd, tau * mean_sd)
    return line, ramp


@dataclass(frozen=True)
class Misfit:
    """Standardised residuals of a measured Allan curve against a model.

    Attributes:
        z: per-tau standardised residual (positive: measured above model).
        nu: per-tau equivalent degrees of freedom under the model.
        corr: correlation matrix of the estimates across taus.
        chi2: ``z^T corr^-1 z``.
        dof: degrees of freedom (taus used minus fitted parameters, at least 1).
        chi2_per_dof: ``chi2/dof``.
        threshold: |z| beyond which a tau is flagged.
    """

    z: np.ndarray
    nu: np.ndarray
    corr: np.ndarray
    chi2: float
    dof: int
    chi2_per_dof: float
    threshold: float

    @property
    def max_abs_z(self) -> float:
        return float(np.max(np.abs(self.z))) if self.z.size else 0.0


def failure_threshold(n_tau: int, family_rate: float = 0.10) -> float:
    """|z| threshold so that a correct model flags any tau with probability <= family_rate
    (Sidak correction over ``n_tau`` two-sided tests; conservative for correlated taus)."""
    per = 1.0 - (1.0 - family_rate) ** (1.0 / max(n_tau, 1))
    return float(dist.norm.isf(per / 2.0))


def standardised_residuals(avar_meas: np.ndarray, avar_model: np.ndarray, nu: np.ndarray
                           ) -> np.ndarray:
    """Normal scores of the measured AVAR under the scaled chi-square law of the model.

    Far in the tails the chi-square probability underflows; there the score is continued from
    its logarithm (asymptotic inverse of the normal tail) and, where even that is not finite,
    by the Wilson-Hilferty cube-root transform, so a model that misses by more still scores
    worse (a clipped score would make every bad model look alike to the fit). Scores are
    bounded by ``Z_CLIP``."""
    nu = np.asarray(nu, dtype=np.float64)
    x = nu * np.asarray(avar_meas) / np.asarray(avar_model)
    lower = dist.chi2.logcdf(x, nu)
    upper = dist.chi2.logsf(x, nu)
    sign = np.where(lower < upper, -1.0, 1.0)
    logp = np.minimum(lower, upper)
    with np.errstate(all="ignore"):
        z = dist.norm.isf(np.exp(logp))
        tail = logp < -700.0
        if np.any(tail):
            # log Phi(-z) = -z^2/2 - ln z - ln(2 pi)/2, solved by fixed-point iteration
            lp = logp[tail]
            zt = np.sqrt(-2.0 * lp)
            for _ in range(4):
                zt = np.sqrt(np.maximum(-2.0 * (lp + np.log(zt) + 0.5 * math.log(2 * math.pi)),
                                        0.0))
            z[tail] = zt
        wh = np.abs(((x / nu) ** (1.0 / 3.0) - (1.0 - 2.0 / (9.0 * nu)))
                    / np.sqrt(2.0 / (9.0 * nu)))
    z = np.where(np.isfinite(z), z, wh)
    z = sign * np.nan_to_num(z, nan=0.0, posinf=Z_CLIP)
    return np.clip(z, -Z_CLIP, Z_CLIP)


def misfit(avar_meas: np.ndarray, avar_model: np.ndarray, cov: np.ndarray, n_params: int,
           family_rate: float = 0.10) -> Misfit:
    """Misfit of measured AVARs to model AVARs with the model's estimate covariance ``cov``."""
    var = np.clip(np.diag(cov), 1e-300, None)
    nu = np.clip(2.0 * np.asarray(avar_model) ** 2 / var, 1.0, 1e12)
    sd = np.sqrt(var)
    corr = cov / np.outer(sd, sd)
    z = standardised_residuals(avar_meas, avar_model, nu)
    chi2 = float(z @ _solve_psd(corr, z))
    dof = max(len(z) - n_params, 1)
    return Misfit(z=z, nu=nu, corr=corr, chi2=chi2, dof=dof, chi2_per_dof=chi2 / dof,
                  threshold=failure_threshold(len(z), family_rate))


def _solve_psd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Solve with a symmetric positive semi-definite matrix, guarding against round-off."""
    w, v = np.linalg.eigh(a)
    w = np.maximum(w, 1e-9 * max(w.max(), 1e-300))
    return v @ ((v.T @ b) / w)


def failures(tau_s: np.ndarray, z: np.ndarray, threshold: float) -> list[dict]:
    """Groups of consecutive taus with ``|z| > threshold`` and the same sign, as docs/json.md's
    ``failures`` entries."""
    out: list[dict] = []
    flagged = np.abs(z) > threshold
    i = 0
    while i < len(z):
        if not flagged[i]:
            i += 1
            continue
        sign = np.sign(z[i])
        j = i
        while j + 1 < len(z) and flagged[j + 1] and np.sign(z[j + 1]) == sign:
            j += 1
        seg = z[i:j + 1]
        out.append({"tau_s": [float(tau_s[i]), float(tau_s[j])],
                    "max_abs_z": float(np.max(np.abs(seg))),
                    "direction": "measured above model" if sign > 0 else
                    "measured below model"})
        i = j + 1
    return out
