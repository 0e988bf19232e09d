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
