"""Whether each line the model holds has the power the spectrum gives it.

The Allan curve sees a sinusoid as a hump near ``tau = 0.37 / f``. Two lines whose
frequencies differ by a few tens of per cent put their humps on the same octave points, so a
fit that holds one of them gives it the power of both. The spectrum resolves them. Each
sinusoid of the fitted model is compared with the spectrum at its frequency:

- the spectrum's amplitude ``A_s = sqrt(2 E)``, ``E`` the power above the local continuum
  over the Hann main lobe around the line's peak bin (the estimate of
  :func:`imunoise.analysis.evidence.lines.spectral_lines`);
- its variance: a bin holding a deterministic line of power ``L`` over Gaussian noise of
  level ``C`` has, averaged over ``K = nu / 2`` segments, variance ``(C^2 + 2 C L) / K``
  (``|N + s|^2`` with ``E|N|^2 = C``). Summed over the lobe, the noise's part is inflated by
  the Hann neighbours' power correlation (``1 + 2 (4/9 + 1/36)``), the cross term's by their
  amplitude correlation (``1 + 2 (2/3 + 1/6)``), and the continuum's own scatter (its
  equivalent degrees of freedom) is added for the five bins it is taken from. On 60 simulated
  records (a 2e-4 line at 0.55 Hz over white noise, flicker and random walk, 2 h at 50 Hz)
  the spectrum's amplitude has no bias, its log-error spread is 0.99 of the stated one (1.15
  with the power correlation alone) and 56 of the 60 intervals cover the truth;
- the fitted amplitude's standard error from its 95 % interval.

The two are compared on the log scale, ``z = (ln A_fit - ln A_s) / sqrt(se_fit^2 + se_s^2)``,
two-sided, Bonferroni over the lines compared. A line is compared only where both amplitudes
are resolved (the spectrum's power more than two of its standard deviations above zero, the
fit's interval clear of zero). Where the fit exceeds the spectrum, the significant lines the
model lacks within :data:`NEIGHBOUR_RATIO` of its frequency are named: their power is what
the fitted line carries beside its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from imunoise.analysis.distributions import norm
from imunoise.analysis.evidence.finding import Finding
from imunoise.analysis.evidence.lines import (
    HANN_NEIGHBOUR_INFLATION,
    LOBE_HALF_WIDTH,
    LineSpectrum,
    line_spectrum,
    lobe_power,
)

_Z95 = 1.959963984540054

HANN_AMPLITUDE_INFLATION = 1.0 + 2.0 * (2.0 / 3.0 + 1.0 / 6.0)
"""The cross term of a line and the noise is linear in the noise, so neighbouring Hann bins
share it by the amplitude correlation (2/3, next-but-one 1/6), not the power's."""

NEIGHBOUR_RATIO = 1.5
"""Lines within this factor in frequency of a held one share its octave Allan points (their
humps peak within about half an octave of each other)."""


def _spectral_amplitude(psd: np.ndarray, cont: float, cont_dof: float, k: int, nu: int,
                        df_hz: float) -> tuple[float, float]:
    """``(E, sd of E)``: the line's power above the continuum ``cont`` over the main lobe
    around bin ``k`` (units^2) and its standard deviation."""
    lobe = psd[k - LOBE_HALF_WIDTH:k + LOBE_HALF_WIDTH + 1]
    excess = lobe_power(psd, cont, k, df_hz)
    line = np.maximum(lobe - cont, 0.0)
    var_noise = lobe.size * cont * cont * 2.0 / nu * HANN_NEIGHBOUR_INFLATION
    var_cross = float(np.sum(2.0 * cont * line)) * 2.0 / nu * HANN_AMPLITUDE_INFLATION
    var_cont = lobe.size ** 2 * cont * cont * 2.0 / cont_dof
    sd = math.sqrt(var_noise + var_cross + var_cont) * df_hz
    return excess, sd


