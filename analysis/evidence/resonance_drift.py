"""Does a resonance keep its frequency through the record?

A fitted resonance has one centre frequency. A real one can be tuned by the sensor's
temperature and wander or drift through a night: the ADIS16405's gyro_z peak near 20 Hz sits at
21.7 Hz in the first eight minutes of run 1 and near 19.8 Hz from the second hour on. The
whole record's spectrum then shows the peak smeared over the range it visited, which no single
resonance follows (the PSD part fails), and the halves of the record disagree on ``f0`` (the
hold-out part fails). This test names the cause.

The record is cut into ``n_blocks`` blocks of equal sample count. In each block a Welch
spectrum (Hann, non-overlapping segments fine enough to resolve the peak: bins at most a
quarter of its half-width ``f0/(2Q)``, at least 256 samples) gives the peak's position as the
centroid of the power above the rest of the model, ``sum f (P - S_rest)+ / sum (P - S_rest)+``
over the band ``f0 +- max(4 f0/(2Q), 4 bins)``. Away from a drift the blocks' centroids are
independent draws of one distribution (the resonance's correlation time, ``Q/(pi f0)``, is far
below a block), so their order carries no information. The statistic is von Neumann's ratio
of mean-square successive difference to the variance, about 2 for an unordered sequence and
small when neighbouring blocks agree more than distant ones, as they do along a drift or a slow
wander. Its p-value comes from ``n_permutations`` random orderings of the same centroids
(fixed seed), so it needs no model of the centroids' noise: exact for exchangeable blocks.

The size of the effect: each block's centroid and time; the wander, the centroids' standard
deviation beyond their block-to-block noise (``sqrt(var - d2/2)``, ``d2`` the mean square
successive difference: an upper bound of the noise, so the wander is if anything understated).
A power that changes along the record moves a centroid only through the error of ``S_rest``
within the band, small where the peak stands well above the rest.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from imunoise.analysis.evidence.finding import Finding
from imunoise.analysis.evidence.lines import welch_bins

MIN_BLOCKS = 8
"""Fewest blocks whose centroids are compared; with fewer the permutation test has no power."""

MIN_Q = 2.0
"""Smallest quality factor tested: below it the term's spectrum has no peak to place (none at
all below 1/sqrt(2)), only a hump as wide as its frequency, and its band would take in the
spectrum's other features."""

_MIN_SEGMENTS = 8  # Welch segments per block: a centroid's noise stays well below the peak width


def _blocks(segments: Sequence[np.ndarray], n_blocks: int) -> list[list[np.ndarray]]:
    """The gap-free pieces of each of ``n_blocks`` equal blocks (by sample count) of the
    concatenated record; no piece crosses a gap."""
    lengths = np.array([len(s) for s in segments], dtype=np.int64)
    offsets = np.concatenate([[0], np.cumsum(lengths)])
    edges = np.linspace(0, int(offsets[-1]), n_blocks + 1).round().astype(np.int64)
    out: list[list[np.ndarray]] = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        pieces = []
        for s, off in zip(segments, offsets[:-1], strict=True):
            lo, hi = max(int(a) - int(off), 0), min(int(b) - int(off), len(s))
            if hi > lo:
                pieces.append(np.asarray(s[lo:hi], dtype=np.float64))
        out.append(pieces)
    return out


def von_neumann_ratio(values: np.ndarray) -> float:
    """Mean-square successive difference over the variance (both with ``n - 1`` and ``n``
    terms as in von Neumann's ratio): about 2 for independent values, small along a trend."""
    v = np.asarray(values, dtype=np.float64)
    ss = float(np.sum((v - v.mean()) ** 2))
    return float(np.sum(np.diff(v) ** 2) / ss) if ss > 0 else 2.0


