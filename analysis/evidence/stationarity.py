"""Does the noise level change along the record (warm-up, a disturbance, a changed setting)?

The record is cut into windows; in each the Allan variance at the shortest averaging time
(half the mean square of first differences) measures the white-noise level. For white noise
the first differences form an MA(1) sequence with lag-one correlation -1/2, so the estimate
has ``n / 1.5`` equivalent degrees of freedom; the log-levels of the windows are compared
with a chi-square homogeneity test (``W - 1`` dof). Samples flagged as outliers are left out.
A change is reported only when the test is significant and the density changes by at least
``MIN_LEVEL_RATIO``.
"""

from __future__ import annotations

import numpy as np

from imunoise.analysis import distributions as dist
from imunoise.analysis.evidence.finding import Finding

_MA1_VARIANCE_FACTOR = 1.5
MIN_LEVEL_RATIO = 1.05
"""Smallest change of the white-noise density worth reporting: over millions of samples the
test resolves changes of a fraction of a percent that change no estimate materially."""


def noise_level_windows(segments: list[np.ndarray], fs_hz: float, n_windows: int = 8,
                        alpha: float = 0.05, exclude: np.ndarray | None = None,
                        units: str = "rad/s") -> Finding:
    """Homogeneity of the short-tau Allan variance across ``n_windows`` windows.

    Args:
        segments: gap-free pieces of the channel (SI units).
        fs_hz: sampling rate in Hz.
        n_windows: number of equal windows in sample count.
        alpha: significance level.
        exclude: optional indices (into the concatenated samples) to leave out, e.g. outliers.
        units: units of the samples, for the explanation.

    Returns:
        Finding of kind ``"nonstationarity"`` (no model term); ``details`` has each window's
        level as a white-noise density ``N`` (units/sqrt(Hz)) and its time span.
    """
    lengths = [len(s) for s in segments]
    total = int(sum(lengths))
    d = np.concatenate([np.diff(s) for s in segments])
    # Position of each difference in sample index terms (the later sample of the pair).
    pos = np.concatenate([np.arange(1, n) + off for n, off in
                          zip(lengths, np.cumsum([0] + lengths[:-1]), strict=True)])
    keep = np.ones(d.size, dtype=bool)
    if exclude is not None and len(exclude):
        bad = np.zeros(total + 1, dtype=bool)
        bad[np.asarray(exclude, int)] = True
        keep &= ~(bad[pos] | bad[pos - 1])
    d, pos = d[keep], pos[keep]
    if d.size < 40 * n_windows:
        n_windows = max(d.size // 40, 1)
    if n_windows < 2:
        return Finding("nonstationarity", None, 0.0, "chi2", 1.0, alpha,
                       why="record too short to compare windows")
    win = np.minimum((pos * n_windows) // max(total, 1), n_windows - 1)
    cnt = np.bincount(win, minlength=n_windows).astype(float)
    ssq = np.bincount(win, weights=d * d, minlength=n_windows)
    avar1 = ssq / np.maximum(cnt, 1) / 2.0
    nu = cnt / _MA1_VARIANCE_FACTOR
    ok = (cnt > 10) & (avar1 > 0)
    if ok.sum() < 2:
        return Finding("nonstationarity", None, 0.0, "chi2", 1.0, alpha,
                       why="too few usable windows to compare")
    loga = np.log(avar1[ok])
    wgt = nu[ok] / 2.0
    mean = np.sum(wgt * loga) / np.sum(wgt)
    chi2 = float(np.sum(wgt * (loga - mean) ** 2))
    dof = int(ok.sum() - 1)
    p = float(dist.chi2.sf(chi2, dof))
    n_density = np.sqrt(avar1 / fs_hz)  # AVAR(tau0) = N^2/tau0 for white noise
    t_edges = np.linspace(0.0, total / fs_hz, n_windows + 1)
    ratio = float(np.sqrt(avar1[ok].max() / avar1[ok].min()))
    details = {"window_N": [float(v) for v in n_density],
               "window_t_s": [[float(a), float(b)] for a, b in zip(t_edges[:-1], t_edges[1:],
                                                                  strict=True)]}
    if ratio < MIN_LEVEL_RATIO:
        # Statistically resolved or not, a change this small is not worth a warning.
        p = max(p, 1.0)
    if p < alpha:
        hi = int(np.argmax(np.where(ok, avar1, -np.inf)))
        lo = int(np.argmin(np.where(ok, avar1, np.inf)))
        start = " (warm-up at the start)" if hi == 0 or lo == 0 else ""
        why = (f"The white-noise level changes along the record by a factor {ratio:.2f} "
               f"between windows{start}: highest {n_density[hi]:.3g}, lowest "
               f"{n_density[lo]:.3g} {units}/sqrt(Hz). A stationary model describes an average; "
               f"check warm-up, disturbances or changed settings, or analyse the steady part.")
    else:
        why = (f"The white-noise level is steady across {int(ok.sum())} windows "
               f"(largest ratio {ratio:.3f}).")
    return Finding("nonstationarity", None, chi2, "chi2", p, alpha, {"level_ratio": ratio},
                   {"t_s": [0.0, total / fs_hz]}, why, details)
