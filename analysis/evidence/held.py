"""Held samples: values a logger or resampler repeated where the sensor gave none.

A logger that polls faster than the sensor updates, or a resampler that fills missing readings
with the last value, writes the same number again and again. Those samples are not
measurements: the noise is missing there, and each held stretch ends in a jump. The Allan
deviation falls at the shortest tau and rises at taus near the holds' length (white noise held
as the Galaxy S5 night below holds it: -4 % at 0.1 s, +15-20 % at 0.8-12.8 s), and no noise
model of the sensor follows them. The Samsung Galaxy S5 night in the shared data (already
resampled to 10 Hz by its publisher) holds 6.6 % of its gyro y samples in 3,318 runs of up to
19 samples (1.9 s), each framed by the ringing of the resampling filter.

The test counts the samples equal to the one before them (within gap-free segments) and asks
whether chance explains that many. Two neighbours of a noisy record are equal by chance only
when their difference falls within the data's resolution ``q``: with ``g`` the density of the
first differences at zero, each pair is equal with probability about ``q g``, so the expected
count is ``E = (n - 1) q g`` whatever the noise's correlation (an expectation is a sum). The
count is judged against Poisson(E), and reported only where it is also at least
``MIN_EXCESS`` times E.

Where either factor is uncertain it is taken on chance's side:

- ``q``, the median spacing of the sorted distinct values of (at most ``RESOLUTION_SAMPLES``
  evenly spaced samples of) the record: the step of quantized data; for data of finer
  resolution an upper bound of it (the spacing of the values a record happens to take);
- ``g``, the larger of the Gaussian density at zero of differences with the MAD's spread and
  the differences' own share within a quarter of that spread of zero.

On quantized simulated noise (white, moving average, Markov) the observed count was 0.8-1.4
times ``E`` where the chance is below 1 % (few repeats, a noisy count) and within 20 % of it up
to ``COARSE_CHANCE``: hence the floor of ``MIN_EXCESS``. A logger that reads every sample twice
repeats half of them: 8-15 times chance's share at 3-7 %.

Where ``q g`` exceeds ``COARSE_CHANCE`` the data are too coarse against their noise (an
ADIS16405 accelerometer moves by one count a sample or by none, 27 % of its neighbours are
equal; its gyros, 3-5 %, are judged): equal neighbours are common there, the spread of the
differences is itself a count or two and ``g`` no longer follows, and a held value cannot be
told from a repeated one. The finding then
says so and is never significant. A channel whose values never change is held throughout
(a stuck sensor or a disconnected input), a fact with ``p_value`` 0.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import special

from imunoise.analysis.evidence.finding import Finding

RESOLUTION_SAMPLES = 1 << 17
"""Most samples sorted to find the data's resolution: a subsample can only widen the spacing of
distinct values, which overstates chance (sorting a million values costs 0.13 s)."""

COARSE_CHANCE = 0.05
"""Chance of two neighbours being equal above which held values cannot be told apart. Below it
the chance estimate held within 20 % on quantized white, moving-average and Markov noise (the
last with a correlation of 0.99 a sample); above it, where the differences' MAD is one or two
steps, it fell short by up to a factor three on Markov noise."""

MIN_EXCESS = 2.0
"""Fewest repeats, as a multiple of the chance expectation, worth reporting: ``E`` is itself an
estimate (within about 40 % on simulated quantized noise), and a finding must name an effect
that is there, not a chance count a little above an estimate."""

_MAD_TO_SIGMA = 1.482602218505602
_MAX_LISTED = 100


def _resolution(x: np.ndarray) -> float:
    """Median spacing of the distinct values of (a strided subsample of) ``x``; 0 when it
    takes a single value."""
    step = max(1, x.size // RESOLUTION_SAMPLES)
    v = np.sort(x[::step])
    d = np.diff(v)
    d = d[d > 0]
    return float(np.median(d)) if d.size else 0.0


def _density_at_zero(d: np.ndarray) -> tuple[float, float]:
    """``(g, spread)``: the first differences' density at zero (per unit of the samples) and
    their robust spread (1.4826 MAD of the non-zero ones; held pairs would shrink it)."""
    moving = np.abs(d[d != 0])
    if moving.size == 0:
        return math.inf, 0.0
    spread = _MAD_TO_SIGMA * float(np.median(moving))
    gaussian = 1.0 / (math.sqrt(2.0 * math.pi) * spread)
    h = 0.25 * spread
    near = float(np.count_nonzero(moving <= h)) / (2.0 * h * d.size)
    return max(gaussian, near), spread


def _runs(equal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start index (of the first repeated pair) and length in pairs of each run of True."""
    e = np.diff(np.concatenate(([0], equal.astype(np.int8), [0])))
    starts = np.flatnonzero(e == 1)
    return starts, np.flatnonzero(e == -1) - starts


