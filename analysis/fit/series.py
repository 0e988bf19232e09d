"""Fitting a rate series: its Allan curve (once), its strongest spectral line, a
temperature regression, then :func:`imunoise.analysis.fit.fit_allan`.
"""

from __future__ import annotations

import math
from collections.abc import Collection, Sequence
from typing import Any

import numpy as np
from scipy import ndimage

from imunoise.analysis.dsp import welch_density
from imunoise.analysis.fit.layout import _fixed_keys
from imunoise.analysis.fit.result import FitResult, ModelLike, TermFit
from imunoise.analysis.fit.solve import _hold, fit_allan
from imunoise.analysis.jobs import JobMap, serial_map
from imunoise.analysis.terms import (
    ModelSpec,
    TermError,
    get_term,
    parse_model,
)

_EXCLUDE_BINS = 8
"""Half-width (Welch bins) around a held line's frequency where :func:`find_line` looks for no
other line: the Hann main lobe (2 bins), the held value's own resolution and a slow wander."""


_FURTHER_LINE_ALPHA = 0.01
"""Chance that a record with no further line shows one anywhere in its spectrum
(:func:`noise_bin_level`)."""

_FURTHER_LINE_SEGMENTS = 16
"""Fewest Welch segments in which :func:`series_lines` looks for a further line."""

_FURTHER_LINE_MIN_SNR = 3.0
"""Least height of a further line above its neighbourhood's median, whatever the average."""


def noise_bin_level(n_samples: int, nper: int, n_bins: int,
                    alpha: float = _FURTHER_LINE_ALPHA) -> float:
    """Height above the neighbourhood's median that no bin of a line-free Welch spectrum
    reaches with probability ``1 - alpha`` over its ``n_bins`` bins: each bin of an average of
    K Hann segments overlapping by half is chi-square over its equivalent degrees of freedom
    ``2 K / (1 + 2 rho^2)`` (``rho = 0.167``, the overlap correlation of the Hann window), and
    the floor it is compared with is that distribution's median. A long record's average so
    resolves a line a few times its floor that a single periodogram cannot tell from noise
    (level 3.0 for 2^19 samples in segments of 2^15). Below ``_FURTHER_LINE_SEGMENTS``
    segments the level is infinite: the floor, a median of 31 bins, is then itself too noisy
    for the chi-square level to hold (over 2^15 samples, one segment, 5 of 20 line-free
    records showed a bin above that level)."""
    from imunoise.analysis.distributions import chi2

    k = 1 + max(n_samples - nper, 0) // max(nper // 2, 1)
    if k < _FURTHER_LINE_SEGMENTS:
        return math.inf
    edf = 2.0 * k / (1.0 + 2.0 * 0.167 ** 2)
    level = float(chi2.isf(alpha / max(n_bins, 1), edf) / chi2.ppf(0.5, edf))
    return max(_FURTHER_LINE_MIN_SNR, level)


def find_line(values: np.ndarray, fs_hz: float, min_snr: float | None = 10.0,
              exclude_hz: Sequence[float] = ()) -> tuple[float, float] | None:
    """Frequency (Hz) and amplitude (units) of the strongest spectral line, or None.

    Welch spectrum (Hann, up to 2^15 samples per segment); the line is the bin standing
    furthest above the running median of its neighbourhood (by at least ``min_snr``, or with
    ``None`` by :func:`noise_bin_level`); its power is the excess summed over the main lobe
    (``A = sqrt(2 P)``). Lines within ``_EXCLUDE_BINS`` bins of a frequency in ``exclude_hz``
    (Hz; lines the model already holds) are passed over."""
    x = np.asarray(values, dtype=np.float64)
    if x.size < 64:
        return None
    nper = int(min(1 << 15, 1 << int(math.log2(x.size))))
    f, p = welch_density(x - x.mean(), fs_hz, nper)
    if p.size < 16:
        return None
    if min_snr is None:
        min_snr = noise_bin_level(x.size, nper, p.size)
    floor = np.maximum(ndimage.median_filter(p, size=31, mode="nearest"), 1e-300)
    ratio = p / floor
    ratio[:4] = 0.0  # the lowest bins carry drift, not lines
    ratio[-4:] = 0.0  # nor does the edge at the Nyquist frequency
    df = f[1] - f[0]
    for f_x in exclude_hz:
        k_x = int(round(float(f_x) / df))
        ratio[max(k_x - _EXCLUDE_BINS, 0):max(k_x + _EXCLUDE_BINS + 1, 0)] = 0.0
    k = int(np.argmax(ratio))
    if ratio[k] < min_snr:
        return None
    lo, hi = max(k - 3, 0), min(k + 4, p.size)
    power = float(np.sum(p[lo:hi] - floor[lo:hi]) * df)
    weights = p[lo:hi] - floor[lo:hi]
    f_line = float(np.sum(f[lo:hi] * weights) / np.sum(weights))
    return f_line, math.sqrt(max(2.0 * power, 0.0))


