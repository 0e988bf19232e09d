"""Simulated static records of one or several IMUs on a moving bench, with known truth.

Channels are SI (gyros rad/s, accelerometers m/s^2). Every channel has its own noise (the
project's term simulators, so ``N`` means what the fitter's ``white`` means); the bench adds
common parts with known amplitudes: a linear vibration line seen by the accelerometer axes
along one direction, and a rocking about x (the gyro sees the rate, the accelerometers the
tilt of gravity it causes). Gravity is along -z.
"""

from __future__ import annotations

import math

import numpy as np

from imunoise.analysis.noise_stream import simulate

G = 9.80665
NAMES = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
GYRO_N = (2e-4, 3e-4, 2.5e-4)       # rad/s/sqrt(Hz)
ACCEL_N = (2e-3, 1.5e-3, 2.5e-3)    # m/s^2/sqrt(Hz)
LINE_F, LINE_A, LINE_DIR = 0.56, 0.01, np.array([0.72, 0.45, 0.52])
ROCK_F, ROCK_W = 1.5, 2e-3          # Hz, rad/s amplitude about x
OWN_RES = {"sigma": 0.01, "f0": 14.0, "Q": 4.0}   # accel_x only
OWN_LINE_F, OWN_LINE_A = 3.3, 4e-3                # accel_z only


def bench_record(seed: int, n: int = 1 << 17, fs: float = 100.0, *, line: bool = True,
                 rock: bool = True, own: bool = True, scale: float = 1.0
                 ) -> tuple[np.ndarray, dict]:
    """``(samples (n, 6), truth)``; ``scale`` multiplies every own white level."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    cols = []
    for k, nn in enumerate(GYRO_N + ACCEL_N):
        model = [("white", {"N": nn * scale})]
        if own and k == 3:
            model.append(("resonance", dict(OWN_RES)))
        cols.append(simulate(model, n, fs, rng))
    x = np.column_stack(cols)
    x[:, 5] -= G
    if own:
        x[:, 5] += OWN_LINE_A * np.sin(2 * math.pi * OWN_LINE_F * t + rng.uniform(0, 6.3))
    if line:
        d = LINE_DIR / np.linalg.norm(LINE_DIR)
        x[:, 3:] += LINE_A * np.sin(2 * math.pi * LINE_F * t + rng.uniform(0, 6.3))[:, None] * d
    if rock:
        phase = rng.uniform(0, 6.3)
        rate = ROCK_W * np.sin(2 * math.pi * ROCK_F * t + phase)
        angle = -ROCK_W / (2 * math.pi * ROCK_F) * np.cos(2 * math.pi * ROCK_F * t + phase)
        x[:, 0] += rate
        # gravity (0, 0, -g) seen in a frame rotated by angle about x: y gets +g sin(angle)
        x[:, 4] += G * np.sin(angle)
    truth = {"N": np.array(GYRO_N + ACCEL_N) * scale}
    return x, truth