def line_powers(segments: list[np.ndarray], fs_hz: float,
                lines: Sequence[tuple[str, float, float, tuple[float, float] | None]],
                alpha: float = 0.05, units: str = "rad/s", nperseg: int | None = None,
                found: Sequence[dict[str, Any]] = (),
                spectrum: LineSpectrum | None = None) -> Finding:
    """Compare each held line's fitted amplitude with the spectrum's (see the module text).

    Args:
        segments: gap-free pieces of one channel (SI units).
        fs_hz: sampling rate, Hz.
        lines: the model's sinusoids as ``(label, f_hz, A, A's 95 % interval or None)``,
            amplitudes peak, in the samples' units.
        alpha: family-wise level over the lines compared.
        units: the samples' units, for the explanation.
        nperseg: Welch segment length (default that of
            :func:`~imunoise.analysis.evidence.lines.welch_bins`).
        found: the significant lines of the spectrum the model does not hold
            (``details["lines"]`` of :func:`~imunoise.analysis.evidence.lines.spectral_lines`:
            ``f_hz`` and ``A``), named as the neighbours a fitted line carries.
        spectrum: the bins and continuum of
            :func:`~imunoise.analysis.evidence.lines.line_spectrum`, where the caller has
            them already (``segments`` and ``nperseg`` are then not read).

    Returns:
        A :class:`Finding` of kind ``"line_power"`` (term ``sinusoid``): the largest |z|, its
        Bonferroni p-value; ``params`` the worst line's ``f``, ``A_fit`` and ``A_spectrum``;
        ``details["lines"]`` every line compared with both amplitudes, the spectrum's 95 %
        interval, ``z`` and the neighbours named.
    """
    spec = line_spectrum(segments, fs_hz, nperseg) if spectrum is None else spectrum
    wb, psd, cont, cont_dof, idx = spec.bins, spec.psd, spec.cont, spec.cont_dof, spec.idx
    compared: list[dict[str, Any]] = []
    for label, f_hz, a_fit, ci in lines:
        if ci is None or not (ci[0] > 0.0 and ci[1] > ci[0] and a_fit > 0.0):
            continue  # the fit does not resolve the amplitude: nothing to compare
        k0 = int(round(f_hz / wb.df_hz))
        lo, hi = k0 - LOBE_HALF_WIDTH, k0 + LOBE_HALF_WIDTH + 1
        if lo < 0 or hi > psd.size:
            continue
        k = lo + int(np.argmax(psd[lo:hi]))
        j = int(np.searchsorted(idx, k))
        if j >= idx.size or idx[j] != k:
            continue  # too near either end of the spectrum for a continuum
        excess, sd = _spectral_amplitude(psd, float(cont[j]), float(cont_dof[j]), k, wb.nu,
                                         wb.df_hz)
        if excess <= 2.0 * sd:
            continue  # the spectrum does not resolve the line's power
        a_spec = math.sqrt(2.0 * excess)
        se_spec = 0.5 * sd / excess
        se_fit = (math.log(ci[1]) - math.log(ci[0])) / (2.0 * _Z95)
        z = (math.log(a_fit) - math.log(a_spec)) / math.hypot(se_fit, se_spec)
        neighbours = [{"f_hz": float(n["f_hz"]), "A": float(n["A"])} for n in found
                      if abs(math.log(float(n["f_hz"]) / f_hz)) < math.log(NEIGHBOUR_RATIO)
                      and abs(float(n["f_hz"]) - f_hz) > LOBE_HALF_WIDTH * wb.df_hz]
        compared.append({"term": label, "f_hz": float(f_hz), "A_fit": float(a_fit),
                         "A_spectrum": a_spec,
                         "A_spectrum_ci95": [a_spec * math.exp(-_Z95 * se_spec),
                                             a_spec * math.exp(_Z95 * se_spec)],
                         "z": z, "neighbours": neighbours if z > 0 else []})
    if not compared:
        return Finding("line_power", "sinusoid", 0.0, "|z|", 1.0, alpha,
                       why="no line of the model resolved both in the fit and in the spectrum")
    m = len(compared)
    worst = max(compared, key=lambda c: abs(c["z"]))
    p = min(1.0, 2.0 * m * float(norm.sf(abs(worst["z"]))))
    details = {"lines": compared, "nu": int(wb.nu), "df_hz": float(wb.df_hz)}
    params = {"f": worst["f_hz"], "A_fit": worst["A_fit"], "A_spectrum": worst["A_spectrum"]}
    rng = {"f_hz": [worst["f_hz"] - wb.df_hz, worst["f_hz"] + wb.df_hz]}
    lo, hi = worst["A_spectrum_ci95"]
    what = (f"The {worst['f_hz']:.4g} Hz line is fitted at {worst['A_fit']:.3g} {units}; the "
            f"spectrum gives it {worst['A_spectrum']:.3g} [{lo:.3g}, {hi:.3g}] {units} "
            f"(z {worst['z']:+.1f}).")
    if p >= alpha:
        why = (f"Each line of the model has the power the spectrum gives it (largest |z| "
               f"{abs(worst['z']):.2g}, p = {p:.2g} over {m}).")
    elif worst["z"] > 0 and worst["neighbours"]:
        names = "; ".join(f"{n['f_hz']:.4g} Hz, {n['A']:.3g} {units}"
                          for n in worst["neighbours"])
        one = len(worst["neighbours"]) == 1
        lines_named, whose = ("line", "that line's") if one else ("lines", "their")
        why = (what + f" The Allan curve cannot tell it from the {lines_named} beside it that "
               f"the model lacks ({names}): the fit gives it {whose} power too.")
    elif worst["z"] > 0:
        why = what + (" The fitted line takes power the spectrum puts elsewhere (a broader "
                      "feature near it, or lines the search did not resolve).")
    else:
        why = what + (" The fit gives the line less power than the spectrum: another term "
                      "takes part of it on the Allan curve.")
    return Finding("line_power", "sinusoid", abs(worst["z"]), "|z| (log amplitude)", p, alpha,
                   params, rng, why, details)
