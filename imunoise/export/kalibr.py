"""Kalibr ``imu.yaml`` from fitted noise models.

Kalibr (ethz-asl/kalibr, "IMU Noise Model") models each axis as white noise plus a bias that is
a random walk, both in continuous time, and uses one value per sensor for all three axes:

- ``gyroscope_noise_density`` sigma_g (rad/s/sqrt(Hz)) and ``accelerometer_noise_density``
  sigma_a (m/s^2/sqrt(Hz)): the white-noise density. Kalibr discretises it as
  sigma_g / sqrt(dt). Our white term has Allan variance N^2/tau and sampled std N sqrt(fs), so
  sigma = N.
- ``gyroscope_random_walk`` sigma_bg (rad/s^2/sqrt(Hz)) and ``accelerometer_random_walk``
  sigma_ba (m/s^3/sqrt(Hz)): the bias derivative's white density. Kalibr discretises it as
  sigma_bg sqrt(dt). Our random_walk term has Allan variance K^2 tau/3 and bias step K sqrt(dt),
  so sigma_b = K.

Axis combination: by default the largest of the three axes' point estimates (``max``, the
conservative choice for a filter); ``rms`` (root mean square) and ``mean`` are offered. An
optional inflation factor multiplies all four values and is stated in the file. When an axis'
random walk is not resolved within the record (K zero, its interval reaching zero, or collapsed
onto the estimate), K is replaced by the largest value the measured Allan band allows,
min over tau of sqrt(3 ci_high^2 / tau), and the file says so. When the fit does not resolve the
white noise N (its interval reaches zero, or the model fails at the shortest averaging times
where N shows), N comes from the PSD's white top band instead, with its own interval; without
that either, there is no file (an unresolved number is never exported as a measurement). Each
axis' own values, 95 % intervals and sources are written as comments, and so are the combined
values' intervals (the same combination applied to the axes' interval ends).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from imunoise.core.errors import InputError

COMBINE = ("max", "rms", "mean")
N_FROM_FIT = "Allan fit, white term"
N_FROM_PSD = "PSD white level of the top band (the Allan fit does not resolve N: {why})"
K_FROM_FIT = "Allan fit, random_walk term"
FROM_OVERBOUND = ("over-bounding model (white noise and random walk whose Allan deviation is on "
                  "or above the measured upper 95 % bound at every tau; excess median {med:.2g} "
                  "%, max {mx:.2g} %)")
_AXES = ("x", "y", "z")
_KIND_KEYS = {
    "gyro": ("gyroscope_noise_density", "gyroscope_random_walk", "rad/s/sqrt(Hz)",
             "rad/s^2/sqrt(Hz)"),
    "accel": ("accelerometer_noise_density", "accelerometer_random_walk", "m/s^2/sqrt(Hz)",
              "m/s^3/sqrt(Hz)"),
}


class KalibrError(InputError):
    """The fitted channels cannot give a Kalibr file (missing axes or terms)."""


@dataclass
class AxisValues:
    """One axis' continuous-time values with 95 % intervals (SI)."""

    channel: str
    N: float
    N_ci: tuple[float, float] | None
    K: float
    K_ci: tuple[float, float] | None
    K_from_allan_bound: bool = False
    N_source: str = N_FROM_FIT
    K_source: str = K_FROM_FIT


@dataclass
class KalibrImu:
    """The four Kalibr values (already combined over axes and inflated) and their sources."""

    gyroscope_noise_density: float
    gyroscope_random_walk: float
    accelerometer_noise_density: float
    accelerometer_random_walk: float
    rostopic: str
    update_rate: float
    combine: str
    inflate: float
    axes: dict[str, list[AxisValues]] = field(default_factory=dict)

    def note(self, key: str) -> str:
        """The comment of one Kalibr key: its 95 % interval (or why it is a bound) and source."""
        kind = "gyro" if key.startswith("gyro") else "accel"
        axes = self.axes.get(kind, [])
        if key.endswith("noise_density"):
            cis = [a.N_ci for a in axes]
            sources = sorted({a.N_source.split(" (")[0] for a in axes})
        else:
            if any(a.K_from_allan_bound for a in axes):
                return ("upper bound: the random walk is not resolved on every axis; largest K "
                        "inside the measured Allan band")
            cis = [a.K_ci for a in axes]
            sources = sorted({a.K_source.split(" (")[0] for a in axes})
        src = "; ".join(sources)
        if not axes or any(c is None for c in cis):
            what = "a bound, not an estimate" if src.startswith("over") else "interval unknown"
            return f"{what}; from the {src}"
        # no interval is None here (returned above); mypy does not narrow through any()
        lo = _combine([c[0] for c in cis], self.combine) * self.inflate  # type: ignore[index]
        hi = _combine([c[1] for c in cis], self.combine) * self.inflate  # type: ignore[index]
        return f"95 % [{_f(lo)}, {_f(hi)}]; from the {src}"


