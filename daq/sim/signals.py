"""Physical signals that drive the chip simulators, in SI units.

A signal source is a callable ``n -> ndarray`` of shape ``(n, 3)`` returning the next ``n``
samples of one triad (rad/s or m/s^2) at the rate it was made for; a temperature source maps
sample times in seconds to degC. The default sources come from the noise-term library in
``analysis`` with the seed-paper models; :func:`white_source` is the plain case used where a
test needs a noise level known in closed form.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from imunoise.core.units import DEG, G0

SignalSource = Callable[[int], np.ndarray]
TemperatureSource = Callable[[np.ndarray], np.ndarray]

SQRT_HOUR = 60.0  # sqrt(3600 s)

# Seed-paper noise models per device, in SI units per channel (see docs/devices.md).
# ADIS16350: Petkov & Slavov (2010); ITG-3200/ADXL345: the SparkFun 9DOF Razor PSD study.
SEED_MODELS: dict[str, dict[str, list[tuple[str, dict[str, float]]]]] = {
    "adis16350": {
        "gyro": [
            ("white", {"N": 5.75e-2 * DEG}),
            ("gauss_markov", {"sigma": 1.55e-2 * DEG, "T": 120.0}),
            ("random_walk", {"K": 9e-4 * DEG}),
        ],
        "accel": [
            ("white", {"N": 0.294 / SQRT_HOUR}),
            ("gauss_markov", {"sigma": 0.325e-3 * G0, "T": 80.0}),
        ],
    },
    "itg3200": {
        "gyro": [
            ("white", {"N": 0.5 / SQRT_HOUR * DEG}),
            ("bias_instability", {"B": 0.006 * DEG}),
        ],
    },
    "adxl345": {
        "accel": [
            ("white", {"N": 0.06 / SQRT_HOUR}),
        ],
    },
}

# Rest orientation: z up, so the accelerometer reads +1 g on z.
GRAVITY_AT_REST = (0.0, 0.0, G0)


def white_source(density: float | Sequence[float], fs_hz: float, *,
                 bias: float | Sequence[float] = 0.0, seed: int = 0) -> SignalSource:
    """White noise of spectral density ``density`` (SI unit per sqrt(Hz)) plus a constant bias.

    The per-sample standard deviation is ``density * sqrt(fs_hz)``.
    """
    rng = np.random.default_rng(seed)
    sigma = np.broadcast_to(np.asarray(density, dtype=np.float64), (3,)) * math.sqrt(fs_hz)
    offset = np.broadcast_to(np.asarray(bias, dtype=np.float64), (3,))

    def take(n: int) -> np.ndarray:
        return offset + sigma * rng.standard_normal((n, 3))

    return take


NoiseFactory = Callable[[list[tuple[str, dict[str, float]]], float, int],
                        Callable[[int], np.ndarray]]
"""Makes one channel's noise stream ``take(n) -> n samples`` of ``model`` at ``fs_hz`` from a
seed: the caller passes the analysis package's simulator (``daq`` does not import it)."""


def model_source(model: list[tuple[str, dict[str, float]]], fs_hz: float, *,
                 bias: float | Sequence[float] = 0.0, seed: int = 0,
                 noise: NoiseFactory | None = None) -> SignalSource:
    """Three independent channels of a noise model, each from ``noise``; without one, the
    model's white-noise term alone."""
    offset = np.broadcast_to(np.asarray(bias, dtype=np.float64), (3,))
    if noise is None:
        n_white = sum(p.get("N", 0.0) for term, p in model if term == "white")
        return white_source(n_white, fs_hz, bias=offset, seed=seed)
    streams = [noise(model, fs_hz, seed * 3 + axis) for axis in range(3)]

    def take(n: int) -> np.ndarray:
        return offset + np.column_stack([s(n) for s in streams])

    take.channels = (streams, offset)  # drawn one channel at a time by imunoise.daq.sim.i2c_chip
    return take


def default_sources(device: str, fs_hz: float, seed: int = 0,
                    noise: NoiseFactory | None = None
                    ) -> tuple[SignalSource | None, SignalSource | None]:
    """(gyro, accel) sources with the seed-paper model of ``device`` (None where absent),
    drawn by ``noise`` (see :func:`model_source`)."""
    models = SEED_MODELS[device]
    gyro = (model_source(models["gyro"], fs_hz, seed=seed, noise=noise)
            if "gyro" in models else None)
    accel = (model_source(models["accel"], fs_hz, bias=GRAVITY_AT_REST, seed=seed + 1000,
                          noise=noise) if "accel" in models else None)
    return gyro, accel


def drifting_temperature(start_c: float = 24.0, rise_c: float = 3.0, tau_s: float = 1800.0,
                         ripple_c: float = 0.05, ripple_period_s: float = 600.0
                         ) -> TemperatureSource:
    """A board warming up after power-on: exponential approach plus a slow ripple (degC)."""

    def temp(t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return (start_c + rise_c * (1.0 - np.exp(-t / tau_s))
                + ripple_c * np.sin(2.0 * math.pi * t / ripple_period_s))

    return temp
