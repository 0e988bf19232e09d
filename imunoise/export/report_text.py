"""Readable per-channel tables for the terminal, SI values with conventional units beside them."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from imunoise.core import units
from imunoise.core.series import ChannelSeries

if TYPE_CHECKING:
    from imunoise.analysis.psd import PsdEstimate


def _kind(name: str) -> str | None:
    try:
        return units.channel_kind(name)
    except ValueError:
        return None


def _duration(seconds: float) -> str:
    if seconds >= 3600:
        return f"{seconds / 3600:.2f} h"
    if seconds >= 60:
        return f"{seconds / 60:.1f} min"
    return f"{seconds:.1f} s"


def _level_units(kind: str | None) -> tuple[str, float]:
    """Conventional unit and factor for a rate/acceleration level (bias-like quantity)."""
    if kind is None:
        return "", 1.0
    return units.conventional("B", kind)


def _density_units(kind: str | None) -> tuple[str, float]:
    """Conventional unit and factor for an amplitude spectral density."""
    if kind == "gyro":
        return "deg/h/sqrt(Hz)", float(units.rad_s_rthz_to_deg_h_rthz(1.0))
    if kind == "accel":
        return "ug/sqrt(Hz)", float(units.m_s2_rthz_to_ug_rthz(1.0))
    return "", 1.0


def white_noise_readouts(series: ChannelSeries, allan: Any | None,
                         psd: PsdEstimate | None) -> list[tuple[str, float]]:
    """Quick white-noise density read-outs N in SI units (channel units/sqrt(Hz)).

    From the Allan deviation at tau = 1 s (log-log interpolated; valid where white noise
    dominates there) and from the PSD's top (Welch) band, N = sqrt(median S / 2) for the
    one-sided S.
    """
    out = []
    if allan is not None and len(allan.tau_s) >= 2 and allan.tau_s[0] <= 1.0 <= allan.tau_s[-1]:
        adev1 = float(np.exp(np.interp(0.0, np.log(allan.tau_s), np.log(allan.dev))))
        out.append(("ADEV(1 s)", adev1))
    if psd is not None and len(psd):
        top = psd.method == "welch"
        if np.any(top):
            out.append(("PSD top band", float(np.sqrt(np.median(psd.psd[top]) / 2.0))))
    return out


def channel_text(key: str, series: ChannelSeries, allan: Any | None, psd: PsdEstimate | None,
                 warnings: list[str] | None = None) -> str:
    """A block of text describing one analysed channel."""
    kind = _kind(key)
    u = series.units
    lines = [f"{key}  [{u}]  fs {series.fs_hz:g} Hz  {series.n_samples:,} samples  "
             f"{_duration(series.duration_s)}  {len(series.segment_starts)} segment(s)"]
    conv, factor = _level_units(kind)
    if allan is not None and len(allan.tau_s):
        ci = getattr(allan, "ci", 0.95)
        lines.append(f"  Allan deviation ({ci * 100:.0f} % interval)")
        head = f"    {'tau [s]':>10}  {'adev [' + u + ']':>14}  {'low':>10}  {'high':>10}"
        if conv:
            head += f"  {'adev [' + conv + ']':>14}"
        lines.append(head)
        for tau, d, lo, hi in zip(allan.tau_s, allan.dev, allan.ci_low, allan.ci_high,
                                  strict=True):
            row = f"    {tau:10.4g}  {d:14.4g}  {lo:10.4g}  {hi:10.4g}"
            if conv:
                row += f"  {d * factor:14.4g}"
            lines.append(row)
    if psd is not None and len(psd):
        dconv, dfactor = _density_units(kind)
        lines.append(f"  PSD, one-sided ({psd.ci * 100:.0f} % interval), "
                     f"{psd.f_hz[0]:.3g} .. {psd.f_hz[-1]:.3g} Hz, {len(psd)} points")
        amp = f"sqrt(PSD) [{u}/sqrt(Hz)]"
        head = f"    {'f [Hz]':>10}  {amp:>26}  {'low':>10}  {'high':>10}"
        if dconv:
            head += f"  {'[' + dconv + ']':>18}"
        lines.append(head)
        decades = 10.0 ** np.arange(np.ceil(np.log10(psd.f_hz[0])),
                                    np.floor(np.log10(psd.f_hz[-1])) + 1)
        picks = sorted({int(np.argmin(np.abs(np.log(psd.f_hz / f)))) for f in decades}
                       | {len(psd) - 1})
        for i in picks:
            a = np.sqrt(psd.psd[i])
            row = (f"    {psd.f_hz[i]:10.4g}  {a:26.4g}  {np.sqrt(psd.ci_low[i]):10.4g}  "
                   f"{np.sqrt(psd.ci_high[i]):10.4g}")
            if dconv:
                row += f"  {a * dfactor:18.4g}"
            lines.append(row)
    if kind is not None:
        n_conv, n_factor = units.conventional("N", kind)
        n_si = units.si_unit("N", kind)
        for label, value in white_noise_readouts(series, allan, psd):
            lines.append(f"  N from {label}: {value:.4g} {n_si} = {value * n_factor:.4g} "
                         f"{n_conv}")
    for w in warnings or []:
        lines.append(f"  warning: {w}")
    return "\n".join(lines)