def _ci(entry: Mapping, param: str) -> tuple[float, float] | None:
    ci = (entry.get("ci95") or {}).get(param)
    if not ci or len(ci) != 2 or ci[0] is None or ci[1] is None:
        return None
    return float(ci[0]), float(ci[1])


def _term(channel_doc: Mapping, term: str, param: str) -> tuple[float, tuple | None] | None:
    for entry in channel_doc.get("model") or []:
        if entry.get("term") == term and param in (entry.get("params") or {}):
            return float(entry["params"][param]), _ci(entry, param)
    return None


def _allan_bound(channel_doc: Mapping) -> float | None:
    """Largest K consistent with the measured Allan band: min over tau of sqrt(3 hi^2 / tau).

    A random walk adds K^2 tau/3 to the Allan variance, so it cannot exceed the measured upper
    95 % bound at any averaging time.
    """
    al = channel_doc.get("allan") or {}
    tau, hi = al.get("tau_s") or [], al.get("ci_high") or []
    vals = [math.sqrt(3.0 * h * h / t) for t, h in zip(tau, hi, strict=False)
            if t and h is not None and t > 0 and math.isfinite(h) and h > 0]
    return min(vals) if vals else None


def _n_unresolved(channel_doc: Mapping, n: tuple[float, tuple | None]) -> str | None:
    """Why the fitted white noise N cannot be exported as a measurement, or None when it can."""
    value, ci = n
    if not value > 0.0 or ci is None or not ci[0] > 0.0:
        return "its 95 % interval reaches zero"
    tau = (channel_doc.get("allan") or {}).get("tau_s") or []
    if tau:
        shortest = min(t for t in tau if t is not None)
        for f in channel_doc.get("failures") or []:
            lo = (f.get("tau_s") or [None])[0]
            if lo is not None and lo <= 2.0 * shortest:
                return (f"the model fails at the shortest averaging times "
                        f"({lo:.3g} s), where N shows")
    return None


def _psd_white(channel_doc: Mapping) -> tuple[float, tuple[float, float]] | None:
    """N and its 95 % interval from the PSD's full-rate (Welch) band of an analyze document."""
    from imunoise.analysis.psd import white_level

    psd = channel_doc.get("psd") or {}
    top = [i for i, m in enumerate(psd.get("method") or []) if m == "welch"]
    if not top:
        return None
    values = [psd["psd"][i] for i in top]
    dofs = [psd["dof"][i] for i in top]
    found = white_level([float("nan") if v is None else v for v in values],
                        [float("nan") if d is None else d for d in dofs])
    if found is None:
        return None
    return found[0], (found[1], found[2])


def overbound_axis(name: str, channel_doc: Mapping) -> AxisValues:
    """N and K of one channel from its over-bounding white + random-walk model (no intervals:
    they are bounds by construction)."""
    from imunoise.pipeline.channel_extras import overbound_for_channel

    ob = overbound_for_channel(channel_doc, markov=False)
    if ob is None or "error" in ob:
        why = (ob or {}).get("error", "no Allan curve")
        raise KalibrError(f"{name}: no over-bounding model ({why})")
    src = FROM_OVERBOUND.format(med=100 * ob["median_excess"], mx=100 * ob["max_excess"])
    return AxisValues(name, ob["N"], None, ob["K"], None, False, src, src)


