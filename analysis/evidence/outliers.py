"""Outliers (isolated spikes) and gaps.

Each sample is compared with the mean of its two neighbours, which removes the slow bias
exactly for any stationary noise while leaving a spike almost whole, and the differences are
scaled by their median absolute deviation (1.4826 MAD is the standard deviation for Gaussian
noise). A spike also raises its neighbours by half; only the local maximum is flagged.
The flag threshold depends on the record length: it is the Gaussian quantile at which
``n`` independent samples exceed it with total probability ``alpha``, so clean white data
of any length is flagged with probability below ``alpha``.
"""

from __future__ import annotations

import numpy as np

from imunoise.analysis import distributions as dist
from imunoise.analysis.evidence.finding import Finding, family_p

_MAD_TO_SIGMA = 1.482602218505602
_MAX_LISTED = 100


def robust_z(x: np.ndarray) -> np.ndarray:
    """Robust z-scores of each sample against the mean of its neighbours."""
    x = np.asarray(x, dtype=np.float64)
    if x.size < 3:
        return np.zeros(x.size)
    r = np.empty(x.size)
    r[1:-1] = x[1:-1] - 0.5 * (x[:-2] + x[2:])
    # End samples against their single neighbour, rescaled to the same variance for white noise.
    r[0] = (x[0] - x[1]) * np.sqrt(0.75)
    r[-1] = (x[-1] - x[-2]) * np.sqrt(0.75)
    mad = float(np.median(np.abs(r - np.median(r))))
    scale = _MAD_TO_SIGMA * mad
    if scale <= 0:
        scale = float(np.std(r)) or 1.0
    return r / scale


def _flag(segments: list[np.ndarray], alpha: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Flagged indices (into the concatenated samples), all |z|, and the threshold."""
    z = np.concatenate([robust_z(s) for s in segments if len(s)])
    n = z.size
    thr = float(dist.norm.isf(0.5 * (-np.expm1(np.log1p(-alpha) / max(n, 1)))))
    az = np.abs(z)
    peak = np.ones(n, dtype=bool)
    peak[1:] &= az[1:] >= az[:-1]
    peak[:-1] &= az[:-1] >= az[1:]
    return np.flatnonzero((az > thr) & peak), az, thr


def outlier_indices(segments: list[np.ndarray], alpha: float = 0.05) -> np.ndarray:
    """Every flagged sample's index into the concatenated segments (see :func:`outliers`)."""
    return _flag(segments, alpha)[0]


def outliers(segments: list[np.ndarray], fs_hz: float, alpha: float = 0.05,
             units: str = "rad/s") -> Finding:
    """Flag samples far outside the noise.

    Returns:
        Finding of kind ``"outliers"``: statistic the largest robust |z|, p-value its
        family-wise probability under Gaussian noise; ``details`` lists the count, the
        threshold and the first indices and times of the flagged samples.
    """
    flagged, az, thr = _flag(segments, alpha)
    n = az.size
    zmax = float(az.max()) if n else 0.0
    p = family_p(float(2.0 * dist.norm.sf(zmax)), n)
    details = {"count": int(flagged.size), "threshold_z": thr,
               "indices": [int(i) for i in flagged[:_MAX_LISTED]],
               "t_s": [float(i / fs_hz) for i in flagged[:_MAX_LISTED]]}
    if flagged.size:
        why = (f"{flagged.size} sample(s) lie beyond {thr:.1f} robust sigma (largest "
               f"{zmax:.1f} sigma), more than Gaussian noise of this length allows: shocks, "
               f"bus errors or glitches. They inflate the Allan deviation at short tau; "
               f"remove them or use a robust estimate.")
    else:
        why = f"No outliers: the largest sample is {zmax:.1f} robust sigma (limit {thr:.1f})."
    return Finding("outliers", None, zmax, "max |z|", p, alpha, {"count": float(flagged.size)},
                   {"t_s": [0.0, n / fs_hz]}, why, details)


def gaps(segment_starts: np.ndarray, n_samples: int, fs_hz: float,
         segment_t0_s: np.ndarray | None = None) -> Finding:
    """Count the gaps between gap-free segments and, when segment start times are known,
    the total missing time in seconds.

    Gaps are a fact, not a statistical question: ``p_value`` is 0 when there is any gap
    (so ``significant`` reports that there are gaps) and 1 otherwise.
    """
    starts = np.asarray(segment_starts, dtype=np.int64)
    count = int(max(starts.size - 1, 0))
    details: dict = {"count": count}
    missing = None
    if segment_t0_s is not None and count:
        t0 = np.asarray(segment_t0_s, dtype=float)
        ends = t0[:-1] + np.diff(np.append(starts, n_samples))[:-1] / fs_hz
        missing = float(np.sum(np.maximum(t0[1:] - ends, 0.0)))
        details["missing_s"] = missing
    if count:
        extra = f", {missing:.3g} s missing in total" if missing is not None else ""
        why = (f"The record has {count} gap(s){extra}; the estimates use the gap-free "
               f"segments only and never average across a gap.")
    else:
        why = "The record has no gaps."
    return Finding("gaps", None, float(count), "count", 0.0 if count else 1.0, 0.5,
                   {"count": float(count)}, {}, why, details)
