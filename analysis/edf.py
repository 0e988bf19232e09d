"""Equivalent degrees of freedom, confidence intervals and power-law noise identification.

The uncertainty of an Allan-family estimate is expressed as a chi-square interval with
``edf`` equivalent degrees of freedom (NIST SP 1065 eq. 45). The ``edf`` depends on the
power-law noise type, written as the exponent ``alpha`` of the one-sided PSD of the rate
("fractional frequency" in time and frequency metrology):

=====  ============================  ==================================
alpha  clock name                    inertial-sensor name
=====  ============================  ==================================
  2    white phase                   angle (velocity) quantization
  1    flicker phase                 -
  0    white frequency               angle (velocity) random walk
 -1    flicker frequency             bias instability
 -2    random-walk frequency         rate random walk
 -3    flicker-walk frequency        -
 -4    random-run frequency          rate ramp (as a random process)
=====  ============================  ==================================

``greenhall_edf`` implements the algorithm of C. A. Greenhall and W. J. Riley, "Uncertainty of
stability variances based on finite differences", Proc. 35th PTTI (2003), which is what
Stable32 uses. ``noise_id_lag1`` implements the lag-1 autocorrelation identification of
W. J. Riley and C. A. Greenhall, "Power law noise identification using the lag 1
autocorrelation", Proc. 18th EFTF (2004). Where the averaged series is too short for it (fewer
than ``LAG1_MIN_POINTS`` averages, the longest taus) ``noise_id_b1_rn`` identifies the noise as
Stable32 does there: the B1 bias ratio (Barnes 1969; Howe, Beard, Greenhall and Riley 2000,
table 3), with R(n), the ratio of the modified to the normal Allan variance, separating the
phase-noise types that B1 cannot (W. J. Riley, Handbook of Frequency Stability Analysis, NIST
SP 1065, 2008, section 5.6).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from scipy import special

from imunoise.analysis import allan_kernels
from imunoise.analysis import distributions as dist

#: Largest number of summands evaluated directly in the Greenhall basic sum.
GREENHALL_JMAX = 100

#: Minimum length of the averaged series for the lag-1 ACF method (Riley & Greenhall 2004).
LAG1_MIN_POINTS = 30

# Greenhall & Riley (2003) Table 1: modified variances (F = 1), (a0, a1) by alpha and d = 1..3.
_TABLE1: dict[int, tuple[tuple[float, float] | None, ...]] = {
    2: ((2 / 3, 1 / 3), (7 / 9, 1 / 2), (22 / 25, 2 / 3)),
    1: ((0.840, 0.345), (0.997, 0.616), (1.141, 0.843)),
    0: ((1.079, 0.368), (1.033, 0.607), (1.184, 0.848)),
    -1: (None, (1.048, 0.534), (1.180, 0.816)),
    -2: (None, (1.302, 0.535), (1.175, 0.777)),
    -3: (None, None, (1.194, 0.703)),
    -4: (None, None, (1.489, 0.702)),
}

# Table 2: unmodified variances (F = m), (a0, a1) by alpha and d = 1..3.
_TABLE2: dict[int, tuple[tuple[float, float] | None, ...]] = {
    2: ((3 / 2, 1 / 2), (35 / 18, 1.0), (231 / 100, 3 / 2)),
    1: ((78.6, 25.2), (790.0, 410.0), (9950.0, 6520.0)),
    0: ((2 / 3, 1 / 6), (2 / 3, 1 / 3), (7 / 9, 1 / 2)),
    -1: (None, (0.852, 0.375), (0.997, 0.617)),
    -2: (None, (1.079, 0.368), (1.033, 0.607)),
    -3: (None, None, (1.053, 0.553)),
    -4: (None, None, (1.302, 0.535)),
}

# Table 3: unmodified variances, alpha = 1: sz(0) ~ b0 + b1 ln(m), by d = 1..3.
_TABLE3: tuple[tuple[float, float], ...] = ((6.0, 4.0), (15.23, 12.0), (47.8, 40.0))


def _sw(t: np.ndarray, alpha: int) -> np.ndarray:
    """Greenhall's generalized autocovariance kernel sw(t) for integer alpha (eq. 7)."""
    t = np.asarray(t, dtype=np.float64)
    at = np.abs(t)
    power = 3 - alpha
    # The overall sign of each kernel cancels in the edf ratio; these follow the paper.
    sign = {2: -1.0, 1: 1.0, 0: 1.0, -1: -1.0, -2: -1.0, -3: 1.0, -4: 1.0}[alpha]
    if alpha % 2 == 0:
        return sign * at**power
    with np.errstate(divide="ignore", invalid="ignore"):
        out = sign * at**power * np.log(at)
    return np.where(at == 0.0, 0.0, out)


