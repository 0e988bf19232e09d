"""A simulated bench shared by several simulated sensors: one motion, seen by each sensor
through its own axes, scale and output filter.

The bench moves as a table of :class:`Motion` entries, each a rotation of the bench about an
axis (its angle in rad) or a translation along a direction (its acceleration in m/s^2), as a
line (a sinusoid of given peak amplitude) or a band (flat density between two frequencies).
The motion is generated on a grid of ``Bench.rate_hz`` samples per second of *bench time*
``tau = t - epoch`` (``t`` on the clock the simulated chips read: the host's monotonic clock,
which every process of the machine shares) and is a deterministic function of ``(seed, tau)``:
each grid block is drawn from its own generator keyed by the seed and the block's index, so
two processes that simulate two sensors compute the same motion for the same instants
without talking to each other.

What a sensor sees (small angles, first order):

- gyro: the bench's rotation rate, ``omega = d(theta)/dt``;
- accelerometer: the specific force of a bench that tilts in gravity and shakes,
  ``f = g z - g (theta x z) + a``, i.e. ``(-g theta_y, g theta_x, g) + a`` in bench axes:
  tilt couples gravity into the horizontal axes (the gravity projection), so a rotation of the
  bench shows in the gyro and, through its tilt, in the accelerometer together;
- both rotated into the sensor's axes (:class:`Mount`: its misalignment to the bench), scaled
  per axis, plus the sensor's own lines (:class:`OwnLine`, not seen by any other sensor), and
  filtered by the sensor's output filter (a second-order Butterworth low-pass at the grid
  rate), then interpolated at the sensor's sample times.

The sensor's own noise stays in its signal sources (:mod:`imunoise.daq.sim.signals`); the chip
models add :meth:`SensorOnBench.at` of each sample's time to it. The static gravity through a
misaligned mount is part of what the bench adds (the sources carry ``+g`` on z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import signal
from scipy.spatial.transform import Rotation

from imunoise.core.units import G0

Vector = tuple[float, float, float]


@dataclass(frozen=True)
class Motion:
    """One component of the bench's motion, in bench axes (z up).

    Attributes:
        kind: ``"rotation"`` (angle about ``axis``, rad) or ``"translation"`` (acceleration
            along ``axis``, m/s^2).
        axis: direction in bench axes (normalised when used).
        line_hz: frequency of a line (Hz); then ``amplitude`` is its peak (rad or m/s^2).
        amplitude: peak of the line.
        band_hz: ``(low, high)`` of a band (Hz); then ``density`` is its flat level.
        density: rad/sqrt(Hz) or m/s^2/sqrt(Hz), in the convention of
            :func:`imunoise.daq.sim.signals.white_source` (white noise of density ``D`` at
            ``fs`` has per-sample standard deviation ``D * sqrt(fs)``).
        label: what it stands for (``"sway"``, ``"pump"`` ...), for the docs and reports.
    """

    kind: str
    axis: Vector
    line_hz: float | None = None
    amplitude: float = 0.0
    band_hz: tuple[float, float] | None = None
    density: float = 0.0
    label: str = ""

    def __post_init__(self) -> None:
        if self.kind not in ("rotation", "translation"):
            raise ValueError(f"motion kind must be 'rotation' or 'translation', got "
                             f"{self.kind!r}")
        if (self.line_hz is None) == (self.band_hz is None):
            raise ValueError("a motion is either a line (line_hz) or a band (band_hz)")
        if not np.linalg.norm(self.axis) > 0:
            raise ValueError("a motion's axis must not be zero")


@dataclass(frozen=True)
class OwnLine:
    """A line of one sensor alone (a resonance of its own package, its own electronics).

    Attributes:
        kind: ``"gyro"`` (rad/s) or ``"accel"`` (m/s^2).
        axis: 0, 1 or 2 (x, y, z of the sensor).
        line_hz: frequency (Hz).
        amplitude: peak (rad/s or m/s^2).
    """

    kind: str
    axis: int
    line_hz: float
    amplitude: float


@dataclass(frozen=True)
class Mount:
    """How one sensor sits on the bench.

    Attributes:
        rotation_deg: (roll, pitch, yaw) of the sensor's axes relative to the bench's
            (intrinsic z-y-x: yaw first), degrees.
        gyro_scale: per-axis scale factor of the gyro on the bench's motion.
        accel_scale: per-axis scale factor of the accelerometer.
        lowpass_hz: corner of the sensor's output filter acting on the motion (second-order
            Butterworth); None: unfiltered.
        own_lines: lines of this sensor alone.
    """

    rotation_deg: Vector = (0.0, 0.0, 0.0)
    gyro_scale: Vector = (1.0, 1.0, 1.0)
    accel_scale: Vector = (1.0, 1.0, 1.0)
    lowpass_hz: float | None = 40.0
    own_lines: tuple[OwnLine, ...] = ()

    def matrix(self) -> np.ndarray:
        """C with ``v_sensor = C.T @ v_bench``."""
        roll, pitch, yaw = self.rotation_deg
        return Rotation.from_euler("ZYX", [yaw, pitch, roll], degrees=True).as_matrix()


@dataclass(frozen=True)
class Bench:
    """A bench: its motion, the places sensors take on it, and its grid.

    Attributes:
        name: what it is called (``--bench NAME``).
        motions: the motion table.
        mounts: the k-th sensor placed on the bench (from 0) takes ``mounts[k % len]``.
        rate_hz: grid rate of the motion (Hz); nothing moves above half of it.
        block_s: length of one independently drawn block of the grid (s); a band's lowest
            frequency should be well above ``4 / block_s``.
    """

    name: str
    motions: tuple[Motion, ...]
    mounts: tuple[Mount, ...] = (Mount(),)
    rate_hz: float = 1000.0
    block_s: float = 8.192

    def mount(self, position: int) -> Mount:
        return self.mounts[position % len(self.mounts)]


_TILT_AXIS = (math.cos(math.radians(30.0)), math.sin(math.radians(30.0)), 0.0)

LAB_MOUNTS = (
    Mount(rotation_deg=(0.2, -0.3, 0.1), gyro_scale=(1.002, 0.998, 1.001),
          accel_scale=(1.001, 0.999, 1.0)),
    Mount(rotation_deg=(-0.4, 0.1, -0.3), gyro_scale=(0.997, 1.003, 1.0),
          accel_scale=(1.0, 1.002, 0.998), own_lines=(OwnLine("accel", 0, 7.7, 0.01),)),
    Mount(rotation_deg=(0.1, 0.2, 0.4), gyro_scale=(1.0, 1.001, 0.999),
          accel_scale=(0.999, 1.0, 1.001)),
)
"""Three places on a bench, each sensor's axes along the bench's within half a degree and
its scale factors within 0.3 %, so that the same axis of sensors of one kind sees the same
motion (what a three-cornered hat needs); the second has a 7.7 Hz line of its own on accel x
(0.01 m/s^2)."""

BENCHES: dict[str, Bench] = {
    "lab": Bench(
        name="lab",
        motions=(
            Motion("rotation", _TILT_AXIS, line_hz=0.56, amplitude=5e-4, label="sway"),
            Motion("rotation", (0.0, 1.0, 0.0), band_hz=(0.5, 20.0), density=2e-6,
                   label="floor tilt"),
            Motion("translation", (0.2, 0.1, 1.0), band_hz=(2.0, 40.0), density=1e-3,
                   label="floor vibration"),
            Motion("translation", (0.0, 0.0, 1.0), line_hz=24.3, amplitude=0.02,
                   label="pump hum"),
        ),
        mounts=LAB_MOUNTS,
    ),
    "sway": Bench(
        name="sway",
        motions=(
            Motion("rotation", _TILT_AXIS, line_hz=0.56, amplitude=2e-3, label="sway"),
            Motion("translation", (0.0, 0.0, 1.0), line_hz=24.3, amplitude=0.05,
                   label="pump hum"),
        ),
        mounts=LAB_MOUNTS,
    ),
}
"""Named benches (``--bench NAME``). ``lab``: a bench that sways at 0.56 Hz (5e-4 rad about a
horizontal axis 30 degrees from x), tilts a little with the floor (0.5-20 Hz), shakes with it
(2-40 Hz, mostly vertical) and carries a pump's hum (24.3 Hz, vertical). ``sway``: a strong
sway (2e-3 rad) and hum alone, seen in a minute of data (for short tests). Both place sensors
on :data:`LAB_MOUNTS`."""


def bench_named(name: str) -> Bench:
    """The bench called ``name``; ``ValueError`` naming the valid ones."""
    try:
        return BENCHES[name]
    except KeyError:
        raise ValueError(f"unknown bench {name!r}: choose one of {', '.join(BENCHES)}") \
            from None


def _unit(v: Vector) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    return a / np.linalg.norm(a)


def _band_kernel(band: tuple[float, float], fs: float, taps: int) -> np.ndarray:
    low, high = band
    nyq = fs / 2.0
    if not 0 <= low < high <= nyq:
        raise ValueError(f"band {band} Hz does not fit under the grid's Nyquist {nyq:g} Hz")
    if low <= 0:
        return signal.firwin(taps, high, fs=fs)
    return signal.firwin(taps, [low, min(high, 0.999 * nyq)], pass_zero=False, fs=fs)


class BenchMotion:
    """The motion of ``bench`` drawn from ``seed``: :meth:`grid` at any grid indices.

    Every call is a pure function of (bench, seed, indices); a small cache keeps the last
    blocks for sequential use.
    """

    def __init__(self, bench: Bench, seed: int = 0) -> None:
        self.bench = bench
        self.seed = int(seed)
        self.fs = float(bench.rate_hz)
        self.block = int(round(bench.block_s * self.fs))
        phases = np.random.default_rng([self.seed, 0x51]).uniform(0, 2 * np.pi,
                                                                   len(bench.motions))
        self._lines = []
        self._bands = []
        taps = self.block // 4 + 1
        for k, (m, phase) in enumerate(zip(bench.motions, phases, strict=True)):
            axis = _unit(m.axis)
            if m.line_hz is not None:
                self._lines.append((m.kind, axis, float(m.line_hz), float(m.amplitude), phase))
            else:
                assert m.band_hz is not None
                h = _band_kernel(m.band_hz, self.fs, taps) * (m.density * math.sqrt(self.fs))
                dh = np.convolve(h, [0.5 * self.fs, 0.0, -0.5 * self.fs])  # d/dt, centred
                self._bands.append((m.kind, axis, h, dh, k))
        self._taps = taps + 2
        self._cache: dict[tuple[int, int], np.ndarray] = {}

    def _noise(self, band: int, j: int) -> np.ndarray:
        key = (band, j)
        got = self._cache.get(key)
        if got is None:
            got = np.random.default_rng([self.seed, 0xB7, band, j + (1 << 40)]) \
                .standard_normal(self.block)
            if len(self._cache) > 8 * max(1, len(self._bands)):
                self._cache.clear()
            self._cache[key] = got
        return got

    def _band_at(self, band: int, kernel: np.ndarray, j0: int, n: int) -> np.ndarray:
        """The band's filtered noise at grid indices ``j0 .. j0+n-1``."""
        m = len(kernel)
        first = (j0 - (m - 1)) // self.block
        last = (j0 + n - 1) // self.block
        w = np.concatenate([self._noise(band, b) for b in range(first, last + 1)])
        off = j0 - (m - 1) - first * self.block
        return signal.oaconvolve(w[off:off + n + m - 1], kernel, mode="valid")

    def grid(self, j0: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(angle rad, rate rad/s, acceleration m/s^2), each (n, 3) in bench axes, at grid
        indices ``j0 .. j0+n-1`` (bench time ``j / rate_hz``)."""
        tau = (j0 + np.arange(n)) / self.fs
        theta = np.zeros((n, 3))
        omega = np.zeros((n, 3))
        accel = np.zeros((n, 3))
        for kind, axis, f, amp, phase in self._lines:
            arg = 2 * np.pi * f * tau + phase
            if kind == "rotation":
                theta += np.outer(amp * np.sin(arg), axis)
                omega += np.outer(amp * 2 * np.pi * f * np.cos(arg), axis)
            else:
                accel += np.outer(amp * np.sin(arg), axis)
        for kind, axis, h, dh, band in self._bands:
            if kind == "rotation":
                # angle and rate from the same noise: the rate is the angle's derivative
                theta += np.outer(self._band_at(band, np.concatenate([[0.0], h, [0.0]]),
                                                j0, n), axis)
                omega += np.outer(self._band_at(band, dh, j0, n), axis)
            else:
                accel += np.outer(self._band_at(band, h, j0, n), axis)
        return theta, omega, accel


@dataclass(frozen=True)
class BenchPlacement:
    """A sensor's place on a bench: what a simulated chip needs (picklable, so that a
    simulator in another process builds the same bench).

    Attributes:
        bench: the bench.
        position: the sensor's place (:meth:`Bench.mount`).
        seed: the bench's seed (the same for every sensor on it).
        epoch: clock time (s) of bench time 0, the same for every sensor on it.
    """

    bench: Bench
    position: int = 0
    seed: int = 0
    epoch: float = 0.0

    def view(self) -> SensorOnBench:
        return SensorOnBench(BenchMotion(self.bench, self.seed), self.bench.mount(self.position),
                             epoch=self.epoch, phase_seed=(self.seed, self.position))


@dataclass
class _Grid:
    start: int = 0
    values: np.ndarray = field(default_factory=lambda: np.zeros((0, 6)))


class SensorOnBench:
    """What one sensor on the bench sees: :meth:`at` of its sample times (s, its clock).

    Times must not go backwards by more than ``keep_s``; the sensor's filter runs along the
    grid once, in order, so memory and work are bounded whatever the run length.
    """

    STEP = 1024  # grid samples filtered at a time
    keep_s = 1.0

    def __init__(self, motion: BenchMotion, mount: Mount, *, epoch: float = 0.0,
                 phase_seed: tuple[int, int] = (0, 0)) -> None:
        self.motion = motion
        self.mount = mount
        self.epoch = float(epoch)
        fs = motion.fs
        c_t = mount.matrix().T
        self._gyro_map = np.diag(mount.gyro_scale) @ c_t
        self._accel_map = np.diag(mount.accel_scale) @ c_t
        self._sos = (signal.butter(2, mount.lowpass_hz, fs=fs, output="sos")
                     if mount.lowpass_hz is not None else None)
        self._zi: np.ndarray | None = None
        phases = np.random.default_rng([*phase_seed, 0x0E]).uniform(
            0, 2 * np.pi, len(mount.own_lines))
        self._own = [(line, phase) for line, phase in zip(mount.own_lines, phases, strict=True)]
        self._grid = _Grid()
        self._next = None  # next grid index to filter

    def _sensor_axes(self, j0: int, n: int) -> np.ndarray:
        theta, omega, accel = self.motion.grid(j0, n)
        f = accel.copy()
        f[:, 0] -= G0 * theta[:, 1]
        f[:, 1] += G0 * theta[:, 0]
        f[:, 2] += G0
        out = np.hstack([omega @ self._gyro_map.T, f @ self._accel_map.T])
        out[:, 5] -= G0  # the sensor's own sources carry +g on z
        if self._own:
            tau = (j0 + np.arange(n)) / self.motion.fs
            for (line, phase) in self._own:
                col = line.axis + (0 if line.kind == "gyro" else 3)
                out[:, col] += line.amplitude * np.sin(2 * np.pi * line.line_hz * tau + phase)
        return out

    def _extend_to(self, j_first: int, j_last: int) -> None:
        g = self._grid
        if self._next is None:
            self._next = j_first - 1
            g.start = self._next
        parts = [g.values]
        while self._next <= j_last:
            raw = self._sensor_axes(self._next, self.STEP)
            if self._sos is not None:
                if self._zi is None:
                    self._zi = signal.sosfilt_zi(self._sos)[:, :, None] * raw[0]
                raw, self._zi = signal.sosfilt(self._sos, raw, axis=0, zi=self._zi)
            parts.append(raw)
            self._next += self.STEP
        values = np.vstack(parts)
        drop = max(0, len(values) - self.STEP - int(self.keep_s * self.motion.fs))
        g.values = values[drop:]
        g.start += drop

    def at(self, t: np.ndarray | float) -> np.ndarray:
        """(n, 6): gyro (rad/s) and accelerometer (m/s^2) additions in sensor axes at clock
        times ``t`` (s)."""
        x = (np.atleast_1d(np.asarray(t, dtype=np.float64)) - self.epoch) * self.motion.fs
        j_last = int(math.floor(x.max())) + 1
        if self._next is None or j_last >= self._next:
            self._extend_to(int(math.floor(x.min())), j_last)
        g = self._grid
        pos = np.clip(x - g.start, 0.0, len(g.values) - 1.000001)
        i = pos.astype(np.int64)
        frac = (pos - i)[:, None]
        return g.values[i] * (1.0 - frac) + g.values[i + 1] * frac
