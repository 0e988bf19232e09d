"""Environment or sensor: are the lines and resonances the diagnosis finds shared by channels?

The per-channel diagnosis (:mod:`imunoise.analysis.diagnosis`) looks at one channel at a time; a
line it asks to model as a sinusoid may be the bench moving, seen by every axis at once. This
module takes several channels' diagnoses and the record's cross-spectra
(:mod:`imunoise.analysis.coherence`) and classifies each spectral feature:

- ``common``: coherent with at least one other channel beyond the zero-coherence test's
  threshold (level ``alpha``, Sidak over the channels tried) *and* with the lower bound of the
  coherence interval above one half: most of the feature's power in this channel is explained
  linearly by the other channel: the environment (motion of the bench, a pump, the air
  conditioning) or an electronic source the channels share. For a line standing at least 1.2
  times above its channel's floor (the median PSD of the 42 bins around it) the continuum is
  taken out first: the share of the line's own power that the other channel explains is
  ``(C S_ii - E) / (S_ii - floor_i)``, ``E`` the median of what the other channel explains
  (``|S_ij|^2 / S_jj``) in those bins, the continuum taken as known. A weak common line is then
  not called own because its bin also holds noise, nor a weak own line common because the
  continuum under it is (several sensors sharing broadband bench noise).
- ``own``: the upper bound of every pair's interval (as a share of the line's power) lies below
  one half: most of the feature's power is the channel's own (a small coherent part may still
  be significant; it is stated).
- ``mixed``: neither (an interval straddles one half).

A line is judged at the Welch bin where the channel's PSD peaks within 1.5 bins of its
frequency; a resonance over its half-power band ``f0 (1 +- 1/(2Q))`` (at least one bin), the
cross-spectra summed over the band with the number of averages that stands for. The MSC
distribution assumed is that of Gaussian data; for a deterministic line it is approximate.

Physical reading of a common feature (accelerometers in m/s^2, gyros in rad/s):

- the accelerometer axes' common part (the principal component of their cross-spectral matrix
  summed over the feature) gives the motion's amplitude and direction in the sensor's axes and
  whether the axes move in phase;
- a *tilt* of the bench rotates the gravity vector, so the change is perpendicular to gravity
  (the mean of the accelerometer axes); its amplitude ratios between axes are those of that
  projection;
- a *rotation* of the bench shows in the gyros and the accelerometers together: a rate of
  amplitude ``W`` at ``f`` tilts gravity by ``W / (2 pi f)`` rad, an acceleration of
  ``|W x g| / (2 pi f)``; the ratio of that to the measured accelerometer amplitude says how
  much of the line the rotation explains;
- otherwise a linear vibration of the bench along the direction found, or an electrical source
  shared by the axes;
- coherent with the temperature: the environment's temperature; with a channel of another
  device on the bench: the environment, not either sensor.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from imunoise.analysis.coherence import (
    DEFAULT_ALPHA,
    CrossSpectra,
    _msc,
    msc_interval,
    msc_threshold,
)

STANDARD_GRAVITY = 9.80665
"""m/s^2, used when the accelerometer means are not given."""

MAJORITY = 0.5
"""Coherence above which most of a feature's power is shared (the common/own boundary)."""

LINE_TERMS = ("sinusoid", "resonance")

LINE_OVER_FLOOR = 1.2
"""A line this many times above its channel's floor is judged on its own power (what the
other channel explains of the continuum around it taken out); weaker, on the bin's
coherence as it is."""
_FLOOR_BINS = 24  # bins either side whose median PSD is a line's floor
_TILT_ANGLE_DEG = 70.0  # a tilt's change lies at 90 deg from gravity; this far off still counts


@dataclass(frozen=True)
class SpectralFeature:
    """A line or band one channel's diagnosis found.

    Attributes:
        channel: the channel's name.
        term: ``"sinusoid"`` or ``"resonance"``.
        f_hz: its frequency (the resonance's f0), Hz.
        band_hz: the band examined, Hz.
        source: ``"suggestion"`` (a suggested term) or ``"spectral_line"`` (a line the
            spectral evidence lists).
    """

    channel: str
    term: str
    f_hz: float
    band_hz: tuple[float, float]
    source: str = "suggestion"