def _sx(t: np.ndarray, f: float, alpha: int) -> np.ndarray:
    """Kernel after the averaging filter of length 1/F (eq. 8); F = inf means no averaging."""
    if math.isinf(f):
        return _sw(t, alpha + 2)
    return f * f * (2.0 * _sw(t, alpha) - _sw(t - 1.0 / f, alpha) - _sw(t + 1.0 / f, alpha))


def _sz(t: np.ndarray, f: float, alpha: int, d: int) -> np.ndarray:
    """Kernel after the d-th difference (eq. 9)."""
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros_like(t)
    for k in range(-d, d + 1):
        out += (-1) ** k * special.comb(2 * d, d + k) * _sx(t + k, f, alpha)
    return out


def _basic_sum(j: int, big_m: float, s: float, f: float, alpha: int, d: int) -> float:
    """Greenhall's basic sum (eq. 10)."""
    j = int(j)
    total = float(_sz(np.zeros(1), f, alpha, d)[0] ** 2)
    total += (1.0 - j / big_m) * float(_sz(np.array([j / s]), f, alpha, d)[0] ** 2)
    if j > 1:
        jj = np.arange(1, j, dtype=np.float64)
        total += float(np.sum(2.0 * (1.0 - jj / big_m) * _sz(jj / s, f, alpha, d) ** 2))
    return total


def greenhall_edf(
    alpha: int, d: int, m: int, n: int, overlapping: bool, modified: bool
) -> float:
    """Equivalent degrees of freedom of a finite-difference variance estimate.

    Args:
        alpha: power-law exponent of the rate PSD (integer, -4..2); needs ``alpha + 2 d > 1``.
        d: order of the phase difference: 2 for Allan and modified Allan, 3 for Hadamard.
        m: averaging factor (tau = m tau0).
        n: number of phase points (rate samples + 1) in the contiguous record.
        overlapping: every start index is used (OADEV, OHDEV, MDEV) rather than stride m.
        modified: modified variance (MDEV): phase averaged over m before differencing.

    Returns:
        edf (> 0), or ``nan`` when the record is too short for a single term.
    """
    alpha = int(alpha)
    if alpha + 2 * d <= 1:
        raise ValueError(f"edf undefined for alpha={alpha} with difference order d={d}")
    f = 1.0 if modified else float(m)
    s = float(m) if overlapping else 1.0
    length = m / f + m * d
    big_m = 1.0 + math.floor(s * (n - length) / m)
    if big_m < 1:
        return math.nan
    j = min(big_m, (d + 1) * s)
    r = big_m / s
    jmax = GREENHALL_JMAX

    if modified:
        if j <= jmax:
            inv = _basic_sum(j, big_m, s, 1.0, alpha, d) / (_sz0(1.0, alpha, d) ** 2 * big_m)
        elif r > d + 1:
            a0, a1 = _table(_TABLE1, alpha, d)
            inv = (a0 - a1 / r) / r
        else:
            mp = jmax / r
            inv = _basic_sum(jmax, jmax, mp, 1.0, alpha, d) / (_sz0(1.0, alpha, d) ** 2 * jmax)
    elif alpha <= 0:
        if j <= jmax:
            fp = float(m) if m * (d + 1) <= jmax else math.inf
            inv = _basic_sum(j, big_m, s, fp, alpha, d) / (_sz0(fp, alpha, d) ** 2 * big_m)
        elif r > d + 1:
            a0, a1 = _table(_TABLE2, alpha, d)
            inv = (a0 - a1 / r) / r
        else:
            mp = jmax / r
            inv = _basic_sum(jmax, jmax, mp, math.inf, alpha, d) / (
                _sz0(math.inf, alpha, d) ** 2 * jmax
            )
    elif alpha == 1:
        b0, b1 = _TABLE3[d - 1]
        if j <= jmax:
            inv = _basic_sum(j, big_m, s, float(m), 1, d) / (_sz0(float(m), 1, d) ** 2 * big_m)
        elif r > d + 1:
            a0, a1 = _table(_TABLE2, 1, d)
            inv = (a0 - a1 / r) / ((b0 + b1 * math.log(m)) ** 2 * r)
        else:
            mp = jmax / r
            inv = _basic_sum(jmax, jmax, mp, mp, 1, d) / ((b0 + b1 * math.log(m)) ** 2 * jmax)
    else:  # alpha == 2, unmodified: only the lags k = 0..d of stride tau are correlated
        k_top = math.ceil(r)
        c0 = special.comb(2 * d, d) ** 2
        kmax = min(k_top - 1, d)
        ks = np.arange(1, kmax + 1, dtype=np.float64)
        terms = (1.0 - ks / r) * special.comb(2 * d, d - ks) ** 2 / c0
        inv = (1.0 + 2.0 * float(np.sum(terms))) / big_m
    return 1.0 / inv if inv > 0 else math.nan