def held_samples(segments: list[np.ndarray], fs_hz: float, alpha: float = 0.05,
                 units: str = "rad/s") -> Finding:
    """Samples equal to the sample before them, beyond what the data's resolution explains.

    Args:
        segments: gap-free pieces of the channel (SI units); a pair across a gap is no pair.
        fs_hz: sampling rate in Hz.
        alpha: significance level.
        units: units of the samples, for the explanation.

    Returns:
        Finding of kind ``"held_samples"`` (no model term): statistic the count of repeated
        samples, p-value the Poisson probability of at least that many by chance (1 when the
        data are too coarse to tell, or the count is below ``MIN_EXCESS`` times chance's).
        ``params``: ``count``, ``share`` (of all samples) and ``longest_s``. ``details``:
        ``runs``, ``longest_samples``, ``expected_by_chance``, ``resolution`` and ``spread``
        (units), ``chance_per_pair``, ``testable``, and the first runs' start times ``t_s``
        (s from the first sample, gaps not counted) and lengths ``run_samples`` (samples
        repeating the one before).
    """
    pieces = [np.asarray(s, dtype=np.float64) for s in segments if len(s)]
    n = int(sum(s.size for s in pieces))
    if n < 3:
        return Finding("held_samples", None, 0.0, "repeats", 1.0, alpha,
                       why="Too few samples to look for held values.")
    x = np.concatenate(pieces)
    d = np.concatenate([np.diff(s) for s in pieces])
    # a run must not join across a gap: mark each segment's first sample as no repeat
    equal = np.zeros(n, dtype=bool)
    offsets = np.cumsum([0] + [s.size for s in pieces[:-1]])
    ok = np.ones(n, dtype=bool)
    ok[offsets] = False
    equal[ok] = d == 0
    count = int(np.count_nonzero(equal))
    starts, lengths = _runs(equal)
    longest = int(lengths.max()) if lengths.size else 0
    q = _resolution(x)
    g, spread = _density_at_zero(d)
    params = {"count": float(count), "share": count / n, "longest_s": longest / fs_hz}
    details = {"runs": int(lengths.size), "longest_samples": longest,
               "t_s": [float(i / fs_hz) for i in starts[:_MAX_LISTED]],
               "run_samples": [int(k) for k in lengths[:_MAX_LISTED]],
               "resolution": q, "spread": spread}
    span = {"t_s": [float(starts[0] / fs_hz), float((starts[-1] + lengths[-1]) / fs_hz)]} \
        if lengths.size else {}
    if count == d.size:
        details.update(testable=True, chance_per_pair=None, expected_by_chance=None)
        why = (f"The channel never changes: all {n} samples equal {x[0]:.6g} {units}. A stuck "
               f"sensor, a disconnected input or a logger repeating one value; there is no "
               f"noise to analyse.")
        return Finding("held_samples", None, float(count), "repeats", 0.0, alpha, params,
                       span, why, details)
    chance = min(1.0, q * g)
    expected = chance * d.size
    details.update(chance_per_pair=chance, expected_by_chance=expected,
                   testable=chance <= COARSE_CHANCE)
    if chance > COARSE_CHANCE:
        why = (f"{count} samples ({100 * count / n:.2g} %) equal the sample before them; at a "
               f"resolution of {q:.3g} {units} against a sample-to-sample spread of "
               f"{spread:.3g} {units} equal neighbours are common by chance (about "
               f"{100 * chance:.2g} % of pairs), so held values cannot be told apart.")
        return Finding("held_samples", None, float(count), "repeats", 1.0, alpha, params,
                       span, why, details)
    # P(X >= count) for X ~ Poisson(expected), without loading scipy.stats at start-up
    p = float(special.gammainc(count, expected)) if count else 1.0
    if count < MIN_EXCESS * expected:
        p = 1.0
    if p < alpha:
        why = (f"{count} samples ({100 * count / n:.2g} %) repeat the sample before them "
               f"exactly, in {lengths.size} runs of up to {longest} samples "
               f"({longest / fs_hz:.3g} s), where the data's resolution ({q:.3g} {units} "
               f"against a sample-to-sample spread of {spread:.3g} {units}) explains about "
               f"{expected:.2g}: a logger or resampler held the last value where readings were "
               f"missing. Those samples are not measurements; they lower the Allan deviation "
               f"at the shortest tau and raise it at taus near their length, which no noise "
               f"term of the sensor follows. Analyse the sensor's own time-stamped samples, "
               f"where a missing reading is a gap.")
    elif count:
        why = (f"No held values: {count} samples equal the sample before them, as the data's "
               f"resolution explains (about {expected:.2g} by chance).")
    else:
        why = "No held values: no sample equals the sample before it."
    return Finding("held_samples", None, float(count), "repeats", p, alpha, params, span,
                   why, details)