def _get(obj: Any, key: str, default: Any = None) -> Any:
    return obj.get(key, default) if isinstance(obj, dict) else getattr(obj, key, default)


def resonance_band(f0_hz: float, q: float) -> tuple[float, float]:
    """Half-power band of a second-order resonance, ``f0 (1 +- 1/(2Q))`` (Hz)."""
    half = f0_hz / (2.0 * max(q, 0.5))
    return max(f0_hz - half, 0.0), f0_hz + half


def features_from_diagnosis(channel: str, diagnosis: Any,
                            significant_only: bool = True) -> list[SpectralFeature]:
    """The lines and resonances of one channel's diagnosis.

    ``diagnosis`` is a :class:`~imunoise.analysis.diagnosis.Diagnosis`, or its JSON form
    (``{"suggestions": [...], "findings": [...]}``), or a list of suggestions (objects or
    dicts with ``term``, ``params``, ``significant``). Lines come from sinusoid and resonance
    suggestions and from every line the spectral-line evidence lists; one feature per
    frequency.
    """
    if isinstance(diagnosis, list):
        suggestions, findings = diagnosis, []
    else:
        suggestions = list(_get(diagnosis, "suggestions", []) or [])
        findings = list(_get(diagnosis, "findings", []) or [])
    out: list[SpectralFeature] = []
    for s in suggestions:
        term = _get(s, "term")
        if term not in LINE_TERMS or (significant_only and not _get(s, "significant", False)):
            continue
        p = _get(s, "params", {}) or {}
        if term == "sinusoid" and p.get("f"):
            f = float(p["f"])
            out.append(SpectralFeature(channel, term, f, (f, f)))
        elif term == "resonance" and p.get("f0"):
            f0 = float(p["f0"])
            out.append(SpectralFeature(channel, term, f0, resonance_band(f0, float(p.get("Q", 1)))))
    for fd in findings:
        if _get(fd, "kind") != "spectral_line":
            continue
        details = _get(fd, "details", {}) or {}
        for line in details.get("lines", []):
            f = float(line["f_hz"])
            out.append(SpectralFeature(channel, "sinusoid", f, (f, f), "spectral_line"))
    unique: list[SpectralFeature] = []
    for feat in out:  # suggestions first: they win over the evidence's copy of a line
        if not any(u.term == feat.term and abs(u.f_hz - feat.f_hz) <= 1e-3 * feat.f_hz + 1e-9
                   for u in unique):
            unique.append(feat)
    return unique


@dataclass
class Partner:
    """Coherence of the feature's channel with one other channel over the feature."""

    channel: str
    msc: float
    ci_low: float
    ci_high: float
    threshold: float
    line_share: tuple[float, float, float] | None = None
    """At a line standing out of its floor: ``(share, low, high)`` of the line's own power
    (above the local continuum) that this channel explains (above what it explains of the
    continuum); None where the coherence itself is the measure (a band, a weak line)."""

    @property
    def coherent(self) -> bool:
        return self.msc > self.threshold

    @property
    def share(self) -> float:
        return self.msc if self.line_share is None else self.line_share[0]

    @property
    def share_low(self) -> float:
        return self.ci_low if self.line_share is None else self.line_share[1]

    @property
    def share_high(self) -> float:
        return self.ci_high if self.line_share is None else self.line_share[2]

    def to_dict(self) -> dict[str, Any]:
        return {"channel": self.channel, "msc": self.msc, "ci": [self.ci_low, self.ci_high],
                "threshold": self.threshold, "coherent": self.coherent,
                "line_share": self.share, "line_share_ci": [self.share_low, self.share_high]}


