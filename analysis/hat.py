"""Several sensors of one kind on one bench: each one's own noise.

Three sensors (the three-cornered hat; J. E. Gray and D. W. Allan, "A method for estimating the
frequency stability of an individual oscillator", Proc. 28th Frequency Control Symposium,
1974): the difference of two sensors' outputs cancels what the bench does to both, so its
Allan variance is the sum of their own ones, ``s_ij = s_i + s_j`` (own noises independent).
Three pairs give each sensor's own variance,

    ``s_i = (s_ij + s_ik - s_jk) / 2``.

Interval: each pair's estimate is chi-square with ``nu`` equivalent degrees of freedom
(:func:`imunoise.analysis.allan.allan`'s edf of the difference series); pairs sharing sensor
``i`` covary by ``2 s_i^2 / nu``. Then

    ``Var(s_i_hat) = (2 s_i^2 + s_i s_j + s_i s_k + s_j s_k) / nu``,

and the estimate is taken as scaled chi-square with Satterthwaite's ``nu_i = 2 s_i^2 / Var``
(plug-in values; ``nu`` the smallest of the three pairs'). The estimate can come out negative
when one sensor is far quieter than the others; it then has an upper bound only (its value
clipped at 0 plus 1.96 standard deviations at the 95 % level).

Two sensors (:func:`two_sensor_bounds`): the cross-spectrum bounds the common part. With
``a = c_a + e_a``, ``b = c_b + e_b`` and the common parts fully coherent,
``|S_ab|^2 / S_bb <= S_{c_a}``: at least this much of ``a``'s PSD is common, so ``a``'s own PSD
is at most ``S_aa (1 - C_ab)``; if the bench reaches both sensors with the same gain,
``S_ab`` is the common PSD (real) and ``S_aa - Re S_ab`` the own one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from imunoise.analysis.allan import allan
from imunoise.analysis.coherence import CrossSpectra
from imunoise.analysis.distributions import chi2, norm


@dataclass
class HatResult:
    """Own Allan variances of three sensors.

    Attributes:
        names: the three sensors (or channels).
        tau_s: averaging times, s.
        avar: own Allan variance, shape ``(3, taus)``, units^2 (may be negative).
        ci_low, ci_high: its interval (confidence ``ci``); ``ci_low`` is 0 where the estimate
            has an upper bound only.
        edf: Satterthwaite degrees of freedom of each estimate (0 where not positive).
        pair_avar: Allan variance of each pair's difference, ``{"a-b": array}``.
        pair_edf: their equivalent degrees of freedom.
    """

    names: tuple[str, str, str]
    tau_s: np.ndarray
    avar: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    edf: np.ndarray
    pair_avar: dict[str, np.ndarray]
    pair_edf: dict[str, np.ndarray]
    ci: float

    def white_level(self, index: int, tau_s: float) -> tuple[float, tuple[float, float]]:
        """The own white level ``N`` (units/sqrt(Hz), Allan variance ``N^2/tau``) of sensor
        ``index`` from its own Allan variance at the tau nearest ``tau_s``, with its interval.
        Right where that sensor's own noise is white there."""
        k = int(np.argmin(np.abs(np.log(self.tau_s / tau_s))))
        t = float(self.tau_s[k])
        value = float(np.sqrt(max(self.avar[index, k], 0.0) * t))
        return value, (float(np.sqrt(self.ci_low[index, k] * t)),
                       float(np.sqrt(self.ci_high[index, k] * t)))

    def to_dict(self) -> dict[str, Any]:
        return {"names": list(self.names), "tau_s": self.tau_s.tolist(),
                "avar": self.avar.tolist(), "ci": {"level": self.ci,
                                                   "low": self.ci_low.tolist(),
                                                   "high": self.ci_high.tolist()},
                "edf": self.edf.tolist(),
                "pair_avar": {k: v.tolist() for k, v in self.pair_avar.items()},
                "method": "three-cornered hat (Gray and Allan 1974), Satterthwaite intervals"}


