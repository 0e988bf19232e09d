"""Seeded, stateful simulation of the noise terms, block by block with bounded memory.

``NoiseStream(model, fs_hz, seed).take(n)`` returns the next ``n`` samples (SI units) of the sum
of the model's terms. Each term draws from its own child generator of ``seed``, always in sample
order, so a run taken in blocks equals one long run: ``take(1000)`` ten times gives exactly the
samples of a fresh ``take(10000)``. Memory is a few numbers per term whatever the run length.

Each term's simulator lives in its module of :mod:`imunoise.analysis.terms` (``Term.simulator``);
the
docstrings there say how each is drawn. ``bias_instability`` is a sum of first-order Markov
processes across a band of correlation times (:mod:`imunoise.analysis.terms.bias_instability`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from imunoise.analysis.terms import BIAS_INSTABILITY_FACTOR, get_term
from imunoise.analysis.terms.bias_instability import (
    DEFAULT_FLICKER_TMAX_S,
    FLICKER_PER_DECADE,
    flicker_avar,
    flicker_flat_band,
    flicker_psd,
    flicker_times,
)

Model = Sequence[tuple[str, dict[str, float]]]


class NoiseStream:
    """Seeded generator of a noise model's samples, continuing across calls.

    Args:
        model: ``[(term, {param: value})]`` in SI units (see :mod:`imunoise.analysis.terms`).
        fs_hz: sampling rate in Hz.
        seed: seed of the generator (``None``: fresh entropy).
        flicker_band_s: ``(t_min, t_max)`` correlation-time band of the flicker simulator in s
            (``None`` entries: half a sample period and 1e5 s).
    """

    def __init__(self, model: Model, fs_hz: float, seed: int | None = None,
                 flicker_band_s: tuple[float | None, float | None] = (None, None)) -> None:
        if not (fs_hz > 0 and math.isfinite(fs_hz)):
            raise ValueError(f"sampling rate must be positive, got {fs_hz}")
        for name, params in model:
            get_term(name).validate(dict(params), fs_hz)
        self.model = [(name, {k: float(v) for k, v in params.items()})
                      for name, params in model]
        self.fs_hz = float(fs_hz)
        children = np.random.SeedSequence(seed).spawn(len(self.model))
        self._sims = [get_term(name).simulator(params, self.fs_hz, np.random.default_rng(ss),
                                               flicker_band_s=flicker_band_s)
                      for (name, params), ss in zip(self.model, children, strict=True)]
        self.samples_taken = 0

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        """The next ``n`` samples (float64, SI units). ``temperature`` (degC, length n) is
        required when the model holds a ``temperature`` term."""
        n = int(n)
        if n < 0:
            raise ValueError("n must be >= 0")
        noise = np.zeros(n)
        other = np.zeros(n)
        filters = []
        for (name, _), sim in zip(self.model, self._sims, strict=True):
            term = get_term(name)
            if term.kind == "filter":
                filters.append(sim)
            elif term.role == "noise":
                noise += sim.take(n, temperature)
            else:
                other += sim.take(n, temperature)
        for sim in filters:
            # an output filter acts on the Gaussian noise (see
            # imunoise.analysis.terms.output_filter)
            noise = sim.apply(noise)
        self.samples_taken += n
        return noise + other

    def take_terms(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        """Like :meth:`take` but one row per term (shape ``(len(model), n)``)."""
        rows = np.stack([sim.take(int(n), temperature) for sim in self._sims]) if self._sims \
            else np.zeros((0, int(n)))
        self.samples_taken += int(n)
        return rows


def simulate(model: Model, n: int, fs_hz: float, rng: int | np.random.Generator | None = None,
             temperature: np.ndarray | None = None) -> np.ndarray:
    """``n`` samples of ``model`` at ``fs_hz`` in one call (see :class:`NoiseStream`).

    ``rng`` may be a seed or a Generator (a seed is then drawn from it)."""
    seed = int(rng.integers(2**63)) if isinstance(rng, np.random.Generator) else rng
    return NoiseStream(model, fs_hz, seed).take(n, temperature=temperature)


def stream_factory(model: Model, fs_hz: float, seed: int):
    """``take(n)`` of a :class:`NoiseStream`: what a device simulator draws its channels with
    (``imunoise.daq.sim.signals.NoiseFactory``)."""
    return NoiseStream(model, fs_hz, seed).take


__all__ = ["NoiseStream", "simulate", "stream_factory", "flicker_avar", "flicker_times",
           "flicker_flat_band", "flicker_psd", "BIAS_INSTABILITY_FACTOR", "FLICKER_PER_DECADE",
           "DEFAULT_FLICKER_TMAX_S"]
