"""Recordings of simulated units at rest, for fleet tests, benchmarks and demonstrations.

Each unit has its own white-noise density and rate random walk on every axis; a recording is
written by the real recorder (ROS 2 MCAP) with the unit's identity in its metadata
(``config.unit_id``, ``config.sensor_model``) and its start time as the sample clock, as a
night on an inspection bench would be.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from imunoise.core.blocks import SampleBlock
from imunoise.daq.recorder import McapRecorder

AXES = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
GRAVITY_Z = -9.80665
"""m/s^2 on accel_z of a unit lying flat."""


@dataclass(frozen=True)
class SimUnit:
    """A simulated unit: white noise density ``n_gyro`` (rad/s/sqrt(Hz)) and ``n_accel``
    (m/s^2/sqrt(Hz)), rate random walk ``k_gyro`` (rad/s/sqrt(s)) and ``k_accel``
    (m/s^2/sqrt(s))."""

    unit_id: str
    sensor_model: str = "sim-imu"
    n_gyro: float = 3e-4
    n_accel: float = 2e-3
    k_gyro: float = 2e-6
    k_accel: float = 2e-5


def write_recording(out_dir: str | Path, unit: SimUnit, start_s: float, duration_s: float,
                    rate_hz: float = 100.0, seed: int = 0, block_s: float = 10.0) -> Path:
    """Write one still recording of ``unit`` starting at ``start_s`` (Unix seconds); returns
    the MCAP path. Deterministic for a given seed."""
    rng = np.random.default_rng(seed)
    n_total = int(round(duration_s * rate_hz))
    block = max(1, int(round(block_s * rate_hz)))
    white = np.array([unit.n_gyro] * 3 + [unit.n_accel] * 3) * np.sqrt(rate_hz)
    walk_step = np.array([unit.k_gyro] * 3 + [unit.k_accel] * 3) / np.sqrt(rate_hz)
    level = np.array([0.0, 0.0, 0.0, 0.0, 0.0, GRAVITY_Z]) + rng.normal(0, 1e-3, 6)
    clock = itertools.count(start_s)  # host clock: one second per call, from the start
    rec = McapRecorder(out_dir, unit.unit_id, config={"unit_id": unit.unit_id,
                                                      "sensor_model": unit.sensor_model},
                       rate_hz=rate_hz, rotate_s=None, fsync=False, threaded=False,
                       reserve_bytes=0, clock=lambda: float(next(clock)))
    try:
        for k in range(0, n_total, block):
            n = min(block, n_total - k)
            steps = rng.normal(0.0, 1.0, (n, 6)) * walk_step
            drift = level + np.cumsum(steps, axis=0)
            level = drift[-1]
            values = drift + rng.normal(0.0, 1.0, (n, 6)) * white
            t = start_s + (k + np.arange(n)) / rate_hz
            rec.write(SampleBlock(f"/{unit.unit_id}/imu", t,
                                  {a: values[:, i].copy() for i, a in enumerate(AXES)}, rate_hz))
    finally:
        rec.close()
    if rec.error:
        raise OSError(rec.error)
    return Path(rec.stats.files[-1])
