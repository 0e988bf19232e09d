"""Shared inputs for the output tests: one simulated 6-axis recording as CSV and as MCAP."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imunoise.analysis.noise_stream import NoiseStream
from imunoise.core.blocks import SampleBlock
from imunoise.daq.recorder import McapRecorder

FS = 100.0
N_SAMPLES = 40_000  # 400 s: short, but long enough for three-term fits on octave taus
GYRO_MODEL = [("white", {"N": 3e-4}), ("bias_instability", {"B": 4e-5}),
              ("random_walk", {"K": 2e-5})]
ACCEL_MODEL = [("white", {"N": 2e-3}), ("bias_instability", {"B": 2e-4}),
               ("random_walk", {"K": 1e-4})]
GAP_AT, GAP_LEN = 25_000, 50  # samples missing in the MCAP recording


def channels(seed: int = 0) -> dict[str, np.ndarray]:
    """Simulated rates (rad/s, m/s^2) of the six axes plus a slow temperature (degC)."""
    out = {}
    for i, axis in enumerate("xyz"):
        out[f"gyro_{axis}"] = NoiseStream(GYRO_MODEL, FS, seed=seed + i).take(N_SAMPLES)
        out[f"accel_{axis}"] = NoiseStream(ACCEL_MODEL, FS, seed=seed + 10 + i).take(N_SAMPLES)
    t = np.arange(N_SAMPLES) / FS
    out["temp"] = 30.0 + 2.0 * np.sin(2 * np.pi * t / t[-1])
    return out


def write_csv(path: Path, seed: int = 0) -> Path:
    ch = channels(seed)
    names = ["t", *ch]
    cols = [np.arange(N_SAMPLES) / FS, *ch.values()]
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=",".join(names),
               comments="", fmt="%.10g")
    return path


def write_mcap(folder: Path, seed: int = 0, block: int = 1000) -> Path:
    """An MCAP recording of the same data, with one gap of ``GAP_LEN`` samples."""
    ch = channels(seed)
    rec = McapRecorder(folder, "sim:adis16350", config={"model": "ADIS16350"},
                       threaded=False, fsync=False, rotate_s=None)
    t0 = 1.7e9
    k = 0
    for start in range(0, N_SAMPLES, block):
        gap = GAP_LEN if start == GAP_AT else 0
        k += gap
        t = t0 + (k + np.arange(block)) / FS
        data = {name: v[start:start + block] for name, v in ch.items()}
        rec.write(SampleBlock("/adis16350/imu", t, data, FS, gap_before=gap))
        k += block
    rec.close()
    assert rec.error is None, rec.error
    (path,) = sorted(folder.glob("*.mcap"))
    return path
