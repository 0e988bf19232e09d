"""Steps that the channels of one kind take together: the bench knocked, tilted or moved.

An accelerometer on a bench reads gravity's projection on its axes. When the bench is knocked,
leaned on or a weight is put down on it, the projection changes at once on every axis: a step
of the bias seen by all the accelerometer channels at the same instant. These are events of the
environment, not noise of the sensing element, but a noise model fitted to the channel takes
them for random walk: its long-tau Allan variance rises, differently in each part of the night
(a step falls in one half and not in the other), and the model predicts neither half. The
accelerometers of the six ADIS16405 runs of the shared data jump together 5 to 8 times a run
(up to 19.5 standard scores on one axis; run 1 at 2149 s, 8.1, 8.3 and 10.3 on accel_x,
accel_y, accel_z), and 2 to 8 of those jumps leave a lasting step on at least one axis.

Detection, per gap-free segment of the channels' common time base:

- each channel's one-second block means (:data:`BLOCK_S`);
- at each block boundary the contrast ``d = mean(after) - mean(before)`` over
  :data:`WINDOW_S` on either side (the last two windows of a segment are not tested: the
  lasting step below needs them); each channel's contrasts standardised by their median and
  median absolute deviation (robust to the steps themselves; white noise, flicker, random walk
  and Markov noise all give Gaussian contrasts, whose scale this is);
- the channels' standardised contrasts combined as ``q = z^T R^-1 z``, ``R`` their correlation
  over the boundaries where no channel exceeds 4 standard scores: chi-square with one degree of
  freedom per channel under stationary Gaussian noise;
- a step where ``q`` exceeds the chi-square point at ``LEVEL / boundaries`` (Bonferroni over
  every boundary of the record: a family-wise false-alarm rate of at most :data:`LEVEL`), the
  largest first, none within two windows of another (each step's windows then hold no other).

What is removed is the step that lasts: a knock often moves the level and lets it settle back
part of the way over a minute or two (run 1's 2149 s event keeps a third to a half of its jump
beyond the first 30 s; run 6's at 4922 s none of it). The size removed is the mean over the
*second* window after the boundary (30-60 s) minus the mean over the window before it,
standardised like the contrasts over every boundary, and a step is removed from a channel only
where that lasting step is beyond :data:`GATE_Z` standard scores: a transient that settles back
is left in the record (the noise terms see a bump, not a new level), a knock along one axis
leaves the other axes as they were, and subtracting a size that is its own noise would add a
random step. The time is the block boundary (at most half a block from the step).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imunoise.analysis.distributions import chi2

TERM = "common_steps"
"""The name a model specification gives the removal (``fit``/``diagnose --model ...``)."""

BLOCK_S = 1.0
"""Block length (s) of the means the contrasts are built from: the steps' time resolution."""

WINDOW_S = 30.0
"""Length (s) averaged on either side of a boundary."""

LEVEL = 1e-3
"""Family-wise false-alarm rate of the detection over a whole record."""

GATE_Z = 3.0
"""A detected step is removed from a channel whose lasting step exceeds this many standard
scores."""

_CLEAN_Z = 4.0  # boundaries with every channel below this estimate the channels' correlation


@dataclass(frozen=True)
class CommonStep:
    """One step the channels took together.

    Attributes:
        index: first sample after the step (index into the channels' values).
        t_s: its time, s from the first sample.
        statistic: ``q``, the combined standardised contrast (chi-square, one degree of freedom
            per channel, under stationary noise).
        log10_p: log10 of the family-wise p-value (Bonferroni over the boundaries).
        sizes: each channel's lasting step (channel units): the mean over the second
            window after the step minus the mean over the window before it.
        z: each channel's lasting step standardised.
        jump_z: each channel's standardised contrast of the window right after the step
            with the one before: what ``statistic`` combines.
    """

    index: int
    t_s: float
    statistic: float
    log10_p: float
    sizes: dict[str, float]
    z: dict[str, float]
    jump_z: dict[str, float]

    def removed_from(self, channel: str) -> bool:
        """Whether this step is removed from ``channel`` (its lasting step beyond
        :data:`GATE_Z`)."""
        return abs(self.z.get(channel, 0.0)) > GATE_Z


@dataclass(frozen=True)
class CommonSteps:
    """The steps found in a record's channels of one kind.

    Attributes:
        channels: the channels searched together.
        fs_hz: their sampling rate, Hz.
        steps: the steps, in time order.
        threshold: the ``q`` a step had to exceed.
        boundaries: the number of boundaries tested.
    """

    channels: list[str]
    fs_hz: float
    steps: list[CommonStep] = field(default_factory=list)
    threshold: float = math.inf
    boundaries: int = 0

    def of(self, channel: str) -> list[CommonStep]:
        """The steps removed from ``channel``."""
        return [s for s in self.steps if s.removed_from(channel)]

    def corrected(self, values: np.ndarray, channel: str) -> np.ndarray:
        """``values`` of ``channel`` (the channels' common time base) with each of its steps
        taken out: from each step on, its size subtracted."""
        x = np.array(values, dtype=np.float64, copy=True)
        for s in self.of(channel):
            x[s.index:] -= s.sizes[channel]
        return x

    def to_dict(self, channel: str) -> dict[str, Any]:
        """JSON-ready summary for ``channel`` (units of the channel, times in s)."""
        return {"channels": list(self.channels), "threshold": self.threshold,
                "boundaries": self.boundaries, "level": LEVEL, "block_s": BLOCK_S,
                "window_s": WINDOW_S, "gate_z": GATE_Z,
                "steps": [{"t_s": s.t_s, "size": s.sizes[channel], "z": s.z[channel],
                           "jump_z": s.jump_z[channel], "statistic": s.statistic,
                           "log10_p": s.log10_p}
                          for s in self.of(channel)],
                "found": len(self.steps)}