def axis_values(name: str, channel_doc: Mapping) -> AxisValues:
    """N and K of one fitted channel (``fit`` keys of docs/json.md, plus ``psd`` when present).

    When the random walk is not resolved (K zero, its interval reaching zero, or collapsed onto
    the estimate, as when the fit sits on its lower bound), K becomes the largest value the
    measured Allan band allows (:func:`_allan_bound`), and the axis is marked. When the white
    noise is not resolved by the fit, N comes from the PSD white level; without a PSD that is
    an error.
    """
    n = _term(channel_doc, "white", "N")
    k = _term(channel_doc, "random_walk", "K")
    missing = [t for t, v in (("white", n), ("random_walk", k)) if v is None]
    if missing:
        raise KalibrError(f"{name}: the fitted model has no {' or '.join(missing)} term; Kalibr "
                          "needs white and random_walk")
    n_val, n_ci = n
    n_source = N_FROM_FIT
    why = _n_unresolved(channel_doc, n)
    if why is not None:
        white = _psd_white(channel_doc)
        if white is None:
            raise KalibrError(f"{name}: the white noise N is not resolved ({why}) and there is "
                              "no PSD to measure it from: analyse the recording itself, not a "
                              "fit-only JSON, or record longer")
        (n_val, n_ci), n_source = white, N_FROM_PSD.format(why=why)
    k_val, k_ci = k
    resolved = (k_val > 0.0 and k_ci is not None and k_ci[0] > 0.0
                and k_ci[1] > k_val * (1.0 + 1e-6))
    bounded = False
    if not resolved:
        bound = _allan_bound(channel_doc)
        if bound is None:
            raise KalibrError(f"{name}: random walk K is not resolved and the Allan curve is "
                              "missing: record longer data")
        k_val, bounded = bound, True
    return AxisValues(name, n_val, n_ci, k_val, k_ci, bounded, n_source)


def _combine(values: list[float], how: str) -> float:
    if how == "max":
        return max(values)
    if how == "rms":
        return math.sqrt(sum(v * v for v in values) / len(values))
    if how == "mean":
        return sum(values) / len(values)
    raise KalibrError(f"unknown axis combination {how!r}: use one of {', '.join(COMBINE)}")


def imu_topics(channels: Mapping[str, Mapping]) -> list[str]:
    """Topic prefixes of the channel names (``""`` for plain ``gyro_x`` names)."""
    return sorted({n.rsplit(":", 1)[0] if ":" in n else "" for n in channels})


def kalibr_values(channels: Mapping[str, Mapping], *, topic: str | None = None,
                  rostopic: str | None = None, combine: str = "max",
                  inflate: float = 1.0, overbound: bool = False) -> KalibrImu:
    """Kalibr values from fitted channels (``analyze --json`` ``channels``).

    Args:
        channels: channel name -> contract ``fit`` document with a white and a random_walk term.
        topic: which IMU topic to use when channels are named ``TOPIC:gyro_x``.
        rostopic: value of ``rostopic`` (default: the topic, or ``/imu0``).
        combine: ``max``, ``rms`` or ``mean`` over the three axes.
        inflate: factor (>= 1 usually) applied to all four values.
        overbound: take N and K from each axis' over-bounding model instead of the fit.

    Raises:
        KalibrError: missing axes or terms, several topics and none chosen, bad factor.
    """
    if not (math.isfinite(inflate) and inflate > 0):
        raise KalibrError(f"inflation factor must be a positive number, got {inflate}")
    if combine not in COMBINE:
        raise KalibrError(f"unknown axis combination {combine!r}: use one of {', '.join(COMBINE)}")
    topics = imu_topics(channels)
    if topic is None:
        if len(topics) > 1:
            raise KalibrError(f"several IMU topics ({', '.join(t or '(none)' for t in topics)}): "
                              "choose one with --topic")
        topic = topics[0] if topics else ""
    elif topic not in topics:
        raise KalibrError(f"no channels of topic {topic!r}; topics are "
                          f"{', '.join(t or '(none)' for t in topics)}")
    prefix = f"{topic}:" if topic else ""
    axes: dict[str, list[AxisValues]] = {}
    combined: dict[str, tuple[float, float]] = {}
    rate = None
    for kind in ("gyro", "accel"):
        names = [f"{prefix}{kind}_{a}" for a in _AXES]
        present = [n for n in names if n in channels]
        if not present:
            raise KalibrError(f"no {kind} channels ({', '.join(names)}): Kalibr needs both "
                              "gyroscope and accelerometer")
        vals = [(overbound_axis if overbound else axis_values)(n, channels[n]) for n in present]
        axes[kind] = vals
        combined[kind] = (_combine([v.N for v in vals], combine),
                          _combine([v.K for v in vals], combine))
        for n in present:
            fs = channels[n].get("fs_hz")
            if fs:
                rate = float(fs) if rate is None else max(rate, float(fs))
    return KalibrImu(
        gyroscope_noise_density=combined["gyro"][0] * inflate,
        gyroscope_random_walk=combined["gyro"][1] * inflate,
        accelerometer_noise_density=combined["accel"][0] * inflate,
        accelerometer_random_walk=combined["accel"][1] * inflate,
        rostopic=rostopic or topic or "/imu0",
        update_rate=float(rate or 0.0),
        combine=combine, inflate=float(inflate), axes=axes,
    )


