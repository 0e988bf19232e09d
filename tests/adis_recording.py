"""An ADIS16405 run of ../shared/data written as the recorder writes a recording: one MCAP
file, topic ``/adis/imu``, gyro in rad/s and accelerometer in m/s^2 at 100 Hz."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from imunoise.core.blocks import SampleBlock
from imunoise.core.units import DEG, G0
from imunoise.daq.recorder import McapRecorder


def write_adis_run(npz: Path, out: Path, name: str = "adis16405_run1") -> Path:
    """``npz`` (``runN.npz``: counts and scales) as an MCAP file in ``out``; its path."""
    d = np.load(npz)
    fs = float(d["fs_hz"])
    gyro = d["gyro_counts"] * float(d["gyro_scale_dps"]) * DEG
    acc = d["accel_counts"] * float(d["accel_scale_g"]) * G0
    start = 1.6e9
    clock = itertools.count(start)
    rec = McapRecorder(out, name, config={"sensor_model": "adis16405"}, rate_hz=fs,
                       rotate_s=None, fsync=False, threaded=False, reserve_bytes=0,
                       clock=lambda: float(next(clock)))
    block = 20_000
    for k in range(0, gyro.shape[0], block):
        t = start + (k + np.arange(min(block, gyro.shape[0] - k))) / fs
        channels = {f"gyro_{a}": gyro[k:k + block, i].copy() for i, a in enumerate("xyz")}
        channels |= {f"accel_{a}": acc[k:k + block, i].copy() for i, a in enumerate("xyz")}
        rec.write(SampleBlock("/adis/imu", t, channels, fs))
    rec.close()
    (path,) = out.glob(f"{name}*.mcap")
    return path