def regress_temperature(rate: np.ndarray, temperature: np.ndarray, blocks: int = 10
                        ) -> tuple[TermFit, np.ndarray]:
    """Least-squares regression of the rate on temperature (with offset).

    Returns the ``temperature`` term (coef in rate units per degC, 95 % interval) and the
    corrected rate ``rate - coef (temperature - mean temperature)``. The interval comes from
    refitting the coefficient on ``blocks`` contiguous blocks (Student t on their spread),
    which stays honest when the residual noise is coloured, as it is for inertial sensors.
    """
    y = np.asarray(rate, dtype=np.float64)
    t = np.asarray(temperature, dtype=np.float64)
    if y.shape != t.shape:
        raise ValueError(f"temperature record has {t.size} samples, rate {y.size}")
    if not np.all(np.isfinite(t)):
        raise ValueError("temperature record holds non-finite values")
    tc = t - t.mean()
    sxx = float(tc @ tc)
    if sxx <= 0:
        raise ValueError("temperature is constant: its coefficient cannot be estimated")
    coef = float(tc @ (y - y.mean()) / sxx)
    per_block = []
    for yb, tb in zip(np.array_split(y, blocks), np.array_split(t, blocks), strict=True):
        tbc = tb - tb.mean()
        s = float(tbc @ tbc)
        if s > 0:
            per_block.append(float(tbc @ (yb - yb.mean()) / s))
    if len(per_block) >= 3:
        from imunoise.analysis import distributions as dist
        half = float(dist.t.ppf(0.975, len(per_block) - 1) * np.std(per_block, ddof=1)
                     / math.sqrt(len(per_block)))
    else:
        half = math.inf
    term = TermFit("temperature", {"coef": coef}, {"coef": (coef - half, coef + half)})
    return term, y - coef * tc


def series_line(values: np.ndarray, fs_hz: float, segment_starts: np.ndarray | None = None,
                exclude_hz: Sequence[float] = ()) -> tuple[float, float] | None:
    """The strongest spectral line of the longest gap-free segment (:func:`find_line`),
    passing over those at ``exclude_hz``: the start of a line term in :func:`fit_series`."""
    lines = series_lines(values, fs_hz, 1, segment_starts, exclude_hz)
    return lines[0] if lines else None


def series_lines(values: np.ndarray, fs_hz: float, count: int,
                 segment_starts: np.ndarray | None = None, exclude_hz: Sequence[float] = ()
                 ) -> tuple[tuple[float, float], ...]:
    """Up to ``count`` spectral lines of the longest gap-free segment, strongest first, as
    ``(f_hz, amplitude)``: the first by :func:`find_line`'s fixed level, each further one the
    strongest line left once the earlier ones are passed over, at the level a bin of the
    average reaches by chance (:func:`noise_bin_level`). The starts of a model's line terms,
    one line each (:func:`imunoise.analysis.fit.fit_allan`): a model that asks for a second
    line is looking for the spectrum's second line, which on an ADIS16405 accelerometer (the
    bench's 0.56 Hz line's third harmonic at 1.69 Hz) stands 3-7 times its floor, where a
    start on the first line leaves the two terms to share it."""
    x = np.asarray(values, dtype=np.float64)
    bounds = np.append(segment_starts if segment_starts is not None else [0], x.size)
    k = int(np.argmax(np.diff(bounds)))
    seg = x[bounds[k]:bounds[k + 1]]
    found: list[tuple[float, float]] = []
    while len(found) < count:
        level = 10.0 if not found else None
        line = find_line(seg, fs_hz, min_snr=level,
                         exclude_hz=tuple(exclude_hz) + tuple(f for f, _ in found))
        if line is None:
            break
        found.append(line)
    return tuple(found)