@dataclass
class Origin:
    """Where a feature comes from.

    Attributes:
        feature: the line or band.
        origin: ``"common"``, ``"own"`` or ``"mixed"``.
        partners: every other channel's coherence over the feature, highest first.
        common_with: channels it is common with (interval above one half).
        f_eval_hz: the bin (line) or band centre (resonance) judged, Hz.
        n_avg: equivalent independent averages there.
        reading: the physical reading (empty for ``own``).
        motion: numbers behind the reading (amplitudes, direction, angle to gravity, the
            gyros' rotation and the acceleration it predicts), SI units.
        ci: confidence level of the intervals.
    """

    feature: SpectralFeature
    origin: str
    partners: list[Partner]
    common_with: list[str]
    f_eval_hz: float
    n_avg: float
    reading: str = ""
    motion: dict[str, Any] = field(default_factory=dict)
    ci: float = 0.95

    @property
    def why(self) -> str:
        """One or two sentences for the suggestion's ``why``."""
        f = self.feature
        top = self.partners[0] if self.partners else None
        what = "line" if f.term == "sinusoid" else "resonance"

        def coh(p: Partner) -> str:
            text = f"{p.channel} {p.msc:.2f} [{p.ci_low:.2f}, {p.ci_high:.2f}]"
            if p.line_share is not None:  # the line's own power, not the bin's
                text += f" ({p.share_low:.2f} to {p.share_high:.2f} of the line's own power)"
            return text

        if self.origin == "common":
            pairs = ", ".join(coh(p) for p in self.partners if p.channel in self.common_with)
            return (f"Common, not {f.channel}'s own: the {what} at {f.f_hz:.4g} Hz is coherent "
                    f"with {pairs} (magnitude-squared coherence, {self.ci:.0%} interval; "
                    f"zero-coherence threshold {top.threshold:.2g}). {self.reading}").strip()
        if top is None:
            return f"Own: no other channel to compare the {what} at {f.f_hz:.4g} Hz with."
        coherent = [p for p in self.partners if p.coherent]
        if self.origin == "own":
            text = (f"Own to {f.channel}: the {what} at {f.f_hz:.4g} Hz is not shared; its "
                    f"highest coherence is with {coh(top)}")
            if coherent:
                text += (f" (a significant common part of at most {top.share_high:.0%} of its "
                         f"power)")
            return text + "."
        return (f"Partly common: the {what} at {f.f_hz:.4g} Hz has coherence {coh(top)}; "
                f"neither mostly shared nor mostly {f.channel}'s own.")

    def to_dict(self) -> dict[str, Any]:
        f = self.feature
        return {"channel": f.channel, "term": f.term, "f_hz": f.f_hz,
                "band_hz": list(f.band_hz), "source": f.source, "origin": self.origin,
                "common_with": list(self.common_with), "f_eval_hz": self.f_eval_hz,
                "n_avg": self.n_avg, "partners": [p.to_dict() for p in self.partners],
                "reading": self.reading, "motion": _plain(self.motion), "why": self.why}