def _chi2_logsf(x: float, k: int) -> float:
    """``ln P(chi2_k > x)``; far in the tail, where it underflows, its leading terms
    (a knock of 20 standard scores is still a number, not minus infinity)."""
    logp = float(chi2.logsf(x, k))
    if math.isfinite(logp):
        return logp
    return -0.5 * x + (0.5 * k - 1.0) * math.log(0.5 * x) - math.lgamma(0.5 * k)


def _contrasts(x: np.ndarray, block: int, window: int
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boundaries (block index), contrasts and lasting contrasts ``(boundaries, channels)``
    of one segment: the ``window`` blocks after each boundary against the ``window`` before
    it, and the ``window`` blocks after a further ``window`` (the step's settling skipped)
    against the same before."""
    nb = x.shape[0] // block
    if nb < 5 * window:
        empty = np.zeros((0, x.shape[1]))
        return np.zeros(0, dtype=np.int64), empty, empty
    m = x[:nb * block].reshape(nb, block, x.shape[1]).mean(axis=1)
    c = np.vstack([np.zeros((1, x.shape[1])), np.cumsum(m, axis=0)])
    k = np.arange(window, nb - 2 * window + 1)
    before = (c[k] - c[k - window]) / window
    d = (c[k + window] - c[k]) / window - before
    lasting = (c[k + 2 * window] - c[k + window]) / window - before
    return k, d, lasting


def _standardised(d: np.ndarray) -> np.ndarray | None:
    """``d`` over its median and median absolute deviation per column (None where a column
    has no spread: a constant channel)."""
    centre = np.median(d, axis=0)
    scale = 1.4826 * np.median(np.abs(d - centre), axis=0)
    if np.any(scale <= 0):
        return None
    return (d - centre) / scale


def find_common_steps(x: np.ndarray, fs_hz: float, channels: list[str],
                      segment_starts: np.ndarray | None = None,
                      level: float = LEVEL) -> CommonSteps:
    """The steps that ``channels`` (the columns of ``x``, ``(samples, channels)``, one time
    base, channel units) take together; see the module notes. A record too short for two
    windows on either side of a boundary, or with fewer than two channels, has none."""
    x = np.asarray(x, dtype=np.float64)
    names = list(channels)
    found = CommonSteps(names, float(fs_hz))
    if x.ndim != 2 or x.shape[1] != len(names) or len(names) < 2 or not np.all(np.isfinite(x)):
        return found
    block = max(int(round(BLOCK_S * fs_hz)), 1)
    window = max(int(round(WINDOW_S / (block / fs_hz))), 1)
    starts = np.zeros(1, dtype=np.int64) if segment_starts is None \
        else np.asarray(segment_starts, dtype=np.int64)
    bounds = np.append(starts, x.shape[0])
    where, contrasts, lasting = [], [], []
    for a, b in zip(bounds[:-1], bounds[1:], strict=True):
        k, d, d_last = _contrasts(x[a:b], block, window)
        where.append(a + k * block)
        contrasts.append(d)
        lasting.append(d_last)
    idx = np.concatenate(where) if where else np.zeros(0, dtype=np.int64)
    if idx.size < 10:
        return found
    d, d_last = np.vstack(contrasts), np.vstack(lasting)
    z, z_last = _standardised(d), _standardised(d_last)
    if z is None or z_last is None:
        return found
    clean = np.all(np.abs(z) < _CLEAN_Z, axis=1)
    corr = np.corrcoef(z[clean].T) if clean.sum() > 3 * len(names) else np.eye(len(names))
    corr = np.atleast_2d(corr)
    try:
        q = np.einsum("ij,jk,ik->i", z, np.linalg.inv(corr), z)
    except np.linalg.LinAlgError:
        q = np.sum(z * z, axis=1)
    n_tests = int(idx.size)
    threshold = float(chi2.isf(level / n_tests, len(names)))
    taken: list[int] = []
    for i in np.argsort(q)[::-1]:
        if q[i] <= threshold:
            break
        if all(abs(int(idx[i]) - int(idx[j])) > 2 * window * block for j in taken):
            taken.append(int(i))
    steps = []
    for i in sorted(taken, key=lambda j: int(idx[j])):
        logp = _chi2_logsf(float(q[i]), len(names)) + math.log(n_tests)
        steps.append(CommonStep(
            index=int(idx[i]), t_s=float(idx[i]) / float(fs_hz), statistic=float(q[i]),
            log10_p=min(logp, 0.0) / math.log(10.0),
            sizes={c: float(d_last[i, n]) for n, c in enumerate(names)},
            z={c: float(z_last[i, n]) for n, c in enumerate(names)},
            jump_z={c: float(z[i, n]) for n, c in enumerate(names)}))
    return CommonSteps(names, float(fs_hz), steps, threshold, n_tests)
