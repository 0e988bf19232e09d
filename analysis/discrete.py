"""Filter-ready discrete-time noise models at the sample period, and their simulator.

A fitted continuous model (docs/terms.md terms, SI parameters) becomes, at the sample period
``dt = 1/fs``, the set of difference equations a Kalman filter designer needs:

=================  ==============================================  ============================
term               discrete model (k = sample index)               exact Allan variance, m = tau fs
=================  ==============================================  ============================
white N            v_k ~ N(0, sigma_d^2), sigma_d = N sqrt(fs)     sigma_d^2 / m  (= N^2/tau)
quantization Q     (e_k - e_{k-1}) / dt, e_k ~ N(0, Q^2)           3 Q^2 / tau^2
random_walk K      b_{k+1} = b_k + w_k, w_k ~ N(0, K^2 dt)         K^2 dt (2 m^2 + 1) / (6 m)
gauss_markov s, T  x_{k+1} = a_d x_k + w_k, a_d = exp(-dt/T),      AR(1) closed form, see
                   w_k ~ N(0, s^2 (1 - a_d^2))                     :func:`markov_avar`
bias_instability   sum of a few gauss_markov states (see below)   their sum
rate_ramp R        deterministic R t                               R^2 tau^2 / 2
sinusoid A, f      deterministic A sin(2 pi f t + phi)             A^2 sin^4(pi f tau) /
                                                                   (m sin(pi f dt))^2
temperature coef   deterministic coef (temp - mean)                not simulated without a record
=================  ==============================================  ============================

Bias instability (flicker, Allan variance flat at (2 ln2/pi) B^2) has no finite-state model.
It is replaced by a small sum of first-order Markov states whose correlation times are
log-spaced from a quarter of the shortest measured averaging time (but not below the sample
period) to the longest, at one per decade to start. Their stationary variances are fitted by
non-negative least squares so the Allan variance of the whole discrete model matches the
continuous model, with residuals weighted by the whole model's Allan variance (the
approximation only has to be good where bias instability matters). The density rises by half a
state per decade (to at most three) until the largest relative error of the whole model's Allan
variance on a fine grid over the measured tau range is below ``tolerance`` (default 2 %, i.e.
about 1 % in deviation), far inside the measurement's confidence band. A bias instability whose
share of the model's Allan variance stays below 1e-4 everywhere in the range gets no states.
The result records the states, the tau range and that error.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import nnls

from imunoise.analysis.terms import TermError, get_term
from imunoise.analysis.terms.gauss_markov import TERM as GAUSS_MARKOV
from imunoise.analysis.terms.gauss_markov import MarkovState, markov_state
from imunoise.analysis.terms.random_walk import sampled_walk_avar as random_walk_avar

# Relative share of the model's Allan variance below which bias instability gets no states.
NEGLIGIBLE_FLICKER = 1e-4


def markov_avar(tau_s: np.ndarray, fs_hz: float, sigma: float, T_s: float) -> np.ndarray:
    """Exact overlapping Allan variance (units^2) of a sampled first-order Markov sequence
    with stationary standard deviation ``sigma`` and correlation time ``T_s`` (the
    ``gauss_markov`` term's)."""
    return GAUSS_MARKOV.avar(tau_s, fs_hz, sigma=sigma, T=T_s)


def flat_flicker_avar(tau_s: np.ndarray, B: float) -> np.ndarray:
    """The bias-instability plateau (2 ln2/pi) B^2 on ``tau_s`` (units^2)."""
    return get_term("bias_instability").avar(tau_s, 1.0, B=B)


@dataclass(frozen=True)
class FlickerApproximation:
    """How the bias-instability term was replaced by Markov states.

    Attributes:
        B: the continuous bias instability (channel units).
        tau_range_s: averaging-time range over which the approximation is fitted.
        states_per_decade: density of correlation times used.
        max_rel_avar_error: largest |approx - model| / model of the whole model's Allan
            variance on the fit grid (dimensionless).
    """

    B: float
    tau_range_s: tuple[float, float]
    states_per_decade: float
    max_rel_avar_error: float


@dataclass
class DiscreteModel:
    """Discrete-time noise model of one channel at the sample period.

    The measured sample is ``y_k = v_k + (e_k - e_{k-1})/dt + b_k + sum_j x_{j,k} + d(t_k)``:
    white measurement noise ``v``, quantization ``e``, random-walk bias ``b``, Markov states
    ``x_j`` and deterministic parts ``d``.

    Attributes:
        fs_hz: sample rate (Hz); ``dt_s = 1/fs_hz``.
        units: SI units of the channel (e.g. ``rad/s``).
        white_sigma: std of ``v_k`` (units), ``N sqrt(fs)``.
        quantization_sigma: std of the angle error ``e_k`` (units * s), i.e. ``Q``.
        random_walk_step: std of the bias step per sample (units), ``K sqrt(dt)``.
        markov: Markov states (gauss_markov terms and the bias-instability approximation).
        ramp_rate: deterministic rate ramp ``R`` (units/s).
        sinusoids: ``(A, f_hz)`` pairs (units, Hz).
        temperature_coef: units per degC (not simulated without a temperature record).
        flicker: how bias instability was approximated, when present.
    """

    fs_hz: float
    units: str = ""
    white_sigma: float = 0.0
    quantization_sigma: float = 0.0
    random_walk_step: float = 0.0
    markov: list[MarkovState] = field(default_factory=list)
    ramp_rate: float = 0.0
    sinusoids: list[tuple[float, float]] = field(default_factory=list)
    temperature_coef: float = 0.0
    flicker: FlickerApproximation | None = None
    flicker_B: float = 0.0
    """Bias instability still to be approximated (set while terms are added)."""

    @property
    def dt_s(self) -> float:
        return 1.0 / self.fs_hz

    def avar(self, tau_s: np.ndarray) -> np.ndarray:
        """Exact Allan variance of this discrete model at ``tau_s`` (s), units^2.

        Sum over independent parts; the temperature term is omitted (it depends on the record).
        """
        tau = np.asarray(tau_s, dtype=np.float64)
        fs = self.fs_hz
        out = get_term("white").avar(tau, fs, N=self.white_sigma / np.sqrt(fs))
        out = out + get_term("quantization").avar(tau, fs, Q=self.quantization_sigma)
        # the discrete state is a point-sampled walk, not the continuous model's averaged one
        out = out + random_walk_avar(tau, fs, self.random_walk_step * np.sqrt(fs))
        for st in self.markov:
            out = out + markov_avar(tau, fs, st.sigma, st.T_s)
        out = out + get_term("rate_ramp").avar(tau, fs, R=self.ramp_rate)
        for amp, f in self.sinusoids:
            out = out + get_term("sinusoid").avar(tau, fs, A=amp, f=f)
        return out.reshape(np.shape(tau))

    def to_dict(self) -> dict:
        """JSON-ready description (the ``discrete_model`` key of ``analyze --json``)."""
        d: dict = {
            "fs_hz": self.fs_hz,
            "dt_s": self.dt_s,
            "units": self.units,
            "white_sigma": self.white_sigma,
            "quantization_sigma": self.quantization_sigma,
            "random_walk_step": self.random_walk_step,
            "markov": [
                {"term": s.term, "T_s": s.T_s, "sigma": s.sigma, "a_d": s.a_d,
                 "driving_sigma": s.driving_sigma}
                for s in self.markov
            ],
            "ramp_rate": self.ramp_rate,
            "sinusoids": [{"A": a, "f_hz": f} for a, f in self.sinusoids],
            "temperature_coef": self.temperature_coef,
            "bias_instability_approximation": None,
        }
        if self.flicker is not None:
            fl = self.flicker
            d["bias_instability_approximation"] = {
                "B": fl.B, "tau_range_s": list(fl.tau_range_s),
                "states_per_decade": fl.states_per_decade,
                "max_rel_avar_error": fl.max_rel_avar_error,
            }
        return d


def _normalise(model) -> list[tuple[str, dict[str, float]]]:
    """Accept ``[(term, params)]`` or contract JSON ``[{"term": ..., "params": {...}}]``."""
    out = []
    for item in model:
        if isinstance(item, Mapping):
            out.append((str(item["term"]), {k: float(v) for k, v in item["params"].items()}))
        else:
            term, params = item
            out.append((str(term), {k: float(v) for k, v in dict(params).items()}))
    return out


def discretize(
    model,
    fs_hz: float,
    units: str = "",
    tau_range_s: tuple[float, float] | None = None,
    flicker_avar: Callable[[np.ndarray, float], np.ndarray] | None = None,
    tolerance: float = 0.02,
    max_states_per_decade: float = 3.0,
) -> DiscreteModel:
    """Discrete-time model at ``dt = 1/fs_hz`` of a fitted continuous model.

    Args:
        model: ``[(term, params)]`` or contract JSON ``[{"term", "params"}]``, SI parameters.
        fs_hz: sample rate in Hz.
        units: channel units, carried along for display.
        tau_range_s: measured averaging-time range (s) over which the bias-instability
            approximation must hold; default ``(1/fs, 3600 s)``.
        flicker_avar: Allan variance of the bias-instability term as ``f(tau_s, B)``; default
            the plateau (2 ln2/pi) B^2.
        tolerance: largest relative error of the whole model's Allan variance allowed for the
            bias-instability approximation.
        max_states_per_decade: cap on the density of Markov states.

    Raises:
        ValueError: unknown term, non-positive rate or empty tau range.
    """
    if not fs_hz > 0:
        raise ValueError(f"sample rate must be positive, got {fs_hz}")
    terms = _normalise(model)
    dm = DiscreteModel(fs_hz=float(fs_hz), units=units)
    for term, p in terms:
        try:
            get_term(term).add_discrete(dm, p)
        except TermError as exc:
            raise ValueError(str(exc)) from None
    bias_b = dm.flicker_B
    if bias_b > 0:
        _approximate_flicker(dm, bias_b, tau_range_s, flicker_avar, tolerance,
                             max_states_per_decade)
    return dm


def _approximate_flicker(dm: DiscreteModel, B: float, tau_range_s, flicker_avar, tolerance: float,
                         max_density: float) -> None:
    fs = dm.fs_hz
    lo, hi = tau_range_s if tau_range_s is not None else (1.0 / fs, 3600.0)
    lo = max(float(lo), 1.0 / fs)
    hi = float(hi)
    if not hi > lo:
        raise ValueError(f"empty tau range for the bias-instability approximation: {lo}..{hi} s")
    decades = np.log10(hi / lo)
    tau = np.logspace(np.log10(lo), np.log10(hi), max(int(np.ceil(16 * decades)) + 1, 8))
    target = (flicker_avar or flat_flicker_avar)(tau, B)
    total = dm.avar(tau) + target  # the continuous model's Allan variance on the grid
    negligible = float(np.max(target / total))
    if negligible < NEGLIGIBLE_FLICKER:
        # Bias instability this far below the other terms needs no state: leaving it out
        # changes the model's Allan variance by at most ``negligible`` (relative).
        dm.flicker = FlickerApproximation(B=B, tau_range_s=(lo, hi), states_per_decade=0.0,
                                          max_rel_avar_error=negligible)
        return
    t_lo, t_hi = max(lo / 4.0, 1.0 / fs), hi
    best = None
    density = 1.0
    while True:
        n = max(2, int(np.ceil(np.log10(t_hi / t_lo) * density)) + 1)
        T = np.logspace(np.log10(t_lo), np.log10(t_hi), n)
        design = np.column_stack([markov_avar(tau, fs, 1.0, t) for t in T]) / total[:, None]
        var, _ = nnls(design, target / total)
        err = float(np.max(np.abs(design @ var - target / total)))
        if best is None or err < best[0]:
            best = (err, T, var, density)
        if err <= tolerance or density >= max_density:
            break
        density += 0.5
    err, T, var, density = best
    for t, v in zip(T, var, strict=True):
        if v > 0:
            dm.markov.append(markov_state("bias_instability", float(np.sqrt(v)), float(t), fs))
    dm.flicker = FlickerApproximation(B=B, tau_range_s=(lo, hi), states_per_decade=density,
                                      max_rel_avar_error=err)


def simulate(dm: DiscreteModel, n: int, seed: int | np.random.Generator | None = None,
             temperature: np.ndarray | None = None) -> np.ndarray:
    """``n`` samples (channel units) of the discrete model, vectorised.

    Markov states start from their stationary distribution, the random walk from zero, the
    sinusoids at a random phase. ``temperature`` (degC, length ``n``) drives the temperature
    term when given; otherwise that term is left out.
    """
    from scipy.signal import lfilter  # slow to import: see analysis.dsp

    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    n = int(n)
    y = np.zeros(n)
    if n == 0:
        return y
    t = np.arange(n) / dm.fs_hz
    if dm.white_sigma > 0:
        y += dm.white_sigma * rng.standard_normal(n)
    if dm.quantization_sigma > 0:
        e = dm.quantization_sigma * rng.standard_normal(n + 1)
        y += np.diff(e) * dm.fs_hz
    if dm.random_walk_step > 0:
        y += np.cumsum(dm.random_walk_step * rng.standard_normal(n))
    for st in dm.markov:
        w = st.driving_sigma * rng.standard_normal(n)
        w[0] = st.sigma * rng.standard_normal()
        y += lfilter([1.0], [1.0, -st.a_d], w)
    if dm.ramp_rate:
        y += dm.ramp_rate * t
    for amp, f in dm.sinusoids:
        y += amp * np.sin(2.0 * np.pi * f * t + rng.uniform(0.0, 2.0 * np.pi))
    if temperature is not None and dm.temperature_coef:
        temp = np.asarray(temperature, dtype=np.float64)
        if temp.shape != (n,):
            raise ValueError(f"temperature must have {n} samples, got {temp.shape}")
        y += dm.temperature_coef * (temp - temp.mean())
    return y
