"""The shared-memory hand-over ring: order, wrap-around, counted losses, torn records, status."""

from __future__ import annotations

import multiprocessing as mp
import struct

import numpy as np
import pytest

from imunoise.core.blocks import SampleBlock
from imunoise.live.block_ring import _HEADER, BlockRing


def _block(k: int, n: int = 10) -> SampleBlock:
    t = 1.7e9 + (k * n + np.arange(n)) / 100.0
    return SampleBlock("/imu", t, {"gyro_x": np.full(n, float(k))}, 100.0)


@pytest.fixture
def ring():
    r = BlockRing(create=True, capacity=8192)
    yield r
    r.close()
    r.unlink()


def test_blocks_come_out_in_order_across_many_wraps(ring):
    got = []
    for k in range(500):
        assert ring.put(_block(k), 10)
        if k % 3 == 2:  # the consumer reads in bursts
            while (item := ring.get()) is not None:
                got.append(item)
    while (item := ring.get()) is not None:
        got.append(item)
    assert [int(b.channels["gyro_x"][0]) for b, _ in got] == list(range(500))
    assert all(lost == 0 for _, lost in got)
    assert ring.lost_samples == 0 and ring.used_bytes == 0


def test_a_full_ring_drops_and_the_next_block_carries_the_loss(ring):
    put = [ring.put(_block(k), 10) for k in range(40)]  # nothing read: the ring fills
    first_refused = put.index(False)
    assert all(put[:first_refused]) and not any(put[first_refused:])
    lost = (40 - first_refused) * 10
    assert ring.lost_samples == lost and ring.lost_blocks == 40 - first_refused
    n_read = 0
    while ring.get() is not None:
        n_read += 1
    assert n_read == first_refused
    assert ring.put(_block(99), 10)
    block, before = ring.get()
    assert before == lost and int(block.channels["gyro_x"][0]) == 99
    assert ring.put(_block(100), 10)
    assert ring.get()[1] == 0  # counted once


def test_a_loss_is_carried_by_the_next_block_of_its_own_stream(ring):
    put = [ring.put(_block(k), 10) for k in range(40)]  # the IMU blocks fill the ring
    lost = put.count(False) * 10
    while ring.get() is not None:
        pass
    temp = SampleBlock("/temperature", np.array([1.7e9]), {"temp": np.array([25.0])}, 1.0)
    assert ring.put(temp, 1)  # the first to fit is another stream's block
    assert ring.put(_block(99), 10)
    (first, first_lost), (second, second_lost) = ring.get(), ring.get()
    assert first.stream == "/temperature" and first_lost == 0
    assert second.stream == "/imu" and second_lost == lost > 0


def test_a_record_not_yet_complete_is_read_later(ring):
    assert ring.put(_block(1), 10)
    payload_at = _HEADER + 16
    good = ring._buf[payload_at]
    ring._buf[payload_at] = (good + 1) % 256  # as if the payload were not visible yet
    assert ring.get() is None
    ring._buf[payload_at] = good
    block, _ = ring.get()
    assert int(block.channels["gyro_x"][0]) == 1


def test_status_round_trip_and_attach_by_name(ring):
    assert ring.status() == {}
    ring.publish_status({"samples": 5, "state": "running"})
    other = BlockRing(ring.name)
    try:
        assert other.status() == {"samples": 5, "state": "running"}
        assert other.put(_block(3), 10)
        assert int(ring.get()[0].channels["gyro_x"][0]) == 3
    finally:
        other.close()
    with pytest.raises(ValueError, match="at least 4096"):
        BlockRing(create=True, capacity=100)


def _produce(name: str, n: int) -> None:
    ring = BlockRing(name)
    k = 0
    while k < n:
        if ring.put(_block(k), 10):
            k += 1
    ring.close()


def test_another_process_produces_while_this_one_consumes(ring):
    proc = mp.get_context("spawn").Process(target=_produce, args=(ring.name, 3000))
    proc.start()
    seen = []
    while len(seen) < 3000:
        item = ring.get()
        if item is not None:
            seen.append(int(item[0].channels["gyro_x"][0]))
    proc.join(30)
    assert seen == list(range(3000))
    assert struct.unpack_from("<Q", ring._buf, 16)[0] == struct.unpack_from("<Q", ring._buf,
                                                                             24)[0]
