"""Narrow spectral lines above the local PSD continuum (sinusoids, mains pickup).

The PSD is a Welch average of ``K`` non-overlapping Hann-windowed, linearly detrended
segments. For Gaussian noise each bin is then ``S(f) * chi2(nu) / nu`` with ``nu = 2 K``
degrees of freedom. The continuum under each bin is estimated from its neighbours (a
quadratic in log-power versus log-frequency, fitted to ``2 W`` bins on either side of a guard
band), and the bin-to-continuum ratio is compared with the F distribution of that ratio. The
single-bin p-value is corrected for the number of bins searched (Sidak), so that a record of
pure noise shows no line with probability ``1 - alpha``.

A local quadratic cannot follow every shape a sensor's spectrum has: the zeros of a
moving-average output filter are V-shaped notches whose bottom the Hann window's leakage
fills, so the bins there stand far above a continuum fitted to the notch's walls. When the
fitted noise model is known, its own PSD is put through the same continuum fit, and bins where
the model departs from its continuum by more than :data:`MODEL_SHAPE_TOLERANCE` are not
searched: there the model, not a line, explains the shape.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import special

from imunoise.analysis import distributions as dist
from imunoise.analysis.dsp import detrend_linear, hann
from imunoise.analysis.evidence.finding import Finding, family_p

_MAINS_HZ = (50.0, 60.0)
_HALF_WINDOW = 12      # neighbour bins on each side used for the continuum
LOBE_HALF_WIDTH = 2
"""Bins on either side of a line's peak that its power spreads over (the Hann main lobe): left
out of the continuum under it, summed for its power."""
_MIN_SEGMENTS = 16
HANN_NEIGHBOUR_INFLATION = 1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0)
"""Powers in adjacent Hann bins correlate by |2/3|^2 (next-but-one: |1/6|^2), so a sum or fit
over neighbouring bins is noisier than one over independent bins by this factor."""
EXCLUDE_HALF_WIDTH = 4
"""Bins on either side of a line the model holds that a search for a further line leaves out:
the Hann main lobe (2 bins) and the held frequency's own resolution."""
MODEL_SHAPE_TOLERANCE = 1.25
"""Largest ratio (either way) between the model's PSD and its own local continuum at a bin that
is still searched; 1.25 is well below the smallest line the test resolves at its dof."""


@dataclass
class WelchBins:
    """Welch PSD of non-overlapping Hann segments with exact chi-square dof.

    Attributes:
        f_hz: bin frequencies in Hz.
        psd: one-sided PSD in units^2/Hz.
        nu: degrees of freedom of every bin (``2 * n_segments``).
        df_hz: bin spacing in Hz.
        enbw_hz: equivalent noise bandwidth of one bin (1.5 bins for Hann).
    """

    f_hz: np.ndarray
    psd: np.ndarray
    nu: int
    df_hz: float
    enbw_hz: float


