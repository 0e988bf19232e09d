"""Shared helpers for the MCAP tests: synthetic sample blocks and a quick recorder run."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imunoise.core.blocks import SampleBlock
from imunoise.daq.recorder import McapRecorder

GYRO_LSB = 0.07326 * np.pi / 180  # rad/s per count (ADIS16350)
ACCEL_LSB = 2.522e-3 * 9.80665  # m/s^2 per count
TEMP_LSB, TEMP_OFFSET = 0.1453, 25.0
CHANNELS = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")


def make_blocks(n_blocks: int, size: int, fs: float = 100.0, t0: float = 1.7e9, seed: int = 0,
                stream: str = "/adis16350/imu", skip: dict[int, int] | None = None,
                gyro: bool = True, accel: bool = True) -> list[SampleBlock]:
    """Blocks of quantized white noise with raw counts; ``skip`` maps a block index to the
    number of samples missing just before it."""
    rng = np.random.default_rng(seed)
    skip = skip or {}
    blocks, k = [], 0
    for b in range(n_blocks):
        k += skip.get(b, 0)
        t = t0 + (k + np.arange(size)) / fs
        raw, ch = {}, {}
        names = [c for c in CHANNELS if (gyro or not c.startswith("gyro"))
                 and (accel or not c.startswith("accel"))]
        for c in names:
            lsb = GYRO_LSB if c.startswith("gyro") else ACCEL_LSB
            raw[c] = rng.integers(-400, 400, size)
            ch[c] = raw[c] * lsb
        raw["temp"] = rng.integers(-10, 10, size)
        ch["temp"] = TEMP_OFFSET + raw["temp"] * TEMP_LSB
        blocks.append(SampleBlock(stream, t, ch, fs, raw=raw, gap_before=skip.get(b, 0)))
        k += size
    return blocks


def record_blocks(out: Path, blocks: list[SampleBlock], **kw) -> McapRecorder:
    kw.setdefault("threaded", False)
    kw.setdefault("fsync", False)
    kw.setdefault("rotate_s", None)
    rec = McapRecorder(out, "sim:adis16350", config={"model": "ADIS16350"}, **kw)
    for b in blocks:
        rec.write(b)
    rec.close()
    assert rec.error is None, rec.error
    return rec
