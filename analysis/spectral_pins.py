"""A resonance's centre frequency and quality factor, pinned by the measured spectrum.

The Allan curve sees a resonance as a bump near tau = 1/(2 f0); moving f0 by the peak's own
width changes it by a few per cent, so an Allan fit leaves f0 and Q loose (ADIS16405 gyro_z:
f0 20.4 Hz [20.3, 20.7], Q 20 [12, 1e4]), while the spectrum shows the peak itself. For each
resonance of a fitted model whose f0 and Q are not held, this fits the measured PSD near the
peak by Whittle likelihood; a wandering resonance's ``spread`` (the standard deviation of its
centre frequency) is fitted with them, and an antiresonance's zeros ``fa`` (over a wider band,
f0/4 to 0.49 fs, with the background's white level and plain resonances free: the zeros dig
into a floor that a level alone cannot follow). Two callers use it: the hold-out part compares
each half's peak (:func:`imunoise.analysis.model_error.holdout_part`), and the diagnosis holds
a suggested resonance at the peak where the Allan refit put it elsewhere, and gives a
wandering resonance or an antiresonance offered in a resonance's place its shape
(:mod:`imunoise.analysis.diagnosis`).
The fit itself stays an Allan fit: held at the peak of a drifting, asymmetric real peak, a
resonance follows the Allan curve worse.

The spectrum: a Welch estimate on a fine linear grid (Hann, 50 % overlap, segment
:func:`pin_nperseg`), its bins between f0/2 and min(2 f0, 0.49 fs) (f0 the Allan fit's). The
model there is

    S(f) = c S_rest(f) + S_res(f; sigma, f0, Q)

with S_rest the fitted model's PSD without this resonance (the level ``c``, free, absorbs a
background the Allan fit set a little off) and S_res the resonance's exact discrete-time PSD
(through the model's output filter, if any). The four log-parameters (five with a wander,
its bounds a tenth of a bin and a quarter of the band) minimise the Whittle
deviance ``sum nu (u - 1 - ln u)``, ``u = P/S``.

Intervals: the inverse Gauss-Newton matrix of the deviance residuals (the Whittle Fisher
information), widened by the Hann window's equivalent noise bandwidth in bins (1.5:
neighbouring bins share that much of their data) and by the deviance per degree of freedom
where it exceeds 1. A peak whose shape the term does not follow exactly, such as one whose
frequency drifts through the record, so gets an interval for its mean position that is as wide
as the misfit says, not the width an ideal peak would allow. The peak's power (``sigma``) has
an interval too (:attr:`Pin.sigma_ci95`, widened by :data:`POWER_BINS`): the hold-out part
compares it between the halves.

A pin is kept only where the spectrum resolves a peak: the fitted f0 inside the band (not at
its edge), Q's interval above Q's lower bound (0.5, no peak), and the resonance lowering the
band's deviance by more than the 0.1 % point of chi-square with 3 degrees of freedom, in units
of the dispersion, and for a wandering resonance the interval of ``spread`` above its lower
bound (else the peak is one resonance's). Otherwise the Allan fit's values stand.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy import optimize, special

from imunoise.analysis.psd import welch_psd
from imunoise.analysis.terms import get_term
from imunoise.analysis.terms.registry import model_psd

PINNED = ("f0", "Q", "spread", "fa")
"""The resonance parameters the spectrum pins (``spread`` only a wandering resonance's, ``fa``
only an antiresonance's)."""

PINNED_TERMS = ("resonance", "wandering_resonance", "antiresonance")
"""The terms whose peaks the spectrum pins."""


def pinned_of(params: dict[str, float]) -> dict[str, float]:
    """The pinned parameters among a resonance's ``params``."""
    return {k: v for k, v in params.items() if k in PINNED}

ENBW_BINS = 1.5
"""Equivalent noise bandwidth of the Hann window in bins: the factor neighbouring bins' shared
data widens an interval's variance by."""

POWER_BINS = 1.0 + 2.0 * (4.0 / 9.0 + 1.0 / 36.0)
"""The factor a sum over many bins has its variance widened by: a Hann window's neighbouring
power bins correlate by (2/3)^2, the next but one by (1/6)^2. A resonance's power rests on
every bin of its peak alike, so its interval takes this factor where the shape's take
:data:`ENBW_BINS` (40 simulated records: the power's spread 1.2 times its Fisher deviation
with the ENBW alone)."""

GAIN_LEVEL = 0.001
"""A resonance is resolved when its deviance gain exceeds this upper point of chi-square(3)."""

MIN_Q = 2.0
"""A pinned resonance's Q interval lies above this: a peak at most half an octave wide. A
broader hump is a bend of the spectrum, which the Allan curve sees as well."""

_Z95 = 1.959963984540054
_EDGE = 0.01
"""Log-frequency distance from the band's edge under which f0 counts as at the edge."""


@dataclass(frozen=True)
class Pin:
    """The spectrum's values of one resonance (model index ``index``).

    Attributes:
        index: the term's index in the model.
        params: ``sigma`` (units of the channel), ``f0`` (Hz), ``Q`` (and a wandering
            resonance's ``spread``, Hz) from the PSD fit.
        ci95: 95 % intervals of ``f0`` and ``Q`` (and ``spread``).
        band_hz: the band fitted, Hz.
        deviance_per_dof: the band's Whittle deviance per degree of freedom (about 1 when the
            peak has the term's shape).
        sigma_ci95: 95 % interval of ``sigma`` from the same fit: the peak's power as the
            spectrum measures it, apart from the background level fitted beside it.
    """

    index: int
    params: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    band_hz: tuple[float, float]
    deviance_per_dof: float
    sigma_ci95: tuple[float, float]


def pin_nperseg(n_longest: int) -> int:
    """Welch segment length for the pins: a power of two, at most 2^14 (6 mHz at 100 Hz) and
    at least 16 segments in the longest gap-free stretch; 0 when that stretch is under 4,096
    samples (too short to resolve a peak better than the Allan curve does)."""
    if n_longest < 4096:
        return 0
    return int(min(2 ** 14, 2 ** int(math.floor(math.log2(n_longest / 16)))))


def record_nperseg(n_samples: int, segment_starts: np.ndarray | None) -> int:
    """:func:`pin_nperseg` of a record of ``n_samples`` whose gap-free segments start at
    ``segment_starts`` (None: one segment), from its longest segment."""
    bounds = np.append(np.zeros(1, dtype=np.int64) if segment_starts is None
                       else np.asarray(segment_starts, dtype=np.int64), n_samples)
    return pin_nperseg(int(np.max(np.diff(bounds))) if n_samples else 0)


def _deviance_residuals(p: np.ndarray, nu: np.ndarray, s: np.ndarray) -> np.ndarray:
    u = p / np.maximum(s, 1e-300)
    d = nu * (u - 1.0 - np.log(u))
    return np.sign(u - 1.0) * np.sqrt(np.maximum(d, 0.0))


def _one(index: int, model: list[tuple[str, dict[str, float]]], f: np.ndarray, p: np.ndarray,
         nu: np.ndarray, fs: float) -> Pin | None:
    name, params = model[index]
    term = get_term(name)
    f0a = float(params["f0"])
    # an anti-resonance's band reaches two octaves below the peak and up to Nyquist: the
    # floor its zeros dig into is shaped by terms (a broad resonance) that one octave
    # leaves loose (ADIS16405 run 1 gyro_z: fa 15.2 Hz over one octave, where the Allan
    # refit then trades the white level to zero; 14.7 Hz over this band, Allan 2.21)
    lo_hz, hi_hz = (f0a / 4.0, 0.49 * fs) if "fa" in term.param_names \
        else (f0a / 2.0, min(2.0 * f0a, 0.49 * fs))
    sel = (f >= lo_hz) & (f <= hi_hz)
    if np.count_nonzero(sel) < 40 or hi_hz <= lo_hz:
        return None
    fb, pb, nub = f[sel], p[sel], nu[sel]
    rest = [(n, q) for k, (n, q) in enumerate(model) if k != index]
    s_rest = model_psd(rest, fb, fs)
    if not np.all(np.isfinite(s_rest)) or np.any(s_rest <= 0):
        return None

    q_lo = term.param("Q").lo
    df = float(fb[1] - fb[0])
    # sigma, f0, Q, the term's own (spread: from a tenth of a bin to a quarter of the band;
    # fa: within the band), background level
    extras = {"spread": (0.1 * df, 0.25 * (hi_hz - lo_hz)), "fa": (lo_hz, hi_hz)}
    own = [k for k in extras if k in term.param_names]
    # an anti-resonance's zeros dig into the floor under the peak: the floor's own terms
    # (white level, other resonances) are fitted with it, not only scaled
    flex = _flexible_background(rest, fs) if "fa" in own else []
    k_flex = 3 + len(own)
    lo_b = np.log([1e-30, lo_hz, q_lo] + [extras[k][0] for k in own]
                  + [lo for _, _, lo, _ in flex] + [1.0 - 1e-6 if flex else 0.2])
    hi_b = np.log([1e6, hi_hz, 1e4] + [extras[k][1] for k in own]
                  + [hi for _, _, _, hi in flex] + [1.0 + 1e-6 if flex else 5.0])
    flexed = sorted({i for i, _, _, _ in flex})
    fixed_rest = [t for k, t in enumerate(rest) if k not in flexed]
    filters = [t for t in rest if get_term(t[0]).kind == "filter"]
    if flex:
        s_rest = model_psd(fixed_rest, fb, fs) \
            if any(get_term(n).kind != "filter" for n, _ in fixed_rest) else np.zeros(fb.size)

    def shape_of(theta: np.ndarray) -> dict[str, float]:
        v = np.exp(theta)
        out = {"sigma": float(v[0]), "f0": float(v[1]), "Q": float(v[2])}
        out.update({k: float(v[3 + n]) for n, k in enumerate(own)})
        return out

    def spectrum(theta: np.ndarray) -> np.ndarray:
        if flex:
            moved = [(n, dict(q)) for n, q in rest]
            for (i, key, _, _), v in zip(flex, np.exp(theta[k_flex:-1]), strict=True):
                moved[i][1][key] = float(v)
            free = [moved[i] for i in flexed]
            # the long-tau terms' level is flat across the band: held as the Allan fit has it
            return s_rest + model_psd(free + filters + [(name, shape_of(theta))], fb, fs)
        with_res = model_psd(rest + [(name, shape_of(theta))], fb, fs)
        return math.exp(float(theta[-1])) * s_rest + (with_res - s_rest)

    def resid(theta: np.ndarray) -> np.ndarray:
        return _deviance_residuals(pb, nub, spectrum(theta))

    # starts: the Allan fit's peak, and the band's largest excess over the background
    ratio = np.convolve(pb / s_rest, np.ones(9) / 9.0, mode="same")
    f_peak = float(fb[int(np.argmax(ratio))])
    sig0 = max(float(params["sigma"]), 1e-12)
    starts = [(sig0, f0a, float(params["Q"])), (sig0, f_peak, 10.0)]
    x0s = []
    for s0, f00, q0 in starts:
        q0 = max(q0, q_lo * 1.01)
        first = {"spread": 0.5 * f00 / q0, "fa": 0.8 * f00}
        x0 = [float(params.get(k, first[k])) for k in own] \
            + [max(float(rest[i][1][key]), 1e-12) for i, key, _, _ in flex]
        x0s.append(np.clip(np.log([s0, f00, q0] + x0 + [1.0]), lo_b + 1e-9, hi_b - 1e-9))
    best = _least_deviance(resid, x0s, lo_b, hi_b)
    if best is None:
        return None
    theta = best.x
    n_dof = max(len(fb) - theta.size, 1)
    dev1 = 2.0 * float(best.cost)
    disp = max(1.0, dev1 / n_dof)

    # without the resonance: the background level alone
    def resid0(lc: np.ndarray) -> np.ndarray:
        return _deviance_residuals(pb, nub, math.exp(float(lc[0])) * s_rest)

    sol0 = optimize.least_squares(resid0, np.zeros(1), bounds=([math.log(0.2)],
                                                               [math.log(5.0)]))
    gain = (2.0 * float(sol0.cost) - dev1) / disp
    if gain <= 2.0 * float(special.gammainccinv(1.5, GAIN_LEVEL)):
        return None
    sd = _pin_sd(np.asarray(best.jac, dtype=np.float64), disp, level_free=not flex,
                 first_background=k_flex)
    if sd is None:
        return None
    ci = _resolved_intervals(theta, sd, lo_b, hi_b, own)
    if ci is None:
        return None
    sd_power = sd[0] * math.sqrt(POWER_BINS / ENBW_BINS)  # sigma is always kept: sd[0] > 0
    sigma_ci = (math.exp(theta[0] - _Z95 * sd_power), math.exp(theta[0] + _Z95 * sd_power))
    return Pin(index, shape_of(theta), ci, (float(fb[0]), float(fb[-1])), dev1 / n_dof,
               sigma_ci)


def _pin_sd(jac: np.ndarray, disp: float, level_free: bool, first_background: int
            ) -> np.ndarray | None:
    """Standard deviations of the pin's log-parameters from the deviance residuals' Jacobian
    (the last column the background level, left out where it is held; a background
    parameter from column ``first_background`` on whose column vanishes, a level at its
    bound, is left out too, its deviation 0), or None where the information matrix is
    singular."""
    n = jac.shape[1]
    norms = np.sqrt(np.sum(jac * jac, axis=0))
    keep = np.ones(n, dtype=bool)
    keep[first_background:n - 1] = norms[first_background:n - 1] > 1e-10 * norms.max()
    keep[n - 1] = level_free
    try:
        cov = np.linalg.inv(jac[:, keep].T @ jac[:, keep]) * ENBW_BINS * disp
    except np.linalg.LinAlgError:
        return None
    var = np.diag(cov)
    if not (np.all(np.isfinite(var)) and np.all(var > 0.0)):
        return None
    sd = np.zeros(n)
    sd[keep] = np.sqrt(var)
    return sd


def _flexible_background(rest: list[tuple[str, dict[str, float]]], fs: float
                         ) -> list[tuple[int, str, float, float]]:
    """``(index in rest, parameter, lower, upper bound)`` of the background's parameters an
    anti-resonance's pin fits with it: the white level and each plain resonance's power,
    centre and width (a broad one shapes the floor the zeros dig into). The long-tau terms
    stay as the Allan fit has them: across the band they are flat and would trade with the
    white level."""
    out: list[tuple[int, str, float, float]] = []
    for i, (n, _) in enumerate(rest):
        if n == "white":
            out.append((i, "N", 1e-30, 1e6))
        elif n == "resonance":
            out += [(i, "sigma", 1e-30, 1e6), (i, "f0", 1e-3 * fs, 0.49 * fs),
                    (i, "Q", get_term(n).param("Q").lo, 1e4)]
    return out


def _least_deviance(resid: Any, starts: list[np.ndarray], lo: np.ndarray, hi: np.ndarray
                    ) -> Any:
    """The bounded least-squares solution of ``resid`` with the least cost over ``starts``,
    or None where none converges to a finite cost."""
    best = None
    for x0 in starts:
        try:
            sol = optimize.least_squares(resid, x0, bounds=(lo, hi), method="trf",
                                         x_scale=1.0, max_nfev=200)
        except (ValueError, FloatingPointError):
            continue
        if best is None or sol.cost < best.cost:
            best = sol
    return best if best is not None and np.isfinite(best.cost) else None


def _resolved_intervals(theta: np.ndarray, sd: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                        own: Sequence[str] = ()) -> dict[str, tuple[float, float]] | None:
    """95 % intervals of the pinned parameters from the log-parameters ``theta`` and their
    standard deviations (``own``: the term's parameters beyond sigma, f0 and Q, from
    ``theta[3]`` on), or None where the spectrum does not resolve the peak: f0 at the
    band's edge, Q's interval below :data:`MIN_Q`, a wander whose interval reaches its
    lower bound (the peak is then one resonance's), or an anti-resonance whose interval
    reaches the band's edge (no dip within it)."""
    lf0, lq = theta[1], theta[2]
    if (lf0 - lo[1] < _EDGE or hi[1] - lf0 < _EDGE
            or lq - _Z95 * sd[2] < math.log(MIN_Q)):
        return None
    ci = {"f0": (math.exp(lf0 - _Z95 * sd[1]), math.exp(lf0 + _Z95 * sd[1])),
          "Q": (math.exp(lq - _Z95 * sd[2]), math.exp(min(lq + _Z95 * sd[2], hi[2])))}
    for n, k in enumerate(own, start=3):
        v, s = theta[n], sd[n]
        if v - _Z95 * s <= lo[n] + _EDGE or (k == "fa" and v + _Z95 * s >= hi[n] - _EDGE):
            return None
        ci[k] = (math.exp(v - _Z95 * s), math.exp(min(v + _Z95 * s, hi[n])))
    return ci


def remembered_welch(values: np.ndarray, fs_hz: float, nperseg: int,
                     segment_starts: np.ndarray | None, memo: dict | None) -> Any:
    """The Welch estimate of ``values`` (:func:`imunoise.analysis.psd.welch_psd`), kept in
    ``memo`` (shared by the fits of one series) by segment length; None where no gap-free
    segment holds ``nperseg`` samples."""
    key = ("welch", id(values), nperseg)
    if memo is not None and key in memo:
        return memo[key]
    try:
        est = welch_psd(np.asarray(values, dtype=np.float64), fs_hz, nperseg=nperseg,
                        segment_starts=segment_starts)
    except ValueError:
        return None
    if memo is not None:
        memo[key] = est
    return est


def pin_resonances(values: np.ndarray, fs_hz: float, model: Sequence[tuple[str, dict]],
                   held: set[tuple[int, str]], segment_starts: np.ndarray | None = None,
                   memo: dict | None = None) -> list[Pin]:
    """The spectrum's f0 and Q of each resonance in a fitted ``model`` (``[(term, params)]``
    in model order, regressors included) that the user did not hold (``held``: ``(index,
    param)`` pairs), in model order; resonances whose peak the spectrum does not resolve are
    left out. ``memo`` (shared by fits of one series) keeps the Welch estimate."""
    noise = [(i, n, dict(p)) for i, (n, p) in enumerate(model)
             if get_term(n).role != "regressor"]
    targets = [i for i, n, _ in noise if n in PINNED_TERMS
               and not any((i, k) in held for k in PINNED)]
    if not targets:
        return []
    nperseg = record_nperseg(len(values), segment_starts)
    if nperseg == 0:
        return []
    est = remembered_welch(values, fs_hz, nperseg, segment_starts, memo)
    if est is None:
        return []
    # positions in the noise-only model used by the spectrum
    work = [(n, p) for _, n, p in noise]
    pos = {i: k for k, (i, _, _) in enumerate(noise)}
    pins: list[Pin] = []
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        # the most prominent peak first: a broad resonance standing in for a bend must not
        # take the peak a sharper one of the same model describes
        targets.sort(key=lambda i: -_prominence(work, pos[i], float(fs_hz)))
        for i in targets:
            pin = _one(pos[i], work, est.f_hz, est.psd,
                       np.broadcast_to(np.asarray(est.dof, dtype=np.float64), est.psd.shape),
                       float(fs_hz))
            if pin is None:
                continue
            work[pos[i]] = (work[pos[i]][0], dict(pin.params))
            pins.append(replace(pin, index=i))
    pins.sort(key=lambda p: p.index)
    return pins


def _prominence(model: list[tuple[str, dict[str, float]]], k: int, fs: float) -> float:
    """Resonance ``k``'s PSD at its centre frequency over the rest of the model's there."""
    f0 = np.array([float(model[k][1]["f0"])])
    rest = model_psd([m for j, m in enumerate(model) if j != k], f0, fs)[0]
    own = model_psd([model[k]], f0, fs)[0]
    return float(own / rest) if rest > 0 else math.inf
