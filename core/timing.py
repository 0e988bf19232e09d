"""Sample timing shared by every reader: the nominal rate and the gap-free segments.

Every reader (CSV, MCAP, rosbag2) turns sample times into a rate and segment boundaries here, so
that the same time stamps give the same rate, gaps and segments whatever the file format.
"""

from __future__ import annotations

import numpy as np


def estimate_rate(t: np.ndarray) -> float:
    """Nominal sampling rate in Hz from sample times in seconds.

    The median interval picks the nominal period robustly (gaps and backward jumps do not move
    it); the rate is then the mean over the intervals within half a period of it, which is exact
    for clean time stamps and unbiased for jittered or coarsely quantised ones (1 ms stamps at
    300 Hz), rounded to 9 significant digits.
    """
    dt = np.diff(np.asarray(t, dtype=np.float64))
    dt = dt[dt > 0]
    if dt.size == 0:
        raise ValueError("cannot infer a sampling rate: fewer than two increasing time stamps")
    med = float(np.median(dt))
    near = dt[np.abs(dt - med) < 0.5 * med]
    return float(f"{1.0 / float(np.mean(near)):.9g}")


def segment_starts_from_times(t: np.ndarray, fs_hz: float, tolerance: float = 0.5) -> np.ndarray:
    """Indices where a new segment starts, given sample times in seconds.

    A new segment starts wherever the interval to the previous sample departs from ``1/fs_hz``
    by more than ``tolerance`` sample periods: missing samples, duplicated or backwards time.
    """
    t = np.asarray(t, dtype=np.float64)
    if t.size == 0:
        return np.zeros(1, dtype=np.int64)
    dt = np.diff(t) * fs_hz
    breaks = np.flatnonzero(np.abs(dt - 1.0) > tolerance) + 1
    return np.concatenate(([0], breaks)).astype(np.int64)
