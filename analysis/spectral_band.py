"""The band of a model's resonances, fitted to the measured spectrum as a whole.

A resonance above fs/8 shows on the Allan curve only at its first three octave points: the
curve sees the band's total power, not how it is shared between the peak, a second mode
beside it, a shelf above it and the output filter's roll-off. The spectrum sees each. On the
ADIS16405 gyro_z nights (a mode near 17-21 Hz that wanders through the night, a shelf near
24 Hz, the output filter's fall towards Nyquist) the Allan fit's resonances miss the spectrum
by a Whittle deviance of 22-178 per bin; the band fitted here, held in the model, brings it
to 1.1-2.2 on the five nights where the diagnosis's loop takes it.

The spectrum: a Welch estimate (Hann, half-overlapping segments, the dof the overlap leaves)
with bins at most :data:`BIN_WIDTH` of the lowest peak's centre apart, from ``f_lo``
(:data:`BAND_EDGE` of that centre: the Allan curve's shortest taus hold the power of the
skirts down to there) to 0.49 fs. The model there is the fitted model's PSD with the long-tau
terms (flicker, random walk, Markov terms, lines) as the Allan fit has them and the band's
terms (the white level, the resonances, the output filter) free; their log-parameters
minimise the Whittle deviance ``sum nu (u - 1 - ln u)``, ``u = P/S``, as
:mod:`imunoise.analysis.spectral_pins` does for one peak.

The structures tried, each from the given model's band terms (a mode: a resonance with Q at
least :data:`PEAK_Q`; a wandering mode's Q is bounded below by it and a shelf is a plain
resonance, so the two do not trade roles from one round to the next):

- the given terms refitted to the spectrum;
- each mode as a wandering resonance (its centre moves through the record; the spectrum holds
  the smeared peak), a bend (Q under :data:`NARROW_Q`) restarted as a shelf above the peak;
- that with a second wandering mode beside the strongest, where none lies within
  :data:`MODE_NEAR` of it (two modes of one part, or one mode that sits at two frequencies for
  parts of the night);
- each of these with a shelf, where the band has no resonance beside its modes;
- each of these behind a moving-average output filter, where the model has no filter.

A larger structure is kept where it lowers the deviance beyond the 0.1 % point of
chi-square with the parameters it adds, in units of its own deviance per degree of freedom
(the dispersion) and of :data:`BIN_CORRELATION`. The result holds every band parameter at
the spectrum's value (the powers too: the Allan curve cannot share the band's power between
terms); the white level and the long-tau terms are left to the Allan refit.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from imunoise.analysis.distributions import chi2
from imunoise.analysis.spectral_pins import record_nperseg, remembered_welch
from imunoise.analysis.terms import get_term
from imunoise.analysis.terms.registry import model_psd

Model = list[tuple[str, dict[str, float]]]

SHORT_TAU_BAND = 0.125
"""Lowest centre frequency of a narrow resonance that makes a band, as a fraction of the
sampling rate: the Allan curve shows a resonance at f0 near tau = 1/(2 f0), so above fs/8
only its first three octave points (1, 2 and 4 samples) see the band at all."""

NARROW_Q = 2.0
"""A resonance with a quality factor at least this makes a band (below it, it is a bend and
starts again as the shelf)."""

PEAK_Q = 8.0
"""A narrow resonance with a quality factor at least this is a mode (made wandering); one
between :data:`NARROW_Q` and this is a shelf and stays a resonance."""

RESONANT = ("resonance", "wandering_resonance")

BIN_CORRELATION = 1.5
"""Hann bins share data with their neighbours: the deviance's fall counts as this many
times fewer independent bins (the window's equivalent noise bandwidth in bins)."""

LEVEL = 1e-3
"""Significance of a larger structure's fall of the deviance."""

SHELF_RATIO, SHELF_Q = 1.2, 5.0
"""Where a shelf starts (a bend of the given model restarted, or a shelf added): above the
strongest mode by this ratio, with this quality factor."""

WANDER_Q, WANDER_SPREAD = 50.0, 0.025
"""A wandering mode starts with at least this quality factor and a wander of this fraction
of its centre (the second mode twice that)."""

MODE_NEAR = 0.1
"""A second mode is tried only where no other mode lies within this fraction of the
strongest one's centre already."""

MODE_OFFSET = 0.02
"""Two wandering modes start this fraction of the peak's centre below and above it."""

BAND_EDGE = 0.1
"""The band starts at this fraction of the lowest narrow resonance's centre: the Allan curve's
shortest taus hold the power of the resonances' skirts down to there."""

BIN_WIDTH = 0.005
"""Welch bins are at most this fraction of the lowest narrow resonance's centre apart."""


@dataclass(frozen=True)
class BandFit:
    """The spectrum's model of a record's resonance band.

    Attributes:
        replaced: indices in the given model of the terms the band's terms replace (its
            resonances and output filter).
        terms: the band's terms ``[(term, params)]``, every parameter from the spectrum.
        white_n: the white level the spectrum gives beside them (units/sqrt(Hz)); the
            Allan refit sets the model's.
        band_hz: the band fitted, Hz.
        deviance_per_bin: the band's Whittle deviance per bin with these terms.
        given_deviance_per_bin: the same with the given model's band terms refitted to the
            spectrum (the structure the Allan fit chose).
        added: parameters the band's terms have beyond the given model's.
        structure: a short description (e.g. ``"moving_average, 2 wandering modes"``).
    """

    replaced: tuple[int, ...]
    terms: Model
    white_n: float
    band_hz: tuple[float, float]
    deviance_per_bin: float
    given_deviance_per_bin: float
    added: int
    structure: str


def _bounds(name: str, key: str, value: float, f_lo: float, fs: float) -> tuple[float, float]:
    """Log bounds of one band parameter."""
    if key == "f0":
        return math.log(0.25 * f_lo), math.log(0.49 * fs)
    if key == "Q":
        # a wandering resonance is a mode; a shelf is a plain resonance's (the two do not
        # trade roles between rounds)
        low = PEAK_Q if name == "wandering_resonance" else get_term(name).param("Q").lo
        return math.log(low), math.log(1e4)
    if key == "spread":
        return math.log(1e-3 * f_lo), math.log(0.25 * fs)
    if key == "taps":
        return 0.0, math.log(64.0)
    # any other parameter (a power, a level, a filter's cutoff) within the term's own
    # physical bounds and twelve e-folds of its start
    v = max(value, 1e-300)
    param = get_term(name).param(key)
    lo = math.log(param.lo) if param.lo > 0.0 else -math.inf
    hi = math.log(param.hi) if math.isfinite(param.hi) else math.inf
    return max(math.log(v) - 12.0, lo + 1e-9), min(math.log(v) + 12.0, hi - 1e-9)


def _fit(rest: Model, band: Model, f: np.ndarray, p: np.ndarray, nu: np.ndarray, fs: float,
         f_lo: float) -> tuple[Model, float] | None:
    """``band`` (every parameter free) fitted beside ``rest`` (held) to the Welch bins: the
    fitted band terms and the deviance, or None where no fit converges."""
    keys = [(i, k) for i, (_, ps) in enumerate(band) for k in ps]
    x0 = np.array([math.log(max(float(band[i][1][k]), 1e-300)) for i, k in keys])
    limits = np.array([_bounds(band[i][0], k, float(band[i][1][k]), f_lo, fs)
                       for i, k in keys])
    lo, hi = limits[:, 0], limits[:, 1]
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)

    def terms(theta: np.ndarray) -> Model:
        out = [(n, dict(ps)) for n, ps in band]
        for (i, k), v in zip(keys, theta, strict=True):
            out[i][1][k] = float(np.exp(v))
        return out

    def resid(theta: np.ndarray) -> np.ndarray:
        s = model_psd(rest + terms(theta), f, fs)
        u = p / np.maximum(s, 1e-300)
        d = nu * (u - 1.0 - np.log(u))
        return np.sign(u - 1.0) * np.sqrt(np.maximum(d, 0.0))

    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            sol = optimize.least_squares(resid, x0, bounds=(lo, hi), method="trf",
                                         diff_step=1e-4, max_nfev=400)
    except (ValueError, FloatingPointError, ArithmeticError):
        return None
    if not np.isfinite(sol.cost):
        return None
    return terms(sol.x), float(2.0 * sol.cost)