def _held_line_frequencies(spec: ModelSpec, fixed: dict[str | int, dict[str, float]] | None,
                           fs_hz: float) -> tuple[float, ...]:
    """Frequencies (Hz) at which the model holds a line term, given in the model text or in
    ``fixed`` (by index or by term name, resolved as the fit resolves them); none when no line
    term has a free frequency (the spectrum's line then only starts the held lines'
    amplitudes)."""
    given: dict[str | int, dict[str, float]] = {i: p for i, p in spec.fixed.items()}
    held = _fixed_keys(spec.names, {**given, **(fixed or {})}, fs_hz)
    lines = [i for i, n in enumerate(spec.names) if get_term(n).role == "line"]
    if all((i, "f") in held for i in lines):
        return ()
    return tuple(sorted(held[(i, "f")] for i in lines if (i, "f") in held))


def _free_line_count(spec: ModelSpec, fixed: dict[str | int, dict[str, float]] | None,
                     fs_hz: float) -> int:
    """How many of the model's line terms have a free frequency."""
    given: dict[str | int, dict[str, float]] = {i: p for i, p in spec.fixed.items()}
    held = _fixed_keys(spec.names, {**given, **(fixed or {})}, fs_hz)
    return sum(1 for i, n in enumerate(spec.names)
               if get_term(n).role == "line" and (i, "f") not in held)


def fit_series(values: np.ndarray, fs_hz: float, model: ModelLike, *,
               segment_starts: np.ndarray | None = None,
               temperature: np.ndarray | None = None,
               fixed: dict[str | int, dict[str, float]] | None = None,
               ci: float = 0.95, start: Any = None, memo: dict | None = None,
               intervals: str = "profile", job_map: JobMap = serial_map,
               profile_terms: Collection[int] | None = None
               ) -> tuple[FitResult, Any]:
    """Fit ``model`` to a rate series: Allan curve (octave taus, computed once), spectral line
    for a sinusoid, temperature regression, then :func:`fit_allan`.

    Args:
        values: rate samples in SI units, all segments concatenated.
        fs_hz: sampling rate, Hz.
        model: a model specification (:func:`imunoise.analysis.terms.parse_model`).
        segment_starts: gap-free segment starts (``ChannelSeries.segment_starts``).
        temperature: temperature in degC at each sample (required with ``temperature``).
        fixed: parameters held at known values (see :func:`fit_allan`).
        ci: confidence level of the curve's ``ci_low``/``ci_high``.
        start: starting point of a refit (see :func:`fit_allan`).
        memo: a dict shared by fits of one series (the diagnosis's candidates): its Allan
            curves, spectral line and nested solutions are computed once. A fit with a memo
            gives exactly the numbers of one without.
        intervals: see :func:`fit_allan` (intervals never change the parameters or chi2).
        job_map: see :func:`fit_allan`.
        profile_terms: see :func:`fit_allan`.

    Returns:
        ``(FitResult, AllanCurve)``; the curve is that of the temperature-corrected series
        when the model holds ``temperature``.
    """
    from imunoise.analysis.allan import oadev

    memo = {} if memo is None else memo
    _hold(memo, values)
    spec = parse_model(model)
    names = spec.names
    x = np.asarray(values, dtype=np.float64)
    temp_term = None
    regressed = any(get_term(n).role == "regressor" for n in names)
    if regressed:
        if temperature is None:
            raise TermError("the temperature term needs a temperature record, and this "
                            "record has none")
        temp_key = ("temperature", id(values), ci)
        if temp_key not in memo:
            memo[temp_key] = regress_temperature(x, np.asarray(temperature, dtype=np.float64))
        temp_term, x = memo[temp_key]
    key = ("curve", id(values), regressed, ci)
    if key not in memo:
        memo[key] = oadev(x, fs_hz, m="octave", segment_starts=segment_starts, ci=ci)
    curve = memo[key]
    line = None
    if any(get_term(n).role == "line" for n in names):
        # A line the model holds at a stated frequency is no start for another line term:
        # two sinusoids started on one line trade its amplitude, and the solve ends with one
        # of them at zero and the next line unmodelled.
        held = _held_line_frequencies(spec, fixed, fs_hz)
        count = max(1, _free_line_count(spec, fixed, fs_hz))
        line_key = ("line", id(values), regressed, held, count)
        if line_key not in memo:
            memo[line_key] = series_lines(x, fs_hz, count, segment_starts, exclude_hz=held)
        line = memo[line_key]
    result = fit_allan(curve, spec, start=start, line=line, temperature=temp_term, fixed=fixed,
                       memo=memo, intervals=intervals, job_map=job_map,
                       profile_terms=profile_terms)
    return result, curve
