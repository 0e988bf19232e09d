"""Channels whose spectra have one shape but no signal in common: the chain they pass through.

Two channels that measure different things, or the same thing with independent noise, can
still have spectra of one shape: each sample passed through the same filter before it was
stored (the sensor's decimation filter, a phone's smoothing, a logger's resampling). Their
PSDs then differ by a constant factor at every frequency, while their coherence is zero: the
shape is not a motion they share. A model fitted to one such channel describes that filter as
much as the sensor (resonances and Markov terms in place of a lowpass), and the user should
know before reading physics into it.

On the log-frequency points of the coherence view (:class:`~imunoise.analysis.coherence
.Coherence`), with ``L_i`` the log-PSD of channel i and ``n`` each point's number of averages
(the variance of a log-PSD point is about ``1/n``), a pair (i, j) shares a shape when

- the log-ratio ``L_i - L_j`` is nearly constant: a constant fitted by weights ``n`` leaves
  at most :data:`MAX_UNEXPLAINED` of the weighted variation of either channel's ``L``
  (``explained`` is one minus that share);
- the shape is a shape: each channel's PSD spans at least :data:`MIN_RANGE` (max over min of
  the points with at least :data:`MIN_AVERAGES` averages). White noise, or a spectrum that
  varies by a few tens of per cent, has nothing to share;
- the pair shares no signal that matters: where the coherence passes the zero-coherence test
  (family level), it stays below :data:`MAX_COMMON_POWER`, the share of a point's power one
  channel explains of the other (with tens of thousands of averages a crosstalk of 0.1 % is
  significant and harmless; a shared motion is not this finding,
  :mod:`imunoise.analysis.environment` reads it).

Channels are gathered into groups whose every pair qualifies. Galaxy S5 record
(``../shared/data``, six channels at 10 Hz): every channel, gyroscope and accelerometer, has
the same shape (the PSD falls by a factor of about 240 between 0.01 and 4.5 Hz, with a notch
near 0.43 Hz and a lobe near 0.6 Hz) and no pair has a tenth of any frequency's power in
common (0.096 at most): the record's decimation, not six sensors' physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from itertools import combinations
from typing import Any

import numpy as np

from imunoise.analysis.coherence import Coherence
from imunoise.analysis.environment import channel_kind
from imunoise.analysis.terms import TermError, get_term

MIN_RANGE = 10.0
"""Smallest span (max/min) of a channel's PSD for its shape to count as one."""

MAX_UNEXPLAINED = 0.05
"""Largest share of a channel's log-PSD variation the constant ratio may leave."""

MAX_COMMON_POWER = 0.1
"""Largest coherence (share of a point's power one channel explains of the other) a pair may
have at a coherent point and still share no signal."""

MIN_AVERAGES = 8.0
"""Points with fewer averages are left out of the span (their scatter alone is a factor of a
few)."""


@dataclass(frozen=True)
class PairShape:
    """How far two channels' spectra have one shape.

    Attributes:
        a, b: the channels.
        explained: share of the smaller weighted log-PSD variation of the two that a constant
            ratio explains (1: the same shape).
        ratio: the constant ratio ``PSD_a / PSD_b`` (units_a^2 / units_b^2).
        common_power: the largest coherence among the points where the pair is coherent at
            the family level (0 where none is).
    """

    a: str
    b: str
    explained: float
    ratio: float
    common_power: float