def permutation_p(values: np.ndarray, n_permutations: int = 9999, seed: int = 0) -> float:
    """One-sided p-value of von Neumann's ratio of ``values`` (small: ordered) against random
    orderings of the same values."""
    v = np.asarray(values, dtype=np.float64)
    ss = float(np.sum((v - v.mean()) ** 2))
    if ss <= 0:
        return 1.0
    observed = float(np.sum(np.diff(v) ** 2))
    rng = np.random.default_rng(seed)
    shuffled = v[np.argsort(rng.random((n_permutations, v.size)), axis=1)]
    d2 = np.sum(np.diff(shuffled, axis=1) ** 2, axis=1)
    # a tiny tolerance: ties of the observed order with itself are counted
    return float((1 + np.count_nonzero(d2 <= observed * (1 + 1e-12))) / (n_permutations + 1))


def resonance_drift(segments: Sequence[np.ndarray], fs_hz: float, f0_hz: float, q: float,
                    rest_psd: Callable[[np.ndarray], np.ndarray], n_blocks: int = 20,
                    alpha: float = 0.05, n_permutations: int = 9999, seed: int = 0,
                    tests: int = 1, t0_s: float = 0.0) -> Finding:
    """Test whether the resonance near ``f0_hz`` (quality factor ``q``) keeps its frequency.

    Args:
        segments: gap-free pieces of the channel, SI units, in time order.
        fs_hz: sampling rate, Hz.
        f0_hz, q: the fitted resonance's centre frequency (Hz) and quality factor.
        rest_psd: one-sided PSD (units^2/Hz) of the rest of the model at given frequencies
            (Hz), taken away before the centroid.
        n_blocks: blocks along the record (fewer when the record is too short for the
            resolution the peak needs, down to :data:`MIN_BLOCKS`).
        alpha: significance level.
        n_permutations, seed: the permutation test's orderings and its generator's seed.
        tests: how many resonances are tested at once: the p-value is multiplied by it
            (Bonferroni).
        t0_s: time of the first sample on the scale cuts are given on (``--split``), s.

    Returns:
        Finding of kind ``"resonance_drift"`` (no model term: the remedy is a cut of the record
        or a model of what tunes the resonance). ``params``: ``f0_first_hz``, ``f0_last_hz``
        (mean centroid of the first and of the last quarter of the blocks), ``f0_min_hz``,
        ``f0_max_hz``, ``wander_hz`` (RMS beyond the noise) and ``noise_hz``; ``details``:
        every block's ``t_s`` (centre: ``t0_s`` plus its sample count over the rate, gaps not
        counted) and ``f0_hz`` (NaN where the peak did not stand above the rest), and where the
        centroids' largest change falls: ``split_t_s`` (the start of the block that best cuts
        them into two levels, least squares), ``f0_before_hz``, ``f0_after_hz``.
    """
    fs = float(fs_hz)
    f0, q = float(f0_hz), float(q)
    total = int(sum(len(s) for s in segments))
    name = f"the resonance near {f0:.3g} Hz"

    def untested(reason: str, details: dict | None = None) -> Finding:
        return Finding("resonance_drift", None, 2.0, "von Neumann ratio", 1.0, alpha,
                       why=f"Whether {name} keeps its frequency is not tested: {reason}.",
                       details=details or {})

    if not (math.isfinite(f0) and math.isfinite(q)):
        return untested("its frequency or quality factor is not a number")
    if q < MIN_Q:
        return untested(f"with Q = {q:.2g} it has no peak to place")
    if not 0.0 < f0 < 0.5 * fs:
        return untested(f"it lies outside the sampled band (0 .. {0.5 * fs:.3g} Hz)")
    half_width = f0 / (2.0 * q)
    nperseg = 1 << max(8, math.ceil(math.log2(4.0 * fs / half_width)))
    # a coarser spectrum still places a peak a few bins wide: coarsen before giving up blocks
    while nperseg > 256 and total // (_MIN_SEGMENTS * nperseg) < MIN_BLOCKS:
        nperseg //= 2
    n_blocks = min(int(n_blocks), total // (_MIN_SEGMENTS * nperseg))
    if n_blocks < MIN_BLOCKS:
        return untested(f"the record is too short for {MIN_BLOCKS} blocks that resolve it")
    df = fs / nperseg
    reach = max(4.0 * half_width, 4.0 * df)
    centroids = np.full(n_blocks, np.nan)
    for b, pieces in enumerate(_blocks(segments, n_blocks)):
        if sum(len(p) // nperseg for p in pieces) < _MIN_SEGMENTS // 2:
            continue
        wb = welch_bins(pieces, fs, nperseg)
        band = (wb.f_hz >= max(f0 - reach, 2.0 * df)) & (wb.f_hz <= min(f0 + reach, 0.49 * fs))
        if np.count_nonzero(band) < 4:
            continue
        f, p = wb.f_hz[band], wb.psd[band]
        excess = np.maximum(p - np.asarray(rest_psd(f), dtype=np.float64), 0.0)
        if excess.sum() > 0:
            centroids[b] = float(np.sum(f * excess) / np.sum(excess))
    block_s = total / n_blocks / fs
    t_s = float(t0_s) + (np.arange(n_blocks) + 0.5) * block_s
    ok = np.isfinite(centroids)
    details = {"t_s": t_s.tolist(), "f0_hz": centroids.tolist(), "block_s": block_s,
               "nperseg": nperseg}
    if ok.sum() < MIN_BLOCKS:
        return untested(f"its peak stands above the rest of the model in {int(ok.sum())} of "
                        f"{n_blocks} blocks only", details)
    c = centroids[ok]
    ratio = von_neumann_ratio(c)
    p_value = min(permutation_p(c, n_permutations, seed) * max(int(tests), 1), 1.0)
    noise = math.sqrt(float(np.mean(np.diff(c) ** 2)) / 2.0)
    wander = math.sqrt(max(float(np.var(c)) - noise**2, 0.0))
    name = f"the resonance near {float(np.median(c)):.3g} Hz"
    quarter = max(len(c) // 4, 1)
    first, last = float(c[:quarter].mean()), float(c[-quarter:].mean())
    # the cut into two levels that leaves the least scatter: where a user would split
    cost = [float(np.sum((c[:k] - c[:k].mean()) ** 2) + np.sum((c[k:] - c[k:].mean()) ** 2))
            for k in range(2, len(c) - 1)]
    k = 2 + int(np.argmin(cost))
    split = float(t0_s) + int(np.flatnonzero(ok)[k]) * block_s
    details.update(split_t_s=split, f0_before_hz=float(c[:k].mean()),
                   f0_after_hz=float(c[k:].mean()))
    params = {"f0_first_hz": first, "f0_last_hz": last, "f0_min_hz": float(c.min()),
              "f0_max_hz": float(c.max()), "wander_hz": wander, "noise_hz": noise}
    rng = {"f_hz": [float(c.min()), float(c.max())],
           "t_s": [float(t0_s), float(t0_s) + n_blocks * block_s]}
    how = (f"(peak centroids of {n_blocks} blocks of {block_s:.3g} s; von Neumann ratio "
           f"{ratio:.2f} against about 2, p = {p_value:.2g})")
    finding = Finding("resonance_drift", None, ratio, "von Neumann ratio", p_value, alpha,
                      params, rng, details=details)
    if finding.significant:
        # frequencies to the digit the blocks' noise resolves, so that a small move shows
        d = min(max(1 - math.floor(math.log10(max(noise, 1e-6))), 1), 4)
        finding.why = (f"The frequency of {name} moves through the record: {first:.{d}f} Hz "
                       f"in its first quarter, {last:.{d}f} Hz in its last, between "
                       f"{c.min():.{d}f} and {c.max():.{d}f} Hz, wandering by {wander:.2g} Hz "
                       f"RMS beyond the blocks' own noise ({noise:.2g} Hz) {how}; its largest "
                       f"change falls near t = {split:.0f} s ({c[:k].mean():.{d}f} Hz before, "
                       f"{c[k:].mean():.{d}f} Hz after). One resonance of fixed frequency cannot "
                       "follow it, in the spectrum or from one half of the record to the "
                       f"other: fit the parts apart (--split {split:.0f}) or model what tunes "
                       "it (temperature).")
    else:
        finding.why = f"{name[0].upper()}{name[1:]} keeps its frequency {how}."
    return finding
