"""Shared pieces of the device tests: constant sources, record collection, noise levels."""

from __future__ import annotations

import numpy as np
from scipy import stats

from imunoise.daq.acquisition import Acquisition


def constant(values) -> callable:
    v = np.asarray(values, dtype=np.float64)

    def take(n: int) -> np.ndarray:
        return np.tile(v, (n, 1))

    return take


def record(acq: Acquisition, duration_s: float) -> dict[str, dict]:
    """Concatenate the blocks of each stream: t, channels, raw, gaps."""
    out: dict[str, dict] = {}
    with acq:
        for b in acq.blocks(duration_s):
            s = out.setdefault(b.stream, {"t": [], "ch": {}, "raw": {}, "gaps": [], "fs": b.fs_hz})
            s["t"].append(b.t)
            s["gaps"].append(b.gap_before)
            for k, v in b.channels.items():
                s["ch"].setdefault(k, []).append(v)
            for k, v in b.raw.items():
                s["raw"].setdefault(k, []).append(v)
    for s in out.values():
        s["t"] = np.concatenate(s["t"])
        s["ch"] = {k: np.concatenate(v) for k, v in s["ch"].items()}
        s["raw"] = {k: np.concatenate(v) for k, v in s["raw"].items()}
    return out


def white_level_interval(x: np.ndarray, confidence: float = 0.999) -> tuple[float, float, float]:
    """Per-sample white-noise variance from first differences, with a chi-square interval.

    For white noise w, var(diff(w)) = 2 var(w); slow terms (bias, drift) almost vanish in the
    differences. Differences of white noise are MA(1) with lag-one correlation -1/2, which
    makes the sample variance's equivalent degrees of freedom n / (1 + 2 * 0.25) = n / 1.5.
    """
    d = np.diff(np.asarray(x, dtype=np.float64))
    est = float(np.var(d, ddof=1) / 2.0)
    dof = (len(d) - 1) / 1.5
    a = (1 - confidence) / 2
    lo = est * dof / stats.chi2.ppf(1 - a, dof)
    hi = est * dof / stats.chi2.ppf(a, dof)
    return est, lo, hi


def expected_variance(density: float, fs_hz: float, lsb: float) -> float:
    """White noise of ``density`` per sqrt(Hz) sampled at fs, plus quantization LSB^2/12."""
    return density ** 2 * fs_hz + lsb ** 2 / 12.0


