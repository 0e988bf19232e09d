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

- ``q``, the median spacing of the sorted distinct values of the record's first
  ``RESOLUTION_SAMPLES`` samples: the step of quantized data; for data of finer resolution an
  upper bound of it (the spacing of the values a record happens to take);
- ``g``, the larger of the Gaussian density at zero of differences with the MAD's spread and
  the differences' own share within a quarter of that spread of zero.

On quantized simulated noise (white, moving average, Markov) the observed count was 0.8-1.3
times ``E`` where the chance is below 1 % (few repeats, a noisy count) and within 20 % of it up
to ``COARSE_CHANCE``: hence the floor of ``MIN_EXCESS``. A logger that reads every sample twice
repeats half of them: 8-15 times chance's share at 3-7 %.

Where ``q g`` exceeds ``COARSE_CHANCE`` the data are too coarse against their noise (an
ADIS16405 accelerometer moves by one count a sample or by none, 27 % of its neighbours are
equal; its gyros, 3-5 %, are judged): equal neighbours are common there, the spread of the
differences is itself a count or two and ``g`` no longer follows, and a held value cannot be
told from a repeated one. The finding then says so and is never significant. A channel whose
values never change is held throughout (a stuck sensor or a disconnected input), a fact with
``p_value`` 0.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import special

from imunoise.analysis.evidence.finding import Finding

RESOLUTION_SAMPLES = 1 << 17
"""Samples (the record's first) sorted to find the data's resolution, and whose differences
give their density at zero: fewer values can only widen the spacing of distinct values, which
overstates chance; a streamed file keeps no more (sorting a million values costs 0.13 s)."""

COARSE_CHANCE = 0.05
"""Chance of two neighbours being equal above which held values cannot be told apart. Below it
the chance estimate held within 20 % on quantized white, moving-average and Markov noise (the
last with a correlation of 0.99 a sample); above it, where the differences' MAD is one or two
steps, it fell short by up to a factor three on Markov noise."""

MIN_EXCESS = 2.0
"""Fewest repeats, as a multiple of the chance expectation, worth reporting: ``E`` is itself an
estimate (within about 30 % on simulated quantized noise), and a finding must name an effect
that is there, not a chance count a little above an estimate."""

_MAD_TO_SIGMA = 1.482602218505602
_MAX_LISTED = 100


def _resolution(x: np.ndarray) -> float:
    """Median spacing of the distinct values of ``x``; 0 when it takes a single value."""
    d = np.diff(np.sort(x))
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


class HeldCounter:
    """The count behind :func:`held_samples`, fed block by block in bounded memory: an
    overnight file streamed through ``analyze`` is never held whole.

    ``update`` takes the next samples of the current gap-free segment, ``new_segment`` starts
    another (a pair across a gap is no pair), ``finding`` judges what was counted. The data's
    resolution and the differences' density at zero come from the first
    ``RESOLUTION_SAMPLES`` samples (and their differences); the count, the runs and the longest
    run from every sample.
    """

    def __init__(self) -> None:
        self.n = 0  # samples
        self.pairs = 0  # neighbouring pairs within segments
        self.count = 0  # samples equal to the one before them
        self.runs = 0
        self.longest = 0
        self.first_value = math.nan
        self._last: float | None = None  # last sample of the current segment
        self._run = 0  # length (pairs) of the run still open at the end of the last block
        self._run_start = 0
        self._starts: list[int] = []
        self._lengths: list[int] = []
        self._head: list[np.ndarray] = []  # the first RESOLUTION_SAMPLES samples
        self._head_diffs: list[np.ndarray] = []
        self._head_n = 0

    def new_segment(self) -> None:
        """The next samples start a new gap-free segment."""
        self._close(self._run_start, self._run)
        self._run, self._last = 0, None

    def _close(self, start: int, length: int) -> None:
        """The run of ``length`` pairs from sample ``start`` has ended (none if 0)."""
        if length:
            self._close_many(np.array([start]), np.array([length]))

    def update(self, values: np.ndarray) -> None:
        """Count the next samples of the current segment."""
        v = np.asarray(values, dtype=np.float64)
        if v.size == 0:
            return
        if self.n == 0:
            self.first_value = float(v[0])
        first = self.n  # index of v[0] among all samples
        d = np.diff(v) if self._last is None else np.diff(v, prepend=self._last)
        at = first + v.size - d.size  # index of the later sample of d[0]
        if self._head_n < RESOLUTION_SAMPLES:
            # copies: the head outlives the block it came from, which its caller may reuse
            self._head.append(v[:RESOLUTION_SAMPLES - self._head_n].copy())
            self._head_diffs.append(d[:RESOLUTION_SAMPLES - self._head_n].copy())
            self._head_n += self._head[-1].size
        self.n += v.size
        self.pairs += d.size
        self._last = float(v[-1])
        equal = d == 0
        self.count += int(np.count_nonzero(equal))
        e = np.diff(np.concatenate(([0], equal.view(np.int8), [0])))
        starts = np.flatnonzero(e == 1)
        lengths = np.flatnonzero(e == -1) - starts
        if not starts.size:
            self._close(self._run_start, self._run)
            self._run = 0
            return
        open_end = bool(equal[-1])
        if starts[0] == 0 and self._run:  # the run open at the last block goes on
            lengths[0] += self._run
            starts[0] = self._run_start - at
        else:
            self._close(self._run_start, self._run)
        ended = slice(0, starts.size - 1 if open_end else starts.size)
        self._close_many(at + starts[ended], lengths[ended])
        self._run, self._run_start = (int(lengths[-1]), int(at + starts[-1])) if open_end \
            else (0, 0)

    def _close_many(self, starts: np.ndarray, lengths: np.ndarray) -> None:
        """:meth:`_close` of every run in a block at once (quantized data hold a run every
        few samples: a call per run cost 0.1 s a pass over a 1e6-sample accelerometer)."""
        if not lengths.size:
            return
        self.runs += int(lengths.size)
        self.longest = max(self.longest, int(lengths.max()))
        room = max(_MAX_LISTED - len(self._starts), 0)
        self._starts.extend(int(i) for i in starts[:room])
        self._lengths.extend(int(k) for k in lengths[:room])

    def finding(self, fs_hz: float, alpha: float = 0.05, units: str = "rad/s") -> Finding:
        """The :func:`held_samples` finding of what was counted (runs still open count as
        ended)."""
        starts = self._starts + ([self._run_start] if self._run and len(self._starts)
                                 < _MAX_LISTED else [])
        lengths = self._lengths + ([self._run] if self._run and len(self._lengths)
                                   < _MAX_LISTED else [])
        runs = self.runs + (1 if self._run else 0)
        longest = max(self.longest, self._run)
        return _judge(self, runs, longest, starts, lengths, fs_hz, alpha, units)