def _structures(band: Model, has_filter: bool) -> list[tuple[str, Model]]:
    """The band structures tried (see the module text), the given one first."""
    narrow = [i for i, (n, ps) in enumerate(band)
              if n in RESONANT and float(ps["Q"]) >= NARROW_Q]
    peaks = [i for i in narrow if float(band[i][1]["Q"]) >= PEAK_Q] or narrow
    strongest = max(peaks, key=lambda i: float(band[i][1]["sigma"]))
    f_peak = float(band[strongest][1]["f0"])
    wandering = [(n, dict(ps)) for n, ps in band]
    for i, (n, ps) in enumerate(band):
        if i in peaks and n == "resonance":
            # the Allan fit's width is the wander's: the peak itself starts sharp
            wandering[i] = ("wandering_resonance",
                            {**ps, "Q": max(float(ps["Q"]), WANDER_Q),
                             "spread": WANDER_SPREAD * float(ps["f0"])})
        elif n == "resonance" and i not in narrow:
            # a broad resonance the Allan fit placed as a bend starts as the shelf above
            # the peak that the spectrum shows (the Allan curve cannot place it)
            wandering[i] = (n, {**ps, "f0": SHELF_RATIO * f_peak, "Q": SHELF_Q})
    out = [("wandering modes", wandering)]
    beside = [i for i in peaks if i != strongest
              and abs(float(band[i][1]["f0"]) / f_peak - 1.0) < MODE_NEAR]
    if not beside:
        # two modes start either side of the one peak, the upper one wider (a mode that
        # spends part of the night higher wanders more there on the ADIS16405)
        n, ps = wandering[strongest]
        pair = list(wandering)
        pair[strongest] = (n, {**ps, "f0": (1.0 - MODE_OFFSET) * float(ps["f0"])})
        second = ("wandering_resonance", {
            "sigma": 0.7 * float(ps["sigma"]), "f0": (1.0 + MODE_OFFSET) * float(ps["f0"]),
            "Q": float(ps["Q"]), "spread": 2.0 * WANDER_SPREAD * float(ps["f0"])})
        out.append(("2 wandering modes", pair + [second]))
    if not any(n in RESONANT and i not in peaks for i, (n, ps) in enumerate(band)):
        # no resonance beside the peaks (a bend or a shelf): the shelf is a term of its own
        sigma = 0.5 * float(band[strongest][1]["sigma"])
        shelf = ("resonance", {"sigma": sigma, "f0": SHELF_RATIO * f_peak, "Q": SHELF_Q})
        out += [(f"{label}, shelf", terms + [shelf]) for label, terms in out]
    out.insert(0, ("as fitted", [(n, dict(ps)) for n, ps in band]))
    if not has_filter:
        out += [(f"moving_average, {label}", [("moving_average", {"taps": 1.5})] + terms)
                for label, terms in out]
    return out