def _plain(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, np.ndarray)):
        return [_plain(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(float(obj)) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _split(name: str) -> tuple[str, str]:
    """``(device, channel)`` of a name: the device is what precedes the last ``/`` or ``:``
    (``"imu1/gyro_x"``, ``"/imu:gyro_x"``), empty when there is none."""
    cut = max(name.rfind("/"), name.rfind(":"))
    return (name[:cut], name[cut + 1:]) if cut >= 0 else ("", name)


def channel_kind(name: str) -> str:
    """``"accel"``, ``"gyro"``, ``"temperature"`` or ``"other"`` from a channel's name (the
    part after a device prefix such as ``imu1/`` or ``/imu:``)."""
    base = _split(name)[1].lower()
    for kind in ("accel", "gyro"):
        if base.startswith(kind):
            return kind
    return "temperature" if base.startswith("temp") else "other"


def channel_device(name: str) -> str:
    """The device part of a channel's name (``"imu1/gyro_x"`` -> ``"imu1"``; ``""`` if none)."""
    return _split(name)[0]


def _feature_matrix(cs: CrossSpectra, feat: SpectralFeature
                    ) -> tuple[np.ndarray, float, float, np.ndarray, Any]:
    """``(matrix at the judged bin or band, n, frequency judged, matrix summed over the
    feature's power in units^2, (each channel's PSD floor, the neighbouring bins it comes
    from) under a line or None for a band)``."""
    i = cs.index(feat.channel)
    df = cs.df_hz
    if feat.term == "resonance" and feat.band_hz[1] > feat.band_hz[0]:
        s, n = cs.band(*feat.band_hz)
        sel = (cs.f_hz >= feat.band_hz[0]) & (cs.f_hz <= feat.band_hz[1])
        power = cs.s[sel].sum(axis=0) * df if np.any(sel) else s * df
        return s, n, 0.5 * (feat.band_hz[0] + feat.band_hz[1]), power, None
    near = np.flatnonzero(np.abs(cs.f_hz - feat.f_hz) <= 1.5 * df)
    if near.size == 0:
        near = np.array([int(np.argmin(np.abs(cs.f_hz - feat.f_hz)))])
    k = int(near[np.argmax(cs.s[near, i, i].real)])
    lobe = slice(max(k - 2, 0), min(k + 3, cs.f_hz.size))  # the Hann main lobe
    power = cs.s[lobe].sum(axis=0) * df
    # each channel's own floor under the lobe (median of the neighbouring bins) is not the
    # line's: off the diagonal independent floors average out, on it they are removed
    side = np.r_[max(k - _FLOOR_BINS, 0):max(k - 3, 0), k + 3:min(k + _FLOOR_BINS, cs.f_hz.size)]
    floor = np.zeros(len(cs.channels))
    if side.size:
        floor = np.median(np.real(np.diagonal(cs.s[side], axis1=1, axis2=2)), axis=0)
        width = (lobe.stop - lobe.start) * df
        power = power - np.diag(np.minimum(floor * width, 0.999 * np.diag(power).real))
    return cs.s[k], cs.n_avg, float(cs.f_hz[k]), power, (floor, side)


def _principal(m: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Rank-one part of a Hermitian power matrix: ``(real direction, amplitude vector's
    norm as peak amplitude, worst phase departure from in/anti-phase in degrees)``."""
    w, v = np.linalg.eigh(m)
    vec = v[:, -1] * np.exp(-1j * np.angle(v[np.argmax(np.abs(v[:, -1])), -1]))
    phase = np.degrees(np.abs(np.angle(vec * np.sign(vec.real + (vec.real == 0)))))
    amplitude = math.sqrt(2.0 * max(float(w[-1]), 0.0))  # power A^2/2 -> peak amplitude
    return vec.real / max(np.linalg.norm(vec.real), 1e-300), amplitude, float(np.max(phase))


def _axis_vector(names: list[str], values: np.ndarray) -> np.ndarray:
    """A 3-vector (x, y, z) from values of channels named ``..._x`` etc. (missing axes 0)."""
    out = np.zeros(3)
    for n, v in zip(names, values, strict=True):
        axis = _split(n)[1][-1:].lower()
        if axis in "xyz" and axis:
            out["xyz".index(axis)] = v
    return out


def _reading(cs: CrossSpectra, feat: SpectralFeature, group: list[str], power: np.ndarray,
             f_hz: float, coherent: list[str], means: dict[str, float] | None
             ) -> tuple[str, dict[str, Any]]:
    kinds = {c: channel_kind(c) for c in group}
    devices = {channel_device(c) for c in group}
    if any(k == "temperature" for k in kinds.values()):
        return ("It follows the temperature record: the environment's temperature (air "
                "conditioning cycling), not noise of the sensor."), {}
    motion: dict[str, Any] = {}
    text = ""
    if len(devices) > 1:
        text = ("It is seen by more than one sensor on the bench: the environment, not either "
                "sensor's own noise. ")
    dev = channel_device(feat.channel)
    accel = [c for c in cs.channels if channel_kind(c) == "accel" and channel_device(c) == dev]
    gyro = [c for c in cs.channels if channel_kind(c) == "gyro" and channel_device(c) == dev]
    accel_in = [c for c in group if c in accel]
    gyro_in = [c for c in group if c in gyro]
    gyro_seen = gyro_in or [c for c in coherent if c in gyro]
    if not accel_in:
        if len(gyro_in) >= 2:
            text += ("A rotation of the bench seen by the gyros together (or an electrical "
                     "source they share).")
        return (text or "An environmental or shared electrical source.").strip(), motion
    ia = [cs.index(c) for c in accel]
    u, amp, phase = _principal(power[np.ix_(ia, ia)])
    motion.update({"accel_channels": accel, "accel_direction": u.tolist(),
                   "accel_amplitude": amp, "accel_phase_spread_deg": phase})
    g_vec = _axis_vector(accel, [means.get(c, 0.0) for c in accel]) if means else np.zeros(3)
    angle = None
    if len(accel) == 3 and np.linalg.norm(g_vec) > 0.5 * STANDARD_GRAVITY:
        angle = math.degrees(math.acos(min(abs(float(_axis_vector(accel, u) @ g_vec))
                                           / float(np.linalg.norm(g_vec)), 1.0)))
        motion["angle_to_gravity_deg"] = angle
    if np.linalg.norm(g_vec) < 0.5 * STANDARD_GRAVITY:
        g_vec = np.array([0.0, 0.0, -STANDARD_GRAVITY])  # the usual mounting, z vertical
    g_norm = float(np.linalg.norm(g_vec))
    explained = None
    if gyro_seen and gyro:
        ig = [cs.index(c) for c in gyro]
        # the gyros' part coherent with the accelerometer line: their cross-power with it
        # over its amplitude (power |P_k0|^2 / P_00 on gyro k), sign from the phase
        i0 = cs.index(feat.channel if feat.channel in accel else accel_in[0])
        cross = power[ig, i0] / math.sqrt(max(float(power[i0, i0].real), 1e-300))
        w_vec = _axis_vector(gyro, np.abs(cross) * np.sign(np.cos(np.angle(cross))))
        w_amp = math.sqrt(2.0 * float(np.sum(w_vec**2)))
        w_dir = w_vec / max(float(np.linalg.norm(w_vec)), 1e-300)
        predicted = w_amp / (2.0 * math.pi * f_hz) * g_norm * \
            float(np.linalg.norm(np.cross(w_dir, g_vec / g_norm)))
        explained = predicted / amp if amp > 0 else float("nan")
        motion.update({"gyro_channels": gyro, "rate_amplitude": w_amp,
                       "rate_direction": w_dir.tolist(),
                       "tilt_amplitude_rad": w_amp / (2.0 * math.pi * f_hz),
                       "accel_from_rotation": predicted, "rotation_explains": explained})
    axes = ", ".join(f"{c} {x:+.2f}" for c, x in zip(accel, u, strict=True))
    in_phase = "in phase" if phase < 20 else f"phases up to {phase:.0f} deg apart"
    if explained is not None and 0.5 <= explained <= 2.0:
        text += (f"A rotation (rocking) of the bench: the gyros see its rate "
                 f"({motion['rate_amplitude']:.3g} rad/s) and the accelerometers the tilt of "
                 f"gravity it causes (predicted {motion['accel_from_rotation']:.3g} m/s^2, "
                 f"measured {amp:.3g} m/s^2).")
    elif len(accel_in) < 2 and gyro_in:
        text += (f"Gyro and accelerometer together, a rotation of the bench; its rate "
                 f"({motion['rate_amplitude']:.3g} rad/s) predicts {explained:.0%} of the "
                 f"accelerometer line's tilt acceleration.")
    elif angle is not None and angle >= _TILT_ANGLE_DEG:
        text += (f"A tilt or sway of the bench: the accelerometers' common part "
                 f"({amp:.3g} m/s^2, direction {axes}, {in_phase}) lies {angle:.0f} deg "
                 f"from gravity, as the gravity projection of a tilt of "
                 f"{amp / g_norm:.3g} rad makes it.")
    else:
        where = f", {angle:.0f} deg from gravity, so not a tilt" if angle is not None else ""
        text += (f"One motion of the bench seen by the accelerometer axes together: "
                 f"{amp:.3g} m/s^2 along {axes} ({in_phase}{where}): a linear vibration "
                 f"of the bench, or an electrical source the axes share.")
        if explained is not None and np.isfinite(explained):
            text += (f" The gyros' coherent part ({motion['rate_amplitude']:.3g} rad/s) "
                     f"would tilt gravity by {motion['tilt_amplitude_rad']:.2g} rad, "
                     f"{explained:.0%} of the line: the rotation does not explain it.")
    return text.strip(), motion


def _line_shares(cs: CrossSpectra, i: int, s: np.ndarray, floor_side: Any,
                 msc: np.ndarray, lo: np.ndarray, hi: np.ndarray, others: list[str]
                 ) -> list[tuple[float, float, float] | None]:
    """Per partner, the share of the line's own power it explains (see :class:`Partner`):
    ``(C S_ii - E_j) / (S_ii - floor_i)`` with ``E_j`` the median over the neighbouring bins of
    what the partner explains there, ``|S_ij|^2 / S_jj``; None unless the line stands
    :data:`LINE_OVER_FLOOR` times above the floor. The bounds map the coherence's interval the
    same way (the continuum taken as known)."""
    if floor_side is None:
        return [None] * len(others)
    floor, side = floor_side
    sii = float(s[i, i].real)
    if side.size == 0 or not sii >= LINE_OVER_FLOOR * floor[i] > 0:
        return [None] * len(others)
    excess = sii - float(floor[i])
    out: list[tuple[float, float, float] | None] = []
    for c, m, a, b in zip(others, msc, lo, hi, strict=True):
        j = cs.index(c)
        around = float(np.median(_msc(cs.s[side, i, j], cs.s[side, i, i].real,
                                      cs.s[side, j, j].real) * cs.s[side, i, i].real))
        out.append(tuple(float(np.clip((v * sii - around) / excess, 0.0, 1.0))
                         for v in (m, a, b)))
    return out


def classify(features: list[SpectralFeature], cs: CrossSpectra, *,
             means: dict[str, float] | None = None, alpha: float = DEFAULT_ALPHA,
             ci: float = 0.95, majority: float = MAJORITY) -> list[Origin]:
    """Classify each feature as common, own or mixed (see the module notes).

    Args:
        features: lines and bands (:func:`features_from_diagnosis`); features of channels
            absent from ``cs`` are skipped.
        cs: the record's cross-spectra (accelerometers in m/s^2, gyros in rad/s).
        means: each channel's mean (SI); the accelerometer means give gravity's direction.
        alpha: level of the zero-coherence test (Sidak over the other channels).
        ci: confidence level of the coherence intervals.
        majority: the common/own boundary on the coherence.
    """
    out: list[Origin] = []
    for feat in features:
        if feat.channel not in cs.channels:
            continue
        s, n, f_eval, power, floor = _feature_matrix(cs, feat)  # floor: (PSD floors, bins)
        i = cs.index(feat.channel)
        others = [c for c in cs.channels if c != feat.channel]
        thr = float(msc_threshold(n, alpha, n_tests=max(len(others), 1)))
        msc = np.array([float(_msc(s[i, cs.index(c)], s[i, i].real,
                                   s[cs.index(c), cs.index(c)].real)) for c in others])
        lo, hi = msc_interval(msc, np.full(msc.shape, n), ci) if others \
            else (np.empty(0), np.empty(0))
        shares = _line_shares(cs, i, s, floor, msc, lo, hi, others)
        partners = sorted((Partner(c, float(m), float(a), float(b), thr, sh)
                           for c, m, a, b, sh in zip(others, msc, lo, hi, shares, strict=True)),
                          key=lambda p: -p.share)
        common_with = [p.channel for p in partners if p.coherent and p.share_low > majority]
        if common_with:
            origin = "common"
        elif all(p.share_high < majority for p in partners):
            origin = "own"
        else:
            origin = "mixed"
        result = Origin(feat, origin, partners, common_with, f_eval, float(n), ci=ci)
        if origin == "common":
            coherent = [p.channel for p in partners if p.coherent]
            result.reading, result.motion = _reading(cs, feat, [feat.channel] + common_with,
                                                     power, f_eval, coherent, means)
        out.append(result)
    return out


def annotate(suggestions: dict[str, list[Any]], origins: list[Origin]) -> int:
    """Append each classified feature's sentence to the ``why`` of the matching suggestion
    (same channel, term and frequency) of ``suggestions`` (channel -> suggestions, objects or
    dicts). Returns the number of suggestions annotated."""
    count = 0
    for o in origins:
        f = o.feature
        for s in suggestions.get(f.channel, []):
            p = _get(s, "params", {}) or {}
            fs = p.get("f" if f.term == "sinusoid" else "f0")
            if _get(s, "term") != f.term or fs is None \
                    or abs(float(fs) - f.f_hz) > 1e-3 * f.f_hz + 1e-9:
                continue
            why = f"{_get(s, 'why', '')} {o.why}".strip()
            if isinstance(s, dict):
                s["why"] = why
                s["origin"] = o.origin
            else:
                s.why = why
            count += 1
    return count