def _judge(c: HeldCounter, runs: int, longest: int, starts: list[int], lengths: list[int],
           fs_hz: float, alpha: float, units: str) -> Finding:
    n, count = c.n, c.count
    if n < 3 or c.pairs < 2:
        return Finding("held_samples", None, 0.0, "repeats", 1.0, alpha,
                       why="Too few samples to look for held values.")
    q = _resolution(np.concatenate(c._head))
    g, spread = _density_at_zero(np.concatenate(c._head_diffs))
    params = {"count": float(count), "share": count / n, "longest_s": longest / fs_hz}
    details: dict = {"runs": runs, "longest_samples": longest,
                     "t_s": [float(i / fs_hz) for i in starts],
                     "run_samples": [int(k) for k in lengths],
                     "resolution": q, "spread": spread}
    span = {"t_s": [float(starts[0] / fs_hz), float((starts[-1] + lengths[-1]) / fs_hz)]} \
        if starts else {}
    if count == c.pairs:
        details.update(testable=True, chance_per_pair=None, expected_by_chance=None)
        why = (f"The channel never changes: all {n} samples equal {c.first_value:.6g} {units}. "
               f"A stuck sensor, a disconnected input or a logger repeating one value; there is "
               f"no noise to analyse.")
        return Finding("held_samples", None, float(count), "repeats", 0.0, alpha, params,
                       span, why, details)
    if spread == 0.0:
        details.update(testable=False, chance_per_pair=None, expected_by_chance=None)
        why = (f"The first {min(n, RESOLUTION_SAMPLES)} samples never change, so the data's "
               f"resolution and noise cannot be judged from them; {count} samples "
               f"({100 * count / n:.2g} %) equal the sample before them, the longest run "
               f"{longest} samples ({longest / fs_hz:.3g} s): a sensor that started stuck, or "
               f"one whose noise stays within one step.")
        return Finding("held_samples", None, float(count), "repeats", 1.0, alpha, params,
                       span, why, details)
    chance = min(1.0, q * g)
    expected = chance * c.pairs
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
               f"exactly, in {runs} runs of up to {longest} samples "
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
    counter = HeldCounter()
    for s in segments:
        if len(s):
            counter.new_segment()
            counter.update(s)
    return counter.finding(fs_hz, alpha, units)


def warning_text(found: Finding) -> str | None:
    """The one-line channel warning of a significant held-samples finding, else None: the
    first command a user runs should say when a log repeats values instead of measuring."""
    if not found.significant:
        return None
    return (f"{int(found.params['count'])} samples ({100 * found.params['share']:.2g} %) repeat "
            f"the sample before them exactly, in runs of up to {found.params['longest_s']:.3g} s:"
            f" held values, not measurements (diagnose's held_samples evidence says more)")