def hat_variances(s_ij: np.ndarray, s_ik: np.ndarray, s_jk: np.ndarray, nu: np.ndarray,
                  ci: float = 0.95) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Own variance of sensor ``i`` from the pair variances and its interval:
    ``(estimate, ci_low, ci_high, edf)`` (module notes)."""
    s_i = 0.5 * (s_ij + s_ik - s_jk)
    s_j = 0.5 * (s_ij + s_jk - s_ik)
    s_k = 0.5 * (s_ik + s_jk - s_ij)
    pi, pj, pk = (np.maximum(v, 0.0) for v in (s_i, s_j, s_k))
    var = (2 * pi**2 + pi * pj + pi * pk + pj * pk) / nu
    a = (1.0 - ci) / 2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        edf = np.where(var > 0, 2 * pi**2 / var, 0.0)
        ok = edf > 0.5
        lo = np.where(ok, s_i * edf / chi2.ppf(1 - a, np.where(ok, edf, 1.0)), 0.0)
        hi = np.where(ok, s_i * edf / chi2.ppf(a, np.where(ok, edf, 1.0)),
                      pi + norm.ppf(1 - a) * np.sqrt(var))
    return s_i, lo, hi, np.where(ok, edf, 0.0)


def three_cornered_hat(x: np.ndarray, fs_hz: float, names: tuple[str, str, str] | None = None,
                       *, m: Any = "octave", segment_starts: np.ndarray | None = None,
                       ci: float = 0.95) -> HatResult:
    """Own Allan variance of each of three sensors of one kind measuring the same quantity.

    Args:
        x: samples ``(n, 3)``, one column per sensor, on one time base (same units, same
            axis of the bench).
        fs_hz: sampling rate, Hz.
        names: the sensors' names.
        m: averaging factors (see :func:`imunoise.analysis.allan.allan`).
        segment_starts: gap-free segment starts.
        ci: confidence level.
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"the three-cornered hat needs three sensors, got shape {x.shape}")
    names = tuple(names) if names is not None else ("a", "b", "c")
    pairs = {}
    edfs = {}
    tau = None
    for i, j in ((0, 1), (0, 2), (1, 2)):
        curve = allan(x[:, i] - x[:, j], fs_hz, "oadev", m, segment_starts, ci=ci)
        key = f"{names[i]}-{names[j]}"
        pairs[key] = curve.avar
        edfs[key] = curve.edf
        tau = curve.tau_s
    s01, s02, s12 = pairs.values()
    nu = np.minimum.reduce([np.nan_to_num(e, nan=1.0) for e in edfs.values()])
    rows = [hat_variances(s01, s02, s12, nu, ci), hat_variances(s01, s12, s02, nu, ci),
            hat_variances(s02, s12, s01, nu, ci)]
    est, lo, hi, edf = (np.stack(v) for v in zip(*rows, strict=True))
    return HatResult(names, np.asarray(tau), est, lo, hi, edf, pairs, edfs, ci)


def two_sensor_bounds(cs: CrossSpectra, a: str, b: str) -> dict[str, np.ndarray]:
    """Per Welch bin of ``cs``: ``a``'s PSD, the lower bound of its common part
    ``|S_ab|^2 / S_bb``, the upper bound of its own part ``S_aa - that``, and the own part if
    the bench reaches both with the same gain and phase, ``S_aa - Re S_ab`` (units^2/Hz; the
    real part, as ``|S_ab|`` is biased up by the own noises' random cross-products)."""
    i, j = cs.index(a), cs.index(b)
    saa, sbb, sab = cs.s[:, i, i].real, cs.s[:, j, j].real, np.abs(cs.s[:, i, j])
    common_low = sab**2 / np.maximum(sbb, 1e-300)
    return {"f_hz": cs.f_hz, "psd": saa, "common_at_least": common_low,
            "own_at_most": saa - common_low, "own_equal_gain": saa - cs.s[:, i, j].real}