def _welch_band(values: np.ndarray, fs: float, segment_starts: np.ndarray | None,
                memo: dict | None, f_lo: float, f_narrow: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """``(f, psd, dof)`` of the Welch bins from ``f_lo`` to 0.49 fs, their spacing at most
    :data:`BIN_WIDTH` of ``f_narrow`` (Hz); None where the record is too short for them."""
    fine = 2 ** int(math.ceil(math.log2(fs / (BIN_WIDTH * f_narrow))))
    nperseg = min(record_nperseg(len(values), segment_starts), fine)
    if nperseg < 64:
        return None
    est = remembered_welch(values, fs, nperseg, segment_starts, memo)
    if est is None:
        return None
    f = np.asarray(est.f_hz, dtype=np.float64)
    keep = (f >= f_lo) & (f <= 0.49 * fs)
    if np.count_nonzero(keep) < 20:
        return None
    nu = np.broadcast_to(np.asarray(est.dof, dtype=np.float64), est.psd.shape)
    return f[keep], np.asarray(est.psd, dtype=np.float64)[keep], nu[keep]


def _size(m: Model) -> int:
    return sum(len(ps) for _, ps in m)


def _chosen(results: list[tuple[str, Model, float]], n_bins: int) -> tuple[str, Model, float]:
    """The structure kept: from the given one (first), each larger one in turn where it
    lowers the deviance beyond :data:`LEVEL` for the parameters it adds (see the module
    text); one no larger where its deviance is lower."""
    best = results[0]
    independent = n_bins / BIN_CORRELATION
    for cand in sorted(results[1:], key=lambda r: _size(r[1])):
        k = _size(cand[1]) - _size(best[1])
        if k <= 0:
            if cand[2] < best[2]:
                best = cand
            continue
        disp = max(cand[2] / n_bins, 1.0)
        if (best[2] - cand[2]) / n_bins * independent / disp > float(chi2.isf(LEVEL, k)):
            best = cand
    return best


def band_fit(values: np.ndarray, fs_hz: float, model: Sequence[tuple[str, dict]],
             segment_starts: np.ndarray | None = None, memo: dict | None = None
             ) -> BandFit | None:
    """The spectrum's model of the band of ``model``'s narrow resonances (see the module
    text), or None where the model has no narrow resonance, the record is too short for a
    spectrum that resolves the band, or no structure can be fitted.

    Args:
        values: the channel (SI units).
        fs_hz: sampling rate, Hz.
        model: the fitted model ``[(term, params)]``, regressors included (they are left out
            of the spectrum's model).
        segment_starts: starts of the gap-free segments, samples.
        memo: a dict shared by the fits of one series (keeps the Welch estimate).
    """
    fs = float(fs_hz)
    where = [i for i, (n, _) in enumerate(model) if get_term(n).role != "regressor"]
    noise = [(model[i][0], dict(model[i][1])) for i in where]
    narrow = [f0 for n, f0, q in ((n, float(ps["f0"]), float(ps["Q"])) for n, ps in noise
                                  if n in RESONANT)
              if q >= NARROW_Q and f0 >= SHORT_TAU_BAND * fs]
    if not narrow:
        return None
    f_lo = BAND_EDGE * min(narrow)
    # a broad resonance below the band bends the floor the band stands on: it is fitted too
    in_band = [i for i, (n, ps) in enumerate(noise)
               if (n in RESONANT and float(ps["f0"]) >= 0.25 * f_lo)
               or get_term(n).kind == "filter"]
    white = [i for i, (n, _) in enumerate(noise) if n == "white"]
    if not white:
        return None
    bins = _welch_band(values, fs, segment_starts, memo, f_lo, min(narrow))
    if bins is None:
        return None
    f, p, nu = bins
    rest = [t for i, t in enumerate(noise) if i not in in_band and i != white[0]]
    band = [noise[white[0]]] + [noise[i] for i in in_band]
    has_filter = any(get_term(n).kind == "filter" for n, _ in band)
    results: list[tuple[str, Model, float]] = []
    for label, terms in _structures(band[1:], has_filter):
        fitted = _fit(rest, [band[0]] + terms, f, p, nu, fs, f_lo)
        if fitted is not None:
            results.append((label, fitted[0], fitted[1]))
    if not results or results[0][0] != "as fitted":
        return None
    given, best = results[0], _chosen(results, f.size)
    return BandFit(replaced=tuple(where[i] for i in in_band), terms=best[1][1:],
                   white_n=float(best[1][0][1]["N"]), band_hz=(float(f_lo), 0.49 * fs),
                   deviance_per_bin=best[2] / f.size,
                   given_deviance_per_bin=given[2] / f.size,
                   added=_size(best[1]) - _size(given[1]), structure=best[0])
