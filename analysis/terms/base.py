"""What a term of a noise model is: the :class:`Term` base class and its :class:`Param`.

A term knows everything the rest of the package needs about it: its parameters (SI units,
physical ranges, fit bounds), its exact sampled-data Allan variance, its one-sided PSD, its
role in the covariance of the Allan estimates, a seeded block-by-block simulator, its
discrete-time states, its explanation, which estimators support it and which parameter is its
amplitude. One term per module in this package; :mod:`imunoise.analysis.terms.registry` collects
them
and :mod:`imunoise.analysis.terms.spec` parses the model strings users write.

Sampling model (what "exact" means here). A rate sample ``y_k`` is the average of the
continuous rate over its sampling interval (integrate-and-dump, as the decimation filter of a
MEMS sensor approximately does). Parameters are in SI units of the channel: for a gyro channel
rad/s; for an accelerometer the same with rad replaced by m/s. Spectral densities are
one-sided (units^2/Hz over 0..fs/2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from imunoise.core.errors import InputError

if TYPE_CHECKING:
    from imunoise.analysis.discrete import DiscreteModel


class TermError(InputError):
    """Unknown term, unknown parameter, or a parameter outside its physical range."""


@dataclass(frozen=True)
class Param:
    """One parameter of a term.

    ``kind`` selects its unit for a channel (see :func:`param_unit`): ``"rate/sqrt(Hz)"``,
    ``"angle"``, ``"rate"``, ``"rate/sqrt(s)"``, ``"rate/s"``, ``"s"``, ``"Hz"``, ``"rate/degC"``,
    ``"samples"`` (a filter length in samples), ``"ratio"`` (dimensionless, e.g. a quality
    factor).
    ``lo``/``hi`` bound physically meaningful values in SI units (``lo`` exclusive when
    ``lo_open``); a frequency (kind ``"Hz"``) is further limited to the Nyquist frequency.
    """

    name: str
    kind: str
    lo: float
    hi: float
    description: str
    lo_open: bool = True

    def upper(self, fs_hz: float | None = None) -> float:
        """Largest physical value; a frequency stops at the Nyquist frequency ``fs_hz/2``."""
        if self.kind == "Hz" and fs_hz is not None:
            return min(self.hi, fs_hz / 2.0)
        return self.hi

    def log_fit_bounds(self, fs_hz: float, duration_s: float) -> tuple[float, float]:
        """Bounds of ``ln(value)`` in the Allan fit: a time between a fifth of a sample and
        50 record lengths, a frequency between half a cycle per record and Nyquist, a length in
        samples between 1 and its upper limit, any other
        (amplitude-like) parameter between 1e-30 and 1e6 channel units."""
        if self.kind == "s":
            return math.log(0.2 / fs_hz), math.log(max(50.0 * duration_s, 1.0 / fs_hz))
        if self.kind == "Hz":
            return math.log(0.5 / duration_s), math.log(0.5 * fs_hz)
        if self.kind in ("samples", "ratio"):
            return math.log(max(self.lo, 1e-300)), math.log(self.hi)
        return math.log(1e-30), math.log(1e6)

    @property
    def is_scale(self) -> bool:
        """True for a time, frequency or length (a shape parameter, never "consistent with
        zero")."""
        return self.kind in ("s", "Hz", "samples", "ratio")


_RATE_UNITS = {"rad/s": ("rad", "rad/s^2"), "m/s^2": ("m/s", "m/s^3"), "deg/s": ("deg",
                                                                              "deg/s^2")}


def param_unit(param: Param, channel_units: str = "rad/s") -> str:
    """Unit string of a parameter for a channel whose samples are in ``channel_units``."""
    angle, ramp = _RATE_UNITS.get(channel_units, (f"{channel_units}*s", f"{channel_units}/s"))
    return {
        "rate/sqrt(Hz)": f"{channel_units}/sqrt(Hz)",
        "angle": angle,
        "rate": channel_units,
        "rate/sqrt(s)": f"{channel_units}/sqrt(s)",
        "rate/s": ramp,
        "s": "s",
        "Hz": "Hz",
        "samples": "samples",
        "ratio": "1",
        "rate/degC": f"{channel_units}/degC",
    }[param.kind]


class TermSimulator:
    """Seeded, stateful simulator of one term: :meth:`take` returns the next ``n`` samples
    (SI units), always drawing in sample order so blocks concatenate to one long run."""

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        raise NotImplementedError


class Term:
    """Base class of a model term. Subclasses set the class attributes and implement
    :meth:`_avar` and :meth:`_psd` (and :meth:`simulator`, :meth:`add_discrete` where they
    can be simulated or discretised).

    Class attributes:
        name: the name users write in ``--model``.
        order: position in the vocabulary (the contract's table order; new terms 100+).
        params: its parameters, in the order of the contract.
        amplitude: the parameter whose square scales the Allan variance and PSD.
        linear: True when the Allan variance is a fixed shape times ``amplitude^2`` (no
            other parameter), so starting values come from one linear solve.
        kind: ``"additive"`` (its Allan variance and PSD add to the others') or ``"filter"``
            (it multiplies the PSD of the noise terms; see docs/terms.md).
        role: how it enters the covariance of the Allan estimates
            (:mod:`imunoise.analysis.misfit`): ``"noise"`` (Gaussian, through its PSD), ``"line"``
            (a deterministic sinusoid: :meth:`line`), ``"ramp"`` (a deterministic drift:
            :meth:`ramp_slope`) or ``"regressor"`` (removed from the series before the Allan
            curve is computed; no Allan variance of its own).
        continuous_psd: False for a term whose spectrum is a line (not drawn as a density).
        repeatable: the model may hold it more than once (each occurrence independent).
        live: usable by the bounded-memory live service (not one that needs a whole record).
        needs_record: name of an auxiliary record the term needs (``"temperature"``), or None.
        estimators: estimators that support it: ``"allan"`` (the Allan-curve fit) and
            ``"block_likelihood"`` (the exact likelihood of :mod:`imunoise.analysis.likelihood`).
        avar_extras: extra keyword arguments :meth:`avar`/:meth:`psd` accept beside the
            parameters (e.g. the temperature record's Allan variance).
        allan_signature, effect, explanation: user-facing text.
        small_default: starting parameters of a term that is new to a warm-started fit.
        reduces_to: the simpler term this one resembles when the fit does not resolve its
            defining feature (see :meth:`unresolved`), or None.
        replaces: the term this one refines, or None: the diagnosis offers it only in that
            term's place, where the evidence shows what it adds (a wandering resonance for a
            resonance whose peak moves through the record), never as a term of its own.
    """

    name: ClassVar[str]
    order: ClassVar[float] = 100.0
    params: ClassVar[tuple[Param, ...]]
    amplitude: ClassVar[str]
    linear: ClassVar[bool] = False
    kind: ClassVar[str] = "additive"
    role: ClassVar[str] = "noise"
    continuous_psd: ClassVar[bool] = True
    repeatable: ClassVar[bool] = False
    live: ClassVar[bool] = True
    needs_record: ClassVar[str | None] = None
    estimators: ClassVar[frozenset[str]] = frozenset({"allan"})
    avar_extras: ClassVar[tuple[str, ...]] = ()
    allan_signature: ClassVar[str]
    effect: ClassVar[str]
    explanation: ClassVar[str]
    small_default: ClassVar[dict[str, float]]
    reduces_to: ClassVar[str | None] = None
    replaces: ClassVar[str | None] = None

    # --- vocabulary --------------------------------------------------------------------------
    def usable(self) -> bool:
        """Whether the term can be evaluated here (a term measured from the record's other
        channels needs them; see :mod:`imunoise.analysis.chain_shape`)."""
        return True

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def param(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise TermError(f"{self.name} has no parameter {name!r}; expected "
                        f"{', '.join(self.param_names)}")

    @property
    def shape_params(self) -> tuple[str, ...]:
        """Parameters other than the amplitude (a Markov time, a frequency)."""
        return tuple(p.name for p in self.params if p.name != self.amplitude)

    def resolved(self, name: str, ci95: tuple[float, float] | None) -> bool:
        """Whether parameter ``name`` with 95 % interval ``ci95`` is an estimate: the
        amplitude of a term that vanishes at zero (not a filter's length or cutoff) is not
        when its interval reaches zero or is undefined; other parameters, and one without
        an interval, are shown as they are."""
        if ci95 is None or self.kind == "filter" or name != self.amplitude:
            return True
        lo, hi = float(ci95[0]), float(ci95[1])
        if math.isnan(lo) or math.isnan(hi):
            return False
        return lo > 0.0 or hi < 0.0  # a signed amplitude (a temperature coefficient) too

    def check(self, params: dict[str, float]) -> dict[str, float]:
        """``params`` when they name exactly this term's parameters (extras allowed)."""
        allowed = set(self.param_names) | set(self.avar_extras)
        unknown = set(params) - allowed
        if unknown:
            raise TermError(f"{self.name}: unknown parameter(s) {', '.join(sorted(unknown))}; "
                            f"expected {', '.join(self.param_names)}")
        missing = set(self.param_names) - set(params)
        if missing:
            raise TermError(f"{self.name}: missing parameter(s) {', '.join(sorted(missing))}")
        return params

    def validate(self, params: dict[str, float], fs_hz: float | None = None,
                 partial: bool = False) -> None:
        """Raise :class:`TermError` naming a parameter that is missing (unless ``partial``),
        unknown, not finite or outside its physical range."""
        if partial:
            for k in params:
                self.param(k)
        else:
            self.check(params)
        for k, v in params.items():
            if k in self.avar_extras:
                continue
            p = self.param(k)
            v = float(v)
            hi = p.upper(fs_hz)
            bad_lo = v <= p.lo if p.lo_open else v < p.lo
            if not math.isfinite(v) or bad_lo or v > hi:
                lo_txt = f"({p.lo:g}" if p.lo_open else f"[{p.lo:g}"
                raise TermError(f"{self.name}.{p.name} = {v:g} outside its physical range "
                                f"{lo_txt}, {hi:g}]")

    def log_fit_bounds(self, param: Param, fs_hz: float, duration_s: float
                       ) -> tuple[float, float]:
        """Bounds of ``ln(value)`` of ``param`` in the Allan fit (see
        :meth:`Param.log_fit_bounds`; a term may narrow them)."""
        return param.log_fit_bounds(fs_hz, duration_s)

    # --- Allan variance and spectrum ---------------------------------------------------------
    def avar(self, tau_s: np.ndarray | float, fs_hz: float, **params: Any) -> np.ndarray:
        """Allan variance (units^2) at averaging times ``tau_s`` (s) for data sampled at
        ``fs_hz`` (Hz)."""
        tau = np.atleast_1d(np.asarray(tau_s, dtype=np.float64))
        return self._avar(tau, float(fs_hz), **self.check(params))

    def psd(self, f_hz: np.ndarray | float, fs_hz: float, **params: Any) -> np.ndarray:
        """One-sided power spectral density (units^2/Hz) at frequencies ``f_hz`` (Hz)."""
        f = np.atleast_1d(np.asarray(f_hz, dtype=np.float64))
        return self._psd(f, float(fs_hz), **self.check(params))

    def avar_fast(self, tau: np.ndarray, fs_hz: float, params: dict[str, float]
                  ) -> np.ndarray:
        """:meth:`avar` without argument checks, for the inner loop of a fit."""
        return self._avar(tau, fs_hz, **params)

    def unit_avar(self, tau: np.ndarray, fs_hz: float, shape: dict[str, float]) -> np.ndarray:
        """Allan variance with the amplitude at 1 and the other parameters at ``shape``."""
        return self._avar(tau, fs_hz, **{self.amplitude: 1.0, **shape})

    def _avar(self, tau: np.ndarray, fs: float, **params: Any) -> np.ndarray:
        raise NotImplementedError

    def autocovariance(self, fs_hz: float, params: dict[str, float]) -> np.ndarray | None:
        """Autocovariance ``R(0), R(1), ...`` (units^2) of the sampled term when it vanishes
        beyond a few lags (white noise: one lag; quantization: two), else None. An output
        filter uses it to filter the term exactly in the time domain."""
        return None

    def _psd(self, f: np.ndarray, fs: float, **params: Any) -> np.ndarray:
        raise NotImplementedError

    # --- filters (kind == "filter") ---------------------------------------------------------
    def response(self, f: np.ndarray, fs_hz: float, params: dict[str, float]) -> np.ndarray:
        """Power response ``|H(f)|^2`` of a ``kind == "filter"`` term at ``f`` (Hz): the PSD of
        every ``role == "noise"`` term is multiplied by it."""
        raise NotImplementedError

    def filtered_avar(self, noise: list[tuple[Term, dict[str, float]]], tau: np.ndarray,
                      fs_hz: float, params: dict[str, float]) -> np.ndarray:
        """Allan variance (units^2) of the ``noise`` terms seen through this filter."""
        raise NotImplementedError

    def filtered_parts(self, noise: list[tuple[Term, dict[str, float]]], tau: np.ndarray,
                       fs_hz: float, params: dict[str, float]
                       ) -> tuple[np.ndarray, list[np.ndarray]]:
        """:meth:`filtered_avar` and each noise term's part of it, in the order given."""
        raise NotImplementedError

    # --- covariance of the Allan estimates (see imunoise.analysis.misfit)
    # -------------------------------
    def line(self, params: dict[str, float]) -> tuple[float, float]:
        """``(amplitude, frequency_hz)`` of a ``role == "line"`` term."""
        raise NotImplementedError

    def ramp_slope(self, params: dict[str, float]) -> float:
        """Slope (units/s) of a ``role == "ramp"`` term."""
        raise NotImplementedError

    # --- what the diagnosis may claim ---------------------------------------------------------
    def unresolved(self, params: dict[str, float],
                   ci95: dict[str, tuple[float, float]]) -> str | None:
        """Why a fit of this term does not resolve the feature that gives it its name (a
        clause for the diagnosis's text), or None when it does. The diagnosis then prefers
        :attr:`reduces_to`, the simpler term it becomes without that feature, when that one
        is significant too."""
        return None

    def refinement_reason(self, old: str, shape: dict[str, float]) -> str:
        """Why the diagnosis offers this term (a refinement, :attr:`replaces`) in the place of
        the model's term labelled ``old``, its shape ``shape`` taken from the spectrum."""
        return f"A {self.name} may describe {old} better."

    # --- starting values of the Allan fit ----------------------------------------------------
    def start_shapes(self, fs_hz: float, duration_s: float,
                     line: tuple[float, float] | None) -> list[dict[str, float]]:
        """Candidate values of the shape parameters (non-amplitude) for the starting-value
        grid search of the Allan fit; ``line`` is the strongest spectral line
        ``(f_hz, amplitude)`` when one was found. Linear terms have one empty candidate."""
        return [{}]

    def start_amplitude(self, fitted: float, line: tuple[float, float] | None) -> float:
        """Starting amplitude given the linear solve's value ``fitted`` (zero when the solve
        left the term out)."""
        return fitted

    # --- simulation and discrete-time states -------------------------------------------------
    def simulator(self, params: dict[str, float], fs_hz: float, rng: np.random.Generator,
                  **options: Any) -> TermSimulator:
        """A seeded simulator of this term (see :mod:`imunoise.analysis.noise_stream`)."""
        raise TermError(f"{self.name} cannot be simulated")

    def add_discrete(self, dm: DiscreteModel, params: dict[str, float]) -> None:
        """Add this term's discrete-time states at the sample period to ``dm``
        (see :mod:`imunoise.analysis.discrete`)."""
        raise TermError(f"{self.name} has no discrete-time model")

    def __repr__(self) -> str:
        return f"<term {self.name}>"