def _sz0(f: float, alpha: int, d: int) -> float:
    return float(_sz(np.zeros(1), f, alpha, d)[0])


def _table(
    table: dict[int, tuple[tuple[float, float] | None, ...]], alpha: int, d: int
) -> tuple[float, float]:
    entry = table[alpha][d - 1]
    if entry is None:
        raise ValueError(f"no Greenhall table entry for alpha={alpha}, d={d}")
    return entry


def chi2_interval(
    dev: np.ndarray, edf: np.ndarray, ci: float = 0.683
) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided chi-square confidence interval on a deviation.

    ``var * edf / chi2`` has a chi-square distribution with ``edf`` degrees of freedom
    (NIST SP 1065 eq. 45). Returns ``(low, high)`` bounds on the deviation (same units as
    ``dev``); ``nan`` where ``edf`` is not a positive finite number.
    """
    if not 0.0 < ci < 1.0:
        raise ValueError(f"confidence level must lie in (0, 1), got {ci}")
    dev = np.asarray(dev, dtype=np.float64)
    edf = np.asarray(edf, dtype=np.float64)
    ok = np.isfinite(edf) & (edf > 0)
    e = np.where(ok, edf, 1.0)
    tail = (1.0 - ci) / 2.0
    chi_hi = dist.chi2.ppf(1.0 - tail, e)
    chi_lo = dist.chi2.ppf(tail, e)
    low = np.where(ok, dev * np.sqrt(e / chi_hi), np.nan)
    high = np.where(ok, dev * np.sqrt(e / chi_lo), np.nan)
    return low, high


def lag1_acf(x: np.ndarray) -> float:
    """Lag-1 autocorrelation of ``x`` about its mean (Riley & Greenhall 2004, eq. 2)."""
    x = np.asarray(x, dtype=np.float64)
    c = x - x.mean()
    den = float(np.dot(c, c))
    if den == 0.0:
        return 0.0
    return float(np.dot(c[:-1], c[1:])) / den


def _detrend(x: np.ndarray, deg: int) -> np.ndarray:
    """Residual of a least-squares polynomial fit of degree 1 or 2 against the index."""
    t = np.arange(x.size, dtype=np.float64)
    t -= t.mean()
    if deg == 1:
        slope = float(np.dot(t, x - x.mean())) / float(np.dot(t, t))
        return x - x.mean() - slope * t
    t /= max(1.0, x.size / 2.0)
    coef = np.polynomial.polynomial.polyfit(t, x, deg)
    return x - np.polynomial.polynomial.polyval(t, coef)


def noise_id_lag1_series(
    z: np.ndarray, data_type: str = "freq", dmax: int = 2
) -> tuple[int, float] | None:
    """Identify the power-law noise of one (already averaged or decimated) series.

    Args:
        z: for ``data_type="freq"`` the non-overlapping m-sample averages of the rate; for
            ``"phase"`` the phase decimated by m.
        data_type: ``"freq"`` (rate) or ``"phase"``.
        dmax: largest number of differencings: 2 for Allan-type, 3 for Hadamard.

    Returns:
        ``(alpha_int, alpha_float)`` with alpha the rate-PSD exponent, or ``None`` when the series
        has fewer than ``LAG1_MIN_POINTS`` points. Freq data are first detrended (linear),
        phase data quadratically, then differenced until ``rho = r1 / (1 + r1) < 0.25``.
    """
    z = np.asarray(z, dtype=np.float64)
    if z.size < LAG1_MIN_POINTS:
        return None
    z = _detrend(z, 2 if data_type == "phase" else 1)
    shift = 2 if data_type == "phase" else 0
    d = 0
    while True:
        r1 = lag1_acf(z)
        rho = r1 / (1.0 + r1) if r1 != -1.0 else -0.5
        if rho < 0.25 or d >= dmax or z.size < 3:
            alpha_f = -2.0 * (rho + d) + shift
            alpha_i = int(-round(2.0 * rho) - 2 * d) + shift
            return alpha_i, alpha_f
        z = np.diff(z)
        d += 1


# Allan-variance tau exponents mu tried by the B1 test, and the alpha each stands for (mu = -2
# covers white and flicker phase noise, which R(n) separates).
_B1_MUS = (-2, -1, 0, 1, 2)
_WHITE_FM_RN = 0.5  # MVAR / AVAR of white rate noise for m >> 1
RN_FROM_MU = -2


def b1_theory(n: float, mu: int) -> float:
    """Expected B1 ratio (standard variance / Allan variance) of ``n`` adjacent averages for
    Allan-variance tau exponent ``mu`` (Howe et al. 2000, table 3)."""
    n = float(n)
    if mu == -2:
        return (n * n - 1.0) / (1.5 * n * (n - 1.0))
    if mu == 0:
        return n * math.log(n) / (2.0 * (n - 1.0) * math.log(2.0))
    return n * (1.0 - n**mu) / (2.0 * (n - 1.0) * (1.0 - 2.0**mu))


def rn_theory_flicker_pm(m: int) -> float:
    """Expected R(n) = MVAR / AVAR of flicker phase noise at averaging factor ``m``, with the
    measurement bandwidth at the Nyquist frequency (NIST SP 1065 table 6 expressions)."""
    avar = (1.038 + 3.0 * math.log(math.pi * m)) / (4.0 * math.pi**2)
    mvar = 3.0 * math.log(256.0 / 27.0) / (8.0 * math.pi**2)
    return mvar / avar


def noise_id_b1_rn(
    z: np.ndarray, n_terms: int, m: int, rn: Callable[[], float]
) -> int | None:
    """Noise exponent alpha from few averages: the B1 ratio, then R(n) for phase noise.

    Args:
        z: the non-overlapping m-sample averages of the rate (at least 3).
        n_terms: number of terms of the statistic being reported at this m (its "#" column in
            Stable32): the B1 expectation is evaluated there, as Stable32 does.
        m: averaging factor.
        rn: returns the measured MVAR / (overlapping) AVAR at ``m``; called only when B1 points
            to phase noise.

    The measured B1 is the sample variance of ``z`` over its non-overlapping Allan variance;
    the noise type is the one whose expectation is nearest on a log scale (boundaries at the
    geometric means). When that is phase noise, R(n) is compared the same way with its
    expectations for white phase (1/m), flicker phase and white rate noise (1/2).

    Returns:
        integer alpha, or ``None`` when ``z`` is too short or constant.
    """
    z = np.asarray(z, dtype=np.float64)
    if z.size < 3 or n_terms < 2:
        return None
    avar = 0.5 * float(np.mean(np.diff(z) ** 2))
    if not avar > 0.0:
        return None
    b1 = float(np.var(z, ddof=1)) / avar
    if not b1 > 0.0:
        return None
    expected = np.array([b1_theory(n_terms, mu) for mu in _B1_MUS])
    mu = _B1_MUS[int(np.argmin(np.abs(np.log(b1 / expected))))]
    if mu > RN_FROM_MU:
        return -mu - 1
    ratio = rn()
    if not ratio > 0.0:
        return 2
    candidates = np.array([1.0 / m, rn_theory_flicker_pm(m), _WHITE_FM_RN])
    return (2, 1, 0)[int(np.argmin(np.abs(np.log(ratio / candidates))))]


def noise_id_lag1(
    data: np.ndarray,
    m: np.ndarray,
    data_type: str = "freq",
    dmax: int = 2,
    alpha_range: tuple[int, int] = (-2, 2),
) -> np.ndarray:
    """Lag-1 ACF noise identification at each averaging factor (Riley's method, as Stable32).

    Args:
        data: rate samples (``data_type="freq"``) or phase samples (``"phase"``).
        m: averaging factors.
        data_type: ``"freq"`` or ``"phase"``.
        dmax: largest number of differencings (2 for Allan-type, 3 for Hadamard).
        alpha_range: clip the result to this range (the edf needs ``alpha > 1 - 2 d``).

    Rate data are averaged in non-overlapping groups of ``m``; phase data are decimated by
    ``m``. Where fewer than ``LAG1_MIN_POINTS`` averages exist (the longest taus) the method
    has too few points: the alpha identified at the nearest shorter tau is carried over, and
    ``0`` (white rate noise) is used when no tau could be identified at all.

    Returns:
        integer alpha per entry of ``m`` (int64 array).
    """
    data = np.asarray(data, dtype=np.float64)
    if data_type == "freq":
        u = np.concatenate(([0.0], np.cumsum(data - data.mean())))
    elif data_type == "phase":
        u = data
    else:
        raise ValueError(f"data_type must be 'freq' or 'phase', got {data_type!r}")
    return noise_id_lag1_phase(u, m, data_type, dmax, alpha_range)


_DIFF_CHUNK = 1 << 16  # differences formed at once: stays in cache, no record-sized copy


def _diff_products(v: np.ndarray) -> tuple[float, float]:
    """``(z.z, z[:-1].z[1:])`` of ``z = diff(v)``, forming ``z`` a cache-sized piece at a
    time (``v`` may be a strided view)."""
    n = v.size - 1
    if n <= _DIFF_CHUNK:
        z = np.diff(v)
        return float(np.dot(z, z)), float(np.dot(z[:-1], z[1:]))
    buf = np.empty(_DIFF_CHUNK)
    zz = p = 0.0
    last = None
    for a in range(0, n, _DIFF_CHUNK):
        b = min(n, a + _DIFF_CHUNK)
        z = buf[:b - a]
        np.subtract(v[a + 1:b + 1], v[a:b], out=z)
        zz += float(np.dot(z, z))
        p += float(np.dot(z[:-1], z[1:]))
        if last is not None:
            p += last * float(z[0])
        last = float(z[-1])
    return zz, p


def lag1_acf_detrended_from_phase(v: np.ndarray, points: int | None = None) -> float:
    """Lag-1 autocorrelation of ``z = diff(v)`` after removing its least-squares line.

    Equal to ``lag1_acf(_detrend(diff(v), 1))`` but computed from five reductions (sums,
    dot products) instead of building the detrended series: it is the inner loop of the
    noise identification on long records. ``points``: the length of the phase ``v`` was
    decimated from (default ``v.size``), which decides whether the compiled kernel runs
    (``allan_kernels.enabled``).
    """
    n = v.size - 1
    # the kernel switch goes by the phase ``v`` was decimated from (``points``), so that one
    # record's taus all take the same path
    if allan_kernels.enabled("noise_id", v.size if points is None else points):
        zz, p, s1 = allan_kernels.diff_products(v)  # one pass, also over a strided view
    else:
        zz, p = _diff_products(v)
        s1 = float(np.sum(v[1:]))
    z0, zl = float(v[1] - v[0]), float(v[-1] - v[-2])
    a = float(v[-1] - v[0]) / n  # mean of z
    # sum(k z_k) by parts, then about the centred index t_k = k - (n - 1) / 2
    skz = n * float(v[-1]) - s1
    t_last = (n - 1) / 2.0
    st = n * (n * n - 1) / 12.0  # sum of t_k^2
    tw = skz - t_last * (a * n)  # sum(t_k z_k) = sum(t_k w_k), w = z - a
    b = tw / st
    w0 = z0 - a
    wl = zl - a
    sum_e2 = zz - n * a * a - b * b * st
    if sum_e2 <= 0.0:
        return 0.0
    sw1 = p - a * (2.0 * a * n - z0 - zl) + (n - 1) * a * a
    cross = (tw + t_last * w0 + w0) + (tw - t_last * wl - wl)
    stt = st - t_last * t_last - t_last
    return (sw1 - b * cross + b * b * stt) / sum_e2


def _lag1_differenced(z: np.ndarray, dmax: int) -> tuple[int, float]:
    """``noise_id_lag1_series(z, "freq", dmax)`` for a series whose detrended lag-1 ACF is
    already known to give ``rho >= 0.25``: it goes straight to the differences. Differencing
    turns the removed line into a constant, which the ACF's mean removal takes out, so the
    detrending is skipped; the series is worked on in place (``z`` is consumed)."""
    d = 0
    while True:
        z = np.diff(z)
        d += 1
        z -= z.mean()
        den = float(np.dot(z, z))
        r1 = float(np.dot(z[:-1], z[1:])) / den if den != 0.0 else 0.0
        rho = r1 / (1.0 + r1) if r1 != -1.0 else -0.5
        if rho < 0.25 or d >= dmax or z.size < 3:
            return int(-round(2.0 * rho) - 2 * d), -2.0 * (rho + d)


def noise_id_lag1_phase(
    u: np.ndarray,
    m: np.ndarray,
    data_type: str = "freq",
    dmax: int = 2,
    alpha_range: tuple[int, int] = (-2, 2),
) -> np.ndarray:
    """As ``noise_id_lag1`` but from the phase ``u`` (for rate data: the running sum of the
    rate, so the m-sample averages are ``diff(u[::m]) / m``)."""
    m = np.asarray(m, dtype=np.int64)
    out = np.empty(m.size, dtype=np.int64)
    last = None
    for idx in np.argsort(m, kind="stable"):
        mi = int(m[idx])
        res = None
        if data_type == "freq":
            v = u[::mi]
            if v.size - 1 >= LAG1_MIN_POINTS:
                r1 = lag1_acf_detrended_from_phase(v, u.size)
                rho = r1 / (1.0 + r1) if r1 != -1.0 else -0.5
                if rho < 0.25 or dmax == 0:
                    res = (int(-round(2.0 * rho)), -2.0 * rho)
                else:
                    res = _lag1_differenced(np.diff(v), dmax)
        else:
            res = noise_id_lag1_series(u[::mi], data_type, dmax)
        if res is not None:
            last = res[0]
        out[idx] = last if last is not None else 0
    return np.clip(out, alpha_range[0], alpha_range[1])