@dataclass(frozen=True)
class SharedShape:
    """Channels whose PSDs have one shape and no coherence.

    Attributes:
        channels: the channels, in the record's order.
        f_lo_hz, f_hi_hz: the band compared (the coherence view's points), Hz.
        span: the smallest of the channels' PSD spans (max/min) over that band.
        explained: the smallest ``explained`` of the group's pairs.
        common_power: the largest ``common_power`` of the group's pairs.
        kinds: the kinds of quantity measured (``gyro``, ``accel``, ...).
        deviance: per channel, the Whittle deviance per point of its PSD against the other
            channels' shape times one constant (about :attr:`deviance_expected` when the
            shape is exactly shared): how far a model made of that shape alone would follow
            it, beside the deviance of a fitted model.
    """

    channels: tuple[str, ...]
    f_lo_hz: float
    f_hi_hz: float
    span: float
    explained: float
    common_power: float
    kinds: tuple[str, ...]
    deviance: dict[str, float] = field(default_factory=dict)

    @property
    def deviance_expected(self) -> float:
        """About what :attr:`deviance` is for channels of exactly one shape: 1, plus the
        scatter of the average of the other channels' spectra (``1/(channels - 1)``)."""
        return 1.0 + 1.0 / max(len(self.channels) - 1, 1)

    def text(self) -> str:
        """One sentence for the user."""
        several = len(set(self.kinds)) > 1
        source = ("channels that measure different quantities share it, which points to "
                  "the chain every sample passes through (a decimation or smoothing filter "
                  "of the sensor or of the recording)") if several else (
                  "it is a filter the channels have in common (the sensor's or the "
                  "recording's) or noise of one origin shaped alike in each")
        return (f"{', '.join(self.channels)} share one spectral shape and no signal: their "
                f"PSDs differ by a constant factor (it explains at least "
                f"{100.0 * self.explained:.1f} % of each one's variation, which spans a "
                f"factor {self.span:.3g} over {self.f_lo_hz:.3g}-{self.f_hi_hz:.3g} Hz) while "
                f"no frequency has more than {100.0 * max(self.common_power, 0.001):.1f} % "
                f"of its power in common between two of them; {source}. The others' shape "
                f"times a constant follows each one's PSD to a Whittle deviance of "
                f"{min(self.deviance.values()):.3g}-{max(self.deviance.values()):.3g} per "
                f"point (about {self.deviance_expected:.2g} for one exact shape). Terms "
                f"fitted to this shape describe that chain, not only the sensing element; "
                f"the chain_filter term takes the chain's response from the other channels "
                f"(--model ...,chain_filter).")

    def to_dict(self) -> dict[str, Any]:
        return {"channels": list(self.channels), "f_hz": [self.f_lo_hz, self.f_hi_hz],
                "span": self.span, "explained": self.explained,
                "common_power": self.common_power, "kinds": list(self.kinds),
                "deviance_per_point": dict(self.deviance),
                "deviance_expected": self.deviance_expected, "text": self.text()}


def _log_psd(co: Coherence) -> tuple[np.ndarray, np.ndarray]:
    """Each channel's log-PSD at the points and its weights, both ``(channels, points)``: a
    point's number of averages, 0 where that channel's PSD there is not positive and finite
    (a constant channel leaves out only itself)."""
    psd = np.asarray(co.psd, dtype=np.float64)
    n = np.asarray(co.n_avg, dtype=np.float64)
    ok = np.isfinite(psd) & (psd > 0.0) & (np.isfinite(n) & (n > 0.0))[None, :]
    logs = np.log(np.where(ok, psd, 1.0))
    return logs, np.where(ok, n[None, :], 0.0)


def _variation(y: np.ndarray, w: np.ndarray) -> float:
    mean = float(np.sum(w * y) / np.sum(w))
    return float(np.sum(w * (y - mean) ** 2))


def pair_shape(co: Coherence, a: str, b: str) -> PairShape:
    """:class:`PairShape` of channels ``a`` and ``b`` of a coherence view."""
    logs, weights = _log_psd(co)
    i, j = co.channels.index(a), co.channels.index(b)
    w = np.minimum(weights[i], weights[j])  # the points both channels have
    if np.sum(w > 0) < 3:
        return PairShape(a, b, math.nan, math.nan, math.nan)
    d = logs[i] - logs[j]
    c = float(np.sum(w * d) / np.sum(w))
    residual = float(np.sum(w * (d - c) ** 2))
    variation = min(_variation(logs[i], w), _variation(logs[j], w))
    explained = 1.0 - residual / variation if variation > 0.0 else math.nan
    k = co.pair(a, b)
    msc = np.asarray(co.msc[k], dtype=np.float64)
    coherent = (msc > np.asarray(co.threshold_family)) & (w > 0)
    common = float(np.max(msc[coherent])) if np.any(coherent) else 0.0
    return PairShape(a, b, explained, math.exp(c), common)


def _span(logs: np.ndarray, n: np.ndarray) -> float:
    keep = n >= MIN_AVERAGES
    if not np.any(keep):
        return math.nan
    return float(math.exp(np.max(logs[keep]) - np.min(logs[keep])))