def welch_bins(segments: list[np.ndarray], fs_hz: float, nperseg: int | None = None) -> WelchBins:
    """Welch PSD over all gap-free ``segments`` (no segment crosses a gap).

    ``nperseg`` defaults to the largest power of two giving at least 16 segments.
    """
    total = sum(len(s) for s in segments)
    if nperseg is None:
        nperseg = 1 << max(int(np.floor(np.log2(max(total // _MIN_SEGMENTS, 16)))), 4)
        while nperseg > 16 and sum(len(s) // nperseg for s in segments) < _MIN_SEGMENTS:
            nperseg //= 2
    blocks = [s[: (len(s) // nperseg) * nperseg].reshape(-1, nperseg) for s in segments
              if len(s) >= nperseg]
    if not blocks:
        raise ValueError(f"no gap-free segment of {nperseg} samples for a spectrum")
    x = np.concatenate(blocks, axis=0)
    x = detrend_linear(x, axis=1)
    w = hann(nperseg)
    spec = np.abs(np.fft.rfft(x * w, axis=1)) ** 2
    psd = spec.mean(axis=0) * 2.0 / (fs_hz * np.sum(w**2))
    psd[0] /= 2.0
    if nperseg % 2 == 0:
        psd[-1] /= 2.0
    df = fs_hz / nperseg
    enbw = df * nperseg * np.sum(w**2) / np.sum(w) ** 2
    return WelchBins(np.fft.rfftfreq(nperseg, 1.0 / fs_hz), psd, 2 * x.shape[0], df, enbw)


def continuum(logp: np.ndarray, logf: np.ndarray,
               nu: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Continuum PSD under each testable bin, its degrees of freedom, and the bins' indices.

    A quadratic in (log f, log P) is fitted by least squares to the neighbours of every bin;
    the mean of log(chi2(nu)/nu) is removed so the result estimates the PSD itself. The
    continuum's own scatter is expressed as equivalent chi-square degrees of freedom from the
    variance of the fitted intercept, inflated for the correlation of neighbouring Hann bins.
    """
    n = logp.size
    k0 = 2 * (_HALF_WINDOW + LOBE_HALF_WIDTH)
    idx = np.arange(k0, n - _HALF_WINDOW - LOBE_HALF_WIDTH - 1)
    if idx.size == 0:
        return idx.astype(float), idx.astype(float), idx
    offs = np.concatenate((np.arange(-LOBE_HALF_WIDTH - _HALF_WINDOW, -LOBE_HALF_WIDTH),
                           np.arange(LOBE_HALF_WIDTH + 1, LOBE_HALF_WIDTH + _HALF_WINDOW + 1)))
    nb = idx[:, None] + offs[None, :]
    u = logf[nb] - logf[idx][:, None]
    y = logp[nb]
    # Normal equations of a per-row quadratic fit, evaluated at u = 0 (the intercept).
    s0 = np.full(idx.size, float(offs.size))
    s1, s2, s3, s4 = (np.sum(u**p, axis=1) for p in (1, 2, 3, 4))
    t0, t1, t2 = np.sum(y, axis=1), np.sum(y * u, axis=1), np.sum(y * u**2, axis=1)
    a = np.stack([np.stack([s0, s1, s2], -1), np.stack([s1, s2, s3], -1),
                  np.stack([s2, s3, s4], -1)], -2)
    rhs = np.stack([t0, t1, t2], -1)[..., None]
    coef = np.linalg.solve(a, rhs)[..., 0]
    a00 = np.linalg.inv(a)[:, 0, 0]
    log_bias = special.digamma(nu / 2.0) - np.log(nu / 2.0)
    var_log = special.polygamma(1, nu / 2.0) * a00 * HANN_NEIGHBOUR_INFLATION
    return np.exp(coef[:, 0] - log_bias), 2.0 / var_log, idx


@dataclass(frozen=True)
class LineSpectrum:
    """The Welch bins a line search and a line's power are read from, with the continuum
    under each testable bin (:func:`continuum`).

    Attributes:
        bins: the Welch estimate.
        logf: natural log of each bin's frequency (the DC bin's floored at a thousandth of
            a bin).
        psd: the bins' PSD floored at the smallest positive float, units^2/Hz.
        logp: its natural log.
        cont: continuum PSD under each bin of ``idx``, units^2/Hz.
        cont_dof: its equivalent chi-square degrees of freedom.
        idx: the bins that have a continuum.
    """

    bins: WelchBins
    logf: np.ndarray
    psd: np.ndarray
    logp: np.ndarray
    cont: np.ndarray
    cont_dof: np.ndarray
    idx: np.ndarray


def line_spectrum(segments: list[np.ndarray], fs_hz: float,
                  nperseg: int | None = None) -> LineSpectrum:
    """The Welch bins of ``segments`` (:func:`welch_bins`) and their continuum, computed once
    for the line search and the held lines' powers."""
    wb = welch_bins(segments, fs_hz, nperseg)
    logf = np.log(np.maximum(wb.f_hz, wb.df_hz * 1e-3))
    psd = np.maximum(wb.psd, np.finfo(float).tiny)
    logp = np.log(psd)
    cont, cont_dof, idx = continuum(logp, logf, wb.nu)
    return LineSpectrum(wb, logf, psd, logp, cont, cont_dof, idx)


def lobe_power(psd: np.ndarray, cont: float, k: int, df_hz: float) -> float:
    """A line's power (units^2): the PSD above the continuum ``cont`` (units^2/Hz) summed
    over the Hann main lobe around its peak bin ``k``; a sinusoid of amplitude ``A`` gives
    ``A^2 / 2``."""
    lobe = psd[k - LOBE_HALF_WIDTH:k + LOBE_HALF_WIDTH + 1]
    return float(np.sum(np.maximum(lobe - cont, 0.0)) * df_hz)


def _mains_label(f: float, tol_hz: float, fs_hz: float) -> str:
    for base in _MAINS_HZ:
        h = int(round(f / base))
        if h >= 1 and abs(f - h * base) <= tol_hz:
            return f"{base:g} Hz mains" if h == 1 else f"harmonic {h} of {base:g} Hz mains"
        # Mains above Nyquist folds back into the band.
        for k in range(1, 6):
            alias = abs(k * base - fs_hz * round(k * base / fs_hz))
            if k * base > fs_hz / 2 and abs(f - alias) <= tol_hz:
                return f"{base:g} Hz mains harmonic {k} aliased"
    return ""


def _model_shape_ok(model_psd: Callable[[np.ndarray], np.ndarray], wb: WelchBins,
                    logf: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Bins (of ``idx``) where the model's PSD is one the local continuum can follow."""
    expected = np.asarray(model_psd(wb.f_hz), dtype=np.float64)
    if expected.shape != wb.f_hz.shape:
        raise ValueError(f"model PSD has shape {expected.shape}, the bins {wb.f_hz.shape}")
    tiny = np.finfo(float).tiny
    # A model that diverges at 0 Hz (random walk) is infinite in the bins below the first one
    # searched; any bin whose continuum would rest on such a value is not searched either.
    log_model = np.log(np.maximum(np.where(np.isfinite(expected), expected, np.nan), tiny))
    # A noiseless "estimate": the same fit with (practically) infinite dof has no bias term.
    cont, _, _ = continuum(log_model, logf, 1 << 40)
    with np.errstate(invalid="ignore"):
        dev = np.abs(log_model[idx] - np.log(np.maximum(cont, tiny)))
        return dev <= np.log(MODEL_SHAPE_TOLERANCE)


def spectral_lines(segments: list[np.ndarray], fs_hz: float, alpha: float = 0.05,
                   units: str = "rad/s", nperseg: int | None = None,
                   max_lines: int = 10,
                   model_psd: Callable[[np.ndarray], np.ndarray] | None = None,
                   exclude_hz: Sequence[float] = (),
                   spectrum: LineSpectrum | None = None) -> Finding:
    """Search the spectrum for narrow lines.

    Args:
        segments: gap-free pieces of one channel (SI units, e.g. rad/s).
        fs_hz: sampling rate in Hz.
        alpha: family-wise significance level over all bins searched.
        units: units of the samples, for the explanation.
        nperseg: Welch segment length (default: see :func:`welch_bins`).
        max_lines: most lines listed in ``details["lines"]``.
        model_psd: the fitted noise model's one-sided PSD (units^2/Hz) as a function of
            frequency (Hz); bins where its shape is one the continuum cannot follow (a
            filter's notch) are left out of the search and reported in
            ``details["bins_skipped"]``.
        exclude_hz: frequencies (Hz) of lines the model already holds; bins within
            :data:`EXCLUDE_HALF_WIDTH` bins (or 1 % of the frequency, if wider) of them are
            not searched, so the finding is about a further line.
        spectrum: the bins and continuum of :func:`line_spectrum`, where the caller has
            them already (``segments`` and ``nperseg`` are then not read).

    Returns:
        A :class:`Finding` of kind ``"spectral_line"`` whose params are the strongest line's
        frequency ``f`` (Hz, interpolated between bins) and amplitude ``A`` (peak, units of
        the samples, from the integrated excess power ``A^2/2``). ``details["lines"]`` lists
        every significant line, strongest first, with its mains label if it is one.
    """
    spec = line_spectrum(segments, fs_hz, nperseg) if spectrum is None else spectrum
    wb, logf, psd, logp = spec.bins, spec.logf, spec.psd, spec.logp
    cont, d2, idx = spec.cont, spec.cont_dof, spec.idx
    skipped = 0
    if model_psd is not None and idx.size:
        keep = _model_shape_ok(model_psd, wb, logf, idx)
        skipped = int(idx.size - np.count_nonzero(keep))
        cont, d2, idx = cont[keep], d2[keep], idx[keep]
    if len(exclude_hz) and idx.size:
        f_idx = wb.f_hz[idx]
        keep = np.ones(idx.size, dtype=bool)
        for f_x in exclude_hz:
            half = max(EXCLUDE_HALF_WIDTH * wb.df_hz, 0.01 * float(f_x))
            keep &= np.abs(f_idx - float(f_x)) > half
        cont, d2, idx = cont[keep], d2[keep], idx[keep]
    if idx.size == 0:
        return Finding("spectral_line", "sinusoid", 0.0, "F", 1.0, alpha,
                       why="record too short to search the spectrum for lines")
    ratio = psd[idx] / cont
    p_single = dist.f.sf(ratio, wb.nu, d2)
    m = idx.size
    # Local maxima only: a line also raises its Hann neighbours (compared with the bins
    # themselves, searched or not).
    local = (psd[idx] >= psd[idx - 1]) & (psd[idx] > psd[idx + 1])
    p_fam = -np.expm1(m * np.log1p(-np.minimum(p_single, 1 - 1e-16)))
    cand = np.flatnonzero(local & (p_fam < alpha))
    cand = cand[np.argsort(p_single[cand])]
    lines = []
    for j in cand[:max_lines]:
        k = idx[j]
        # Gaussian (log-parabolic) interpolation of the peak, exact for a Gaussian-shaped lobe.
        la, lb, lc = logp[k - 1], logp[k], logp[k + 1]
        denom = la - 2 * lb + lc
        delta = 0.5 * (la - lc) / denom if denom < 0 else 0.0
        f = float((k + np.clip(delta, -0.5, 0.5)) * wb.df_hz)
        amp = float(np.sqrt(2.0 * lobe_power(psd, float(cont[j]), k, wb.df_hz)))
        lines.append({"f_hz": f, "A": amp, "ratio": float(ratio[j]),
                      "p_value": float(p_fam[j]),
                      "mains": _mains_label(f, max(2 * wb.df_hz, 0.2), fs_hz)})
    # The finding's strength is that of the best local maximum: a bin on a slope (the edge of
    # a filter's notch) is not a line, however far it stands from the continuum fit.
    if np.any(local):
        jbest = int(np.flatnonzero(local)[np.argmin(p_single[local])])
        p_best = family_p(float(p_single[jbest]), m)
    else:
        jbest, p_best = int(np.argmin(p_single)), 1.0
    f_lo, f_hi = float(wb.f_hz[idx[0]]), float(wb.f_hz[idx[-1]])
    details = {"lines": lines, "bins_searched": int(m), "bins_skipped": skipped,
               "nu": int(wb.nu),
               "df_hz": float(wb.df_hz), "f_searched_hz": [f_lo, f_hi]}
    if lines:
        top = lines[0]
        tag = f" ({top['mains']})" if top["mains"] else ""
        why = (f"The PSD has a narrow line at {top['f_hz']:.4g} Hz{tag}, {top['ratio']:.1f} times "
               f"the surrounding noise floor: a sinusoid of amplitude {top['A']:.3g} {units} "
               f"(vibration, a pump or fan, or electrical pickup); in the Allan deviation it "
               f"shows as a bump near tau = {0.37 / top['f_hz']:.3g} s.")
        if len(lines) > 1:
            why += f" {len(lines) - 1} further line(s) found."
        params = {"A": top["A"], "f": top["f_hz"]}
        rng = {"f_hz": [top["f_hz"] - wb.df_hz, top["f_hz"] + wb.df_hz]}
        # Interpolated peak: within a quarter bin for a line well above the floor.
        details["ci95"] = {"f": (top["f_hz"] - 0.5 * wb.df_hz, top["f_hz"] + 0.5 * wb.df_hz)}
    else:
        why = (f"No spectral line stands out of the noise floor between {f_lo:.3g} and "
               f"{f_hi:.3g} Hz.")
        params, rng = {}, {"f_hz": [f_lo, f_hi]}
    return Finding("spectral_line", "sinusoid", float(ratio[jbest]), "PSD / continuum",
                   p_best, alpha, params, rng, why, details)
