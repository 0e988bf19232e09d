"""The simulated I2C chips' sample source: drawn ahead one channel at a time, the samples
are exactly those of the three channel streams in order, and no single read pays for more
than one channel's chunk."""

from __future__ import annotations

import numpy as np

from imunoise.analysis.noise_stream import stream_factory
from imunoise.daq.sim.i2c_chip import CHUNK, SourceBuffer
from imunoise.daq.sim.signals import model_source

MODEL = [("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-4})]


def test_drawing_ahead_by_channel_keeps_every_sample_in_order() -> None:
    buffered = SourceBuffer(model_source(MODEL, 1000.0, seed=3, bias=0.5,
                                         noise=stream_factory))
    direct = model_source(MODEL, 1000.0, seed=3, bias=0.5, noise=stream_factory)
    got = []
    # a chip's reads: one sample, then the draw-ahead; now and then a longer read
    for i in range(3 * CHUNK):
        got.append(buffered.take(7 if i % 50 == 0 else 1))
        buffered.prefetch()
    got.append(buffered.take(5 * CHUNK))  # more than is buffered: completes a pending draw
    got.append(buffered.skip_take_last(CHUNK + 3)[None, :])
    got = np.vstack(got)
    want = direct(len(got) - 1 + CHUNK + 3)
    np.testing.assert_array_equal(got[:-1], want[:len(got) - 1])
    np.testing.assert_array_equal(got[-1], want[-1])


def test_one_channel_per_prefetch() -> None:
    calls: list[int] = []
    streams = [lambda n, k=k: calls.append(k) or np.full(n, float(k)) for k in range(3)]

    def triad(n: int) -> np.ndarray:
        return np.column_stack([s(n) for s in streams])

    triad.channels = (streams, np.zeros(3))
    buf = SourceBuffer(triad)
    buf.take(1)  # the first chunk, all three channels
    assert calls == [0, 1, 2]
    calls.clear()
    while len(calls) < 3:
        before = len(calls)
        buf.take(1)
        buf.prefetch()
        assert len(calls) - before <= 1
    assert calls == [0, 1, 2]