def three_channel_own_psd(cs: CrossSpectra, a: str, b: str, c: str) -> np.ndarray:
    """Own PSD of channel ``a`` per Welch bin when ``a``, ``b`` and ``c`` see one common source
    through any gains: ``S_aa - Re(S_ab S_ca / S_cb)`` (units^2/Hz).

    With ``x_i = g_i s + e_i`` and the own parts independent, ``S_ab S_ca / S_cb = |g_a|^2 S_s``
    whatever the gains (the frequency-domain form of the three-cornered hat: Sleeman, van
    Wettum and Trampert, Bull. Seismol. Soc. Am. 96 (2006) 258-271). Unlike the Allan form it
    needs no equal gains: three axes of one sensor seeing one motion of the bench qualify. The
    estimate scatters where the common part is weak (``S_cb`` near zero) and can come out
    negative there.
    """
    i, j, k = cs.index(a), cs.index(b), cs.index(c)
    s = cs.s
    with np.errstate(divide="ignore", invalid="ignore"):
        common = s[:, i, j] * s[:, k, i] / s[:, k, j]
    return s[:, i, i].real - np.nan_to_num(common.real)


WHITE_TAU_S = 1.0
"""Averaging time at which :func:`sensors_document` reads each sensor's own white level."""


def sensors_document(values: dict[str, np.ndarray], fs_hz: float, *,
                     segment_starts: np.ndarray | None = None, ci: float = 0.95,
                     white_tau_s: float = WHITE_TAU_S) -> dict[str, Any]:
    """Several sensors of one kind on one bench: for each channel name that two or more
    devices share (``imu1/gyro_x``, ``/imu2:gyro_x`` ...), the three-cornered hat of the first
    three (own Allan variance per tau with intervals, and the own white level at
    ``white_tau_s``) or, with two, the two-sensor bounds on log-frequency points.

    ``values``: channel key -> samples (SI), all on one time base.
    """
    from imunoise.analysis.coherence import cross_spectra, log_coherence
    from imunoise.analysis.environment import channel_device

    by_name: dict[str, list[str]] = {}
    for key in values:
        device = channel_device(key)
        if device:
            by_name.setdefault(key[len(device) + 1:], []).append(key)
    out: dict[str, Any] = {}
    for name, keys in by_name.items():
        if len(keys) >= 3:
            trio = keys[:3]
            x = np.column_stack([values[k] for k in trio])
            hat = three_cornered_hat(x, fs_hz, tuple(trio), segment_starts=segment_starts, ci=ci)
            doc = hat.to_dict()
            doc["white_level"] = {}
            for i, k in enumerate(trio):
                level, (lo, hi) = hat.white_level(i, white_tau_s)
                doc["white_level"][k] = {"N": level, "ci": [lo, hi],
                                         "tau_s": float(hat.tau_s[int(np.argmin(np.abs(
                                             np.log(hat.tau_s / white_tau_s))))])}
            out[name] = doc
        elif len(keys) == 2:
            x = np.column_stack([values[k] for k in keys])
            cs = cross_spectra(x, fs_hz, keys, segment_starts=segment_starts)
            bounds = two_sensor_bounds(cs, keys[0], keys[1])
            co = log_coherence(cs, intervals=False)
            idx = np.floor(np.log10(cs.f_hz) * 10.0 + 1e-9).astype(np.int64)
            _, first, counts = np.unique(idx, return_index=True, return_counts=True)

            def merged(v: np.ndarray, first=first, counts=counts) -> list[float]:
                return (np.add.reduceat(v, first) / counts).tolist()

            out[name] = {"method": "two sensors: the cross-spectrum bounds the common part",
                         "sensors": keys, "f_hz": co.f_hz.tolist(),
                         "psd": merged(bounds["psd"]),
                         "common_at_least": merged(bounds["common_at_least"]),
                         "own_at_most": merged(bounds["own_at_most"]),
                         "own_equal_gain": merged(bounds["own_equal_gain"])}
    return out