def shared_shapes(co: Coherence) -> list[SharedShape]:
    """Groups of two or more channels of ``co`` whose every pair has one spectral shape, a
    span of at least :data:`MIN_RANGE` and no signal in common (see the module); largest
    group first, each channel in at most one group."""
    names = list(co.channels)
    if len(names) < 2 or len(co.f_hz) < 3:
        return []
    logs, w = _log_psd(co)
    spans = [_span(logs[k][w[k] > 0], w[k][w[k] > 0]) for k in range(len(names))]
    shaped = [k for k in range(len(names)) if spans[k] >= MIN_RANGE]
    pairs: dict[tuple[int, int], PairShape] = {}
    for i, j in combinations(shaped, 2):
        p = pair_shape(co, names[i], names[j])
        if p.explained >= 1.0 - MAX_UNEXPLAINED and p.common_power <= MAX_COMMON_POWER:
            pairs[(i, j)] = p
    groups: list[list[int]] = []
    taken: set[int] = set()
    # the channel with the most partners first, then every channel that agrees with all of
    # the group so far
    partners = {k: sum(1 for p in pairs if k in p) for k in shaped}
    for k in sorted(shaped, key=lambda k: (-partners[k], k)):
        if k in taken or partners[k] == 0:
            continue
        group = [k]
        for m in shaped:
            if m not in taken and m not in group \
                    and all((min(m, g), max(m, g)) in pairs for g in group):
                group.append(m)
        if len(group) >= 2:
            groups.append(sorted(group))
            taken.update(group)
    out = []
    for g in sorted(groups, key=lambda g: (-len(g), g)):
        members = [pairs[(i, j)] for i, j in combinations(g, 2)]
        both = np.all(w[g] > 0, axis=0)
        if np.sum(both) < 3:  # every pair has points, the whole group too few together
            continue
        f = np.asarray(co.f_hz, dtype=np.float64)[both]
        out.append(SharedShape(
            channels=tuple(names[k] for k in g), f_lo_hz=float(f[0]), f_hi_hz=float(f[-1]),
            span=min(spans[k] for k in g), explained=min(p.explained for p in members),
            common_power=max(p.common_power for p in members),
            kinds=tuple(channel_kind(names[k]) for k in g),
            deviance={names[k]: _deviance_from_others(logs[:, both], w[:, both], g, k)
                      for k in g}))
    return out


def _deviance_from_others(logs: np.ndarray, n: np.ndarray, group: list[int], k: int
                          ) -> float:
    """Whittle deviance per point of channel ``k``'s PSD against the shape of the group's
    other channels times one constant: each other channel brought to ``k``'s level by its
    weighted mean log-ratio, their log-PSDs averaged, the level then set by Whittle's
    estimate. The points' degrees of freedom are ``2 n``."""
    others = [j for j in group if j != k]
    weights = n[k]
    shape = np.mean([logs[j] - np.sum(weights * (logs[j] - logs[k])) / np.sum(weights)
                     for j in others], axis=0)
    u = np.exp(logs[k] - shape)
    u /= np.sum(weights * u) / np.sum(weights)
    return float(np.mean(2.0 * weights * (u - 1.0 - np.log(u))))


def _shapes_spectrum(term: str) -> bool:
    """Whether a suggested term is a spectral shape (a Gaussian noise term or an output
    filter), as opposed to a line, a step, a ramp or a regression."""
    try:
        t = get_term(term)
    except TermError:  # an unknown name is not a shape; the caller names it
        return False
    return t.kind == "filter" or t.role == "noise"


def annotate_shapes(suggestions: dict[str, list[Any]], shapes: list[SharedShape]) -> int:
    """Append to the ``why`` of every suggestion of a shaping term (noise or filter) of a
    channel in a shared-shape group that the term may describe the chain's filter (objects
    or dicts). Returns the number of suggestions annotated."""
    count = 0
    for shape in shapes:
        for channel in shape.channels:
            others = [c for c in shape.channels if c != channel]
            sentence = (f"The channel's spectrum has the shape of {', '.join(others)} with no "
                        f"signal in common (coherence.shared_shapes): this term may describe "
                        f"the filter the samples pass through, not the sensing element.")
            for s in suggestions.get(channel, []):
                term = s.get("term") if isinstance(s, dict) else getattr(s, "term", None)
                if not isinstance(term, str) or not _shapes_spectrum(term):
                    continue
                if isinstance(s, dict):
                    s["why"] = f"{s.get('why', '')} {sentence}".strip()
                else:
                    s.why = f"{getattr(s, 'why', '')} {sentence}".strip()
                count += 1
    return count
