"""Live coherence fed block by block equals the batch estimate of the same samples."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.coherence import cross_spectra, log_coherence
from imunoise.core.blocks import SampleBlock
from imunoise.live.coherence import LiveCoherence
from tests.analysis.bench_records import NAMES, bench_record


def _blocks(x: np.ndarray, size: int, stream: str = "/imu"):
    for a in range(0, len(x), size):
        chunk = x[a:a + size]
        yield SampleBlock(stream, np.arange(a, a + len(chunk)) / 100.0,
                          {n: chunk[:, k] for k, n in enumerate(NAMES)}, 100.0)


def test_live_equals_batch_and_waits_for_segments():
    x, _ = bench_record(51, n=40000)
    live = LiveCoherence(segment_s=10.24)
    assert live.document()["ready"] is False
    blocks = list(_blocks(x, 250))
    for b in blocks[:4]:
        live.update(b)
    assert live.document()["ready"] is False  # 1000 samples: no 1024-sample segment yet
    for b in blocks[4:]:
        live.update(b)
    doc = live.document()
    assert doc["ready"] and doc["stream"] == "/imu" and len(doc["pairs"]) == 15
    batch = log_coherence(cross_spectra(x, 100.0, NAMES, nperseg=1024)).to_dict()
    assert np.allclose(doc["msc"], batch["msc"], atol=1e-9)
    assert doc["f_hz"] == batch["f_hz"]
    k = doc["pairs"].index(["gyro_x", "accel_y"])  # the simulated rocking at 1.5 Hz
    j = int(np.argmin(np.abs(np.array(doc["f_hz"]) - 1.5)))
    assert doc["msc"][k][j] > doc["threshold"][j]
    with pytest.raises(KeyError, match="valid streams"):
        live.document("/other")


def test_devices_sampled_at_their_own_instants_are_compared_live():
    """Two devices, 0.37 of a period apart, block sizes that differ, a line they share and a
    line of the second alone: the ``devices`` document finds the shared line coherent across
    them and the other not."""
    fs, n = 100.0, 30000
    rng = np.random.default_rng(11)
    t_a = np.arange(n) / fs
    t_b = (np.arange(n) + 0.37) / fs
    live = LiveCoherence(segment_s=10.24)

    def signals(t, own_line: bool) -> dict[str, np.ndarray]:
        ch = {name: 1e-3 * rng.standard_normal(t.size) for name in NAMES}
        ch["gyro_x"] += 2e-3 * np.sin(2 * np.pi * 3.1 * t + 0.4)
        if own_line:
            ch["gyro_y"] += 2e-3 * np.sin(2 * np.pi * 7.7 * t)
        return ch

    a, b = signals(t_a, False), signals(t_b, True)
    blocks = []
    for k in range(0, n, 200):
        blocks.append(SampleBlock("/a/imu", t_a[k:k + 200], {c: v[k:k + 200]
                                                              for c, v in a.items()}, fs))
    for k in range(0, n, 330):  # the second device hands out its own block sizes
        blocks.append(SampleBlock("/b/imu", t_b[k:k + 330], {c: v[k:k + 330]
                                                              for c, v in b.items()}, fs))
    blocks.sort(key=lambda blk: blk.t[-1])  # as they arrive
    for blk in blocks:
        live.update(blk)
    assert live.streams == ["/a/imu", "/b/imu", "devices"]
    doc = live.document("devices")
    assert doc["ready"], doc
    assert doc["n_segments"] >= 0.9 * (n / 512 - 1)  # nearly every chunk fed
    f = np.array(doc["f_hz"])

    def msc(x: str, y: str, hz: float) -> float:
        k = doc["pairs"].index([x, y])
        return float(doc["msc"][k][int(np.argmin(np.abs(f - hz)))])

    assert msc("/a/imu:gyro_x", "/b/imu:gyro_x", 3.1) > 0.9
    assert msc("/a/imu:gyro_y", "/b/imu:gyro_y", 7.7) < 0.2
    assert msc("/a/imu:gyro_x", "/b/imu:gyro_x", 20.0) < 0.2