def _f(v: float) -> str:
    return f"{v:.6e}"


def _ci_text(ci: tuple[float, float] | None, source: str = "") -> str:
    if ci is not None:
        return f"95 % [{_f(ci[0])}, {_f(ci[1])}]"
    return "a bound, not an estimate" if source.startswith("over") else "interval unknown"


def render_yaml(imu: KalibrImu, source: str = "", stated: Mapping | None = None,
                notes: list[str] | tuple[str, ...] = ()) -> str:
    """The ``imu.yaml`` text: Kalibr's keys, then per-axis values as comments, and what the
    dataset's own ``sensor.yaml`` states (``stated``, from ``analyze``'s ``dataset``) when known.
    ``notes`` are facts about the recording (rate, jitter, missing samples, motion)."""
    how = {"max": "largest of the axes", "rms": "root mean square of the axes",
           "mean": "mean of the axes"}[imu.combine]
    lines = [
        "# IMU noise parameters for Kalibr, written by imunoise export-kalibr",
        f"# source: {source}" if source else "# source: (not given)",
        *[f"# recording: {line}" for line in notes],
        "# continuous-time values: noise density = white-noise N, random walk = rate random walk K",
        f"# axes combined as the {how}; inflation factor {imu.inflate:g}"
        + (" (values below already multiplied)" if imu.inflate != 1 else " (none)"),
        "",
        "# Accelerometers",
        f"accelerometer_noise_density: {_f(imu.accelerometer_noise_density)}  # m/s^2/sqrt(Hz)",
        f"#   {imu.note('accelerometer_noise_density')}",
        f"accelerometer_random_walk: {_f(imu.accelerometer_random_walk)}  # m/s^3/sqrt(Hz)",
        f"#   {imu.note('accelerometer_random_walk')}",
        "",
        "# Gyroscopes",
        f"gyroscope_noise_density: {_f(imu.gyroscope_noise_density)}  # rad/s/sqrt(Hz)",
        f"#   {imu.note('gyroscope_noise_density')}",
        f"gyroscope_random_walk: {_f(imu.gyroscope_random_walk)}  # rad/s^2/sqrt(Hz)",
        f"#   {imu.note('gyroscope_random_walk')}",
        "",
        f"rostopic: {_yaml_str(imu.rostopic)}",
        f"update_rate: {float(imu.update_rate)!r}  # Hz",
        "",
        "# Per-axis fitted values before combination and inflation (SI):",
    ]
    for kind in ("gyro", "accel"):
        _, _, n_unit, k_unit = _KIND_KEYS[kind]
        for ax in imu.axes.get(kind, []):
            n_ci = _ci_text(ax.N_ci, ax.N_source)
            lines.append(f"#   {ax.channel}: N = {_f(ax.N)} {n_unit} ({n_ci}; "
                         f"from the {ax.N_source})")
            if ax.K_from_allan_bound:
                lines.append(f"#   {ax.channel}: K = {_f(ax.K)} {k_unit} (random walk not "
                             "resolved: largest K inside the measured Allan band)")
            else:
                k_ci = _ci_text(ax.K_ci, ax.K_source)
                lines.append(f"#   {ax.channel}: K = {_f(ax.K)} {k_unit} ({k_ci}; "
                             f"from the {ax.K_source})")
    if stated:
        lines.append(f"# The dataset's {stated.get('sensor_yaml', 'sensor.yaml')} states (not "
                     "measured):")
        lines += [f"#   {key}: {_f(float(stated[key]))}" for key in
                  ("gyroscope_noise_density", "gyroscope_random_walk",
                   "accelerometer_noise_density", "accelerometer_random_walk", "rate_hz")
                  if key in stated]
    return "\n".join(lines) + "\n"


def _yaml_str(s: str) -> str:
    """A YAML scalar that reads back as the same string (a JSON string is valid YAML)."""
    return json.dumps(s)
