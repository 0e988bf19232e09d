"""The response of the filter a record's channels share, measured from the channels themselves.

When several channels of one record have one spectral shape and no signal in common
(:mod:`imunoise.analysis.shared_shape`: a phone's decimation, a logger's smoothing), that shape
is the power response ``|G(f)|^2`` of the chain every sample passed through. No filter of the
vocabulary has it (the Galaxy S5's falls by a factor of about 240 with a notch and a lobe), but
the other channels measure it: the ``chain_filter`` term
(:mod:`imunoise.analysis.terms.chain_filter`) applies it to the channel's noise terms, so a
model describes the sensor's noise seen through the chain instead of imitating the chain with
resonances and Markov terms.

The response (:func:`chain_shape`) is the geometric mean of the other channels' Welch PSDs, each
divided by its median over the reference band ``[fs/500, fs/100]``, on the linear bins of the
coherence view's cross-spectra; below ``fs/100`` it is 1 (what the other channels hold there is
their own bias instability and random walk, which a decimation filter passes). It is measured
from the other channels only, so the channel's own noise is fitted against it, not with it.

The shape in use is a context (:func:`using`): the command that reads the record installs a
:class:`ChainSource` before it fits (it measures the shape when first asked, from a coherence
computed in the background where there is one), and every term evaluation in the same context,
and in the worker processes forked from it, reads it with :func:`current`. The hold-out part
fits each half of the record against that half's own shape (:func:`using_half`).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any

import numpy as np

REFERENCE_BAND = (1.0 / 500.0, 1.0 / 100.0)
"""The band (fractions of the sampling rate) where the shared response is taken as 1."""


@dataclass(frozen=True)
class ChainShape:
    """A measured power response on the bins ``k fs / nperseg``, ``k = 0 .. nperseg/2``.

    Attributes:
        f_hz: bin frequencies in Hz, from 0 to the Nyquist frequency.
        power: ``|G(f)|^2`` at ``f_hz`` (dimensionless, 1 below the reference band).
        fs_hz: sampling rate in Hz.
        channels: the channels it was measured from.
        token: a digest of ``power`` and ``fs_hz`` (the term's caches are keyed by it).
    """

    f_hz: np.ndarray
    power: np.ndarray
    fs_hz: float
    channels: tuple[str, ...]
    token: str

    @classmethod
    def from_power(cls, power: np.ndarray, fs_hz: float, channels: tuple[str, ...]
                   ) -> ChainShape:
        """The shape with ``power`` on ``len(power)`` bins from 0 to ``fs_hz / 2``."""
        p = np.array(power, dtype=np.float64)
        if p.ndim != 1 or p.size < 3 or not np.all(np.isfinite(p)) or np.any(p <= 0.0):
            raise ValueError("a chain shape needs at least 3 positive, finite powers")
        f = np.linspace(0.0, 0.5 * float(fs_hz), p.size)
        for a in (p, f):
            a.setflags(write=False)
        digest = hashlib.sha1(p.tobytes() + np.float64(fs_hz).tobytes()).hexdigest()[:16]
        return cls(f, p, float(fs_hz), tuple(channels), digest)

    def to_dict(self, points: int = 60) -> dict[str, Any]:
        """JSON-ready summary: the channels, the reference band and ``power`` at ``points``
        log-spaced frequencies from the first bin above the reference band to Nyquist."""
        lo = REFERENCE_BAND[1] * self.fs_hz
        f = np.geomspace(lo, 0.5 * self.fs_hz, points)
        return {"channels": list(self.channels), "fs_hz": self.fs_hz,
                "reference_band_hz": [REFERENCE_BAND[0] * self.fs_hz, lo],
                "f_hz": np.round(f, 9).tolist(),
                "power": np.round(self.response(f), 9).tolist()}

    def response(self, f_hz: np.ndarray, depth: float = 1.0) -> np.ndarray:
        """``|G(f)|^(2 depth)`` at ``f_hz`` (Hz); a frequency beyond Nyquist folds back (the
        response of a sampled filter is periodic in ``fs`` and even)."""
        f = np.abs(np.atleast_1d(np.asarray(f_hz, dtype=np.float64)))
        folded = np.abs(np.mod(f + 0.5 * self.fs_hz, self.fs_hz) - 0.5 * self.fs_hz)
        return np.interp(folded, self.f_hz, self.power) ** float(depth)

    def autocorrelation(self, depth: float = 1.0, floor: float = 1.0e-9) -> np.ndarray:
        """``r[-K..K]`` of the zero-phase filter whose power response is ``power^depth``
        (``r[0] = sum g^2``, ``sum r = 1``), cut where ``|r|`` stays below ``floor r[0]``."""
        n = 2 * (self.power.size - 1)
        r = np.fft.irfft(self.power ** float(depth), n=n)
        half = r[: n // 2 + 1]
        big = np.flatnonzero(np.abs(half) >= floor * half[0])
        k_last = int(big[-1]) if big.size else 0
        half = half[: k_last + 1]
        half = half / (half[0] + 2.0 * np.sum(half[1:]))  # unit DC gain after the cut
        return np.concatenate((half[:0:-1], half))

    def impulse_response(self, depth: float = 1.0, floor: float = 1.0e-9) -> np.ndarray:
        """Taps ``g`` (unit sum) of the zero-phase filter whose power response is
        ``power^depth``, cut where ``|g|`` stays below ``floor max|g|`` (for simulation)."""
        n = 2 * (self.power.size - 1)
        g = np.fft.fftshift(np.fft.irfft(np.sqrt(self.power ** float(depth)), n=n))
        keep = np.flatnonzero(np.abs(g) >= floor * np.max(np.abs(g)))
        g = g[keep[0]: keep[-1] + 1] if keep.size else g
        return g / np.sum(g)


def chain_shape(coherence: Any, channel: str) -> ChainShape | None:
    """The response shared by ``channel`` and the other channels of its shape group in the
    coherence view ``coherence`` (:class:`imunoise.analysis.coherence.Coherence`, with its
    linear cross-spectra), measured from those other channels (see the module); None when the
    channel is in no group or the view kept no cross-spectra."""
    from imunoise.analysis.shared_shape import shared_shapes

    cs = getattr(coherence, "cross", None)
    if cs is None:
        return None
    group = next((g for g in shared_shapes(coherence) if channel in g.channels), None)
    if group is None:
        return None
    others = tuple(c for c in group.channels if c != channel)
    fs = float(cs.fs_hz)
    f = np.asarray(cs.f_hz, dtype=np.float64)
    lo, hi = REFERENCE_BAND[0] * fs, REFERENCE_BAND[1] * fs
    band = (f >= lo) & (f <= hi)
    if not np.any(band):
        band = f <= max(hi, float(f[0]))
    logs = []
    for c in others:
        p = np.asarray(cs.psd(c), dtype=np.float64)
        if not np.all(np.isfinite(p) & (p > 0.0)):
            return None
        logs.append(np.log(p) - math.log(float(np.median(p[band]))))
    shape = np.exp(np.mean(logs, axis=0))
    # the full grid k fs/nperseg, k = 0..nperseg/2: the cross-spectra leave out the first
    # two bins and Nyquist
    n_half = int(cs.nperseg) // 2
    grid = np.arange(n_half + 1, dtype=np.float64) * fs / float(cs.nperseg)
    power = np.interp(grid, f, shape)
    power[grid < hi] = 1.0
    return ChainShape.from_power(power, fs, others)


class ChainSource:
    """The record's shared response, measured when first asked: on the whole record
    (``whole()``), or on one half of it (``half(k)``, ``k`` = 0, 1: the first and second
    ``n // 2`` samples; None where a half alone shows no shared shape, which then uses the
    whole record's). Each is measured once."""

    def __init__(self, whole: Callable[[], ChainShape | None],
                 half: Callable[[int], ChainShape | None] | None = None) -> None:
        self._whole, self._half = whole, half
        self._shapes: dict[int | None, ChainShape | None] = {}

    def shape(self, part: int | None = None) -> ChainShape | None:
        """The shape of the whole record (``part`` None) or of half ``part``."""
        if part not in self._shapes:
            whole = self._shapes[None] if None in self._shapes else self._whole()
            self._shapes[None] = whole
            if part is not None:
                own = self._half(part) if whole is not None and self._half is not None \
                    else None
                self._shapes[part] = own if own is not None else whole
        return self._shapes[part]


_CURRENT: ContextVar[tuple[ChainSource, int | None] | None] = ContextVar(
    "imunoise_chain_shape", default=None)


@contextmanager
def using(source: ChainShape | ChainSource | None) -> Iterator[None]:
    """Install ``source`` (a measured shape, a :class:`ChainSource` that measures it when
    first asked, or None) as the record's chain shape for the block."""
    if isinstance(source, ChainShape):
        shape = source
        source = ChainSource(lambda: shape)
    token = _CURRENT.set(None if source is None else (source, None))
    try:
        yield
    finally:
        _CURRENT.reset(token)


@contextmanager
def using_half(k: int) -> Iterator[None]:
    """Within the block, :func:`current` gives half ``k``'s shape (the hold-out part fits
    each half of the record against the response measured on that half, as a fit of that
    half alone would); nothing changes where no source is installed."""
    now = _CURRENT.get()
    token = _CURRENT.set(None if now is None else (now[0], int(k)))
    try:
        yield
    finally:
        _CURRENT.reset(token)


def prepare_halves() -> None:
    """Measure both halves' shapes now (before worker processes are forked, which would each
    measure them again)."""
    now = _CURRENT.get()
    if now is not None:
        for k in (0, 1):
            now[0].shape(k)


def current() -> ChainShape | None:
    """The chain shape installed by :func:`using` (of the half :func:`using_half` names), or
    None."""
    now = _CURRENT.get()
    return None if now is None else now[0].shape(now[1])
