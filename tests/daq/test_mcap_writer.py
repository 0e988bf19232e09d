"""The block writer writes the files mcap's own Writer writes, byte for byte."""

from __future__ import annotations

import io

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

from imunoise.daq.mcap_writer import McapBlockWriter


def _operations(seed: int) -> list[tuple]:
    """A random recording: schemas and channels, metadata, blocks of equal-size messages of
    several lengths, single messages of any size, flushes."""
    rng = np.random.default_rng(seed)
    ops: list[tuple] = [("schema", "pkg/msg/A", b"float64 x"), ("schema", "pkg/msg/B", b"int8 y"),
                        ("channel", "/dev/imu", 1), ("channel", "/dev/temperature", 2),
                        ("channel", "/diagnostics", 1),
                        ("metadata", "device", {"rate_hz": "1000.0"})]
    t = 10**18
    seq = {1: 0, 2: 0, 3: 0}
    for step in range(60):
        kind = rng.choice(["block", "block", "block", "single", "flush", "metadata"])
        if kind == "block":
            cid = int(rng.integers(1, 3))
            n = int(rng.integers(1, 400))
            size = 300 if cid == 1 else 48
            times = t + np.cumsum(rng.integers(0, 2_000_000, size=n)).astype(np.int64)
            t = int(times[-1])
            payloads = rng.integers(0, 256, size=(n, size), dtype=np.uint8)
            ops.append(("block", cid, times, payloads, seq[cid]))
            seq[cid] += n
        elif kind == "single":
            data = rng.integers(0, 256, size=int(rng.integers(0, 900)), dtype=np.uint8).tobytes()
            t_event = t - int(rng.integers(0, 10**9))  # events may be stamped in the past
            ops.append(("single", 3, t_event, data, seq[3]))
            seq[3] += 1
        elif kind == "flush":
            ops.append(("flush",))
        else:
            ops.append(("metadata", f"note{step}", {"k": str(step)}))
    return ops


def _write(ops: list[tuple], chunk_size: int, ours: bool) -> bytes:
    out = io.BytesIO()
    if ours:
        writer = McapBlockWriter(out, chunk_size=chunk_size)
    else:
        writer = Writer(out, chunk_size=chunk_size, compression=CompressionType.ZSTD,
                        index_types=IndexType.CHUNK | IndexType.MESSAGE | IndexType.METADATA)
    writer.start(profile="ros2", library="imunoise test")
    for op in ops:
        if op[0] == "schema":
            writer.register_schema(op[1], "ros2msg", op[2])
        elif op[0] == "channel":
            writer.register_channel(op[1], "cdr", op[2], {"offered_qos_profiles": ""})
        elif op[0] == "metadata":
            writer.add_metadata(op[1], op[2])
        elif op[0] == "flush":
            writer.flush()
        elif op[0] == "single":
            _, cid, t, data, seq = op
            writer.add_message(cid, t, data, t, seq)
        elif ours:
            _, cid, times, payloads, seq = op
            writer.add_messages(cid, times, payloads, seq)
        else:
            _, cid, times, payloads, seq = op
            for i, row in enumerate(payloads):
                writer.add_message(cid, int(times[i]), row.tobytes(), int(times[i]), seq + i)
    writer.finish()
    return out.getvalue()


@pytest.mark.parametrize("seed, chunk_size", [(0, 1 << 20), (1, 4096), (2, 700), (3, 50_000)])
def test_the_same_recording_gives_the_same_bytes_as_mcaps_writer(seed, chunk_size):
    ops = _operations(seed)
    ours = _write(ops, chunk_size, ours=True)
    theirs = _write(ops, chunk_size, ours=False)
    assert len(ours) == len(theirs)
    assert ours == theirs


def test_a_block_longer_than_a_chunk_is_split_where_mcaps_writer_splits_it():
    ops = [("schema", "pkg/msg/A", b"float64 x"), ("channel", "/dev/imu", 1),
           ("block", 1, np.arange(5000, dtype=np.int64) * 1000,
            np.full((5000, 100), 7, dtype=np.uint8), 0)]
    data = _write(ops, 10_000, ours=True)
    assert data == _write(ops, 10_000, ours=False)
    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    assert summary is not None
    assert summary.statistics.message_count == 5000
    assert summary.statistics.chunk_count == len(summary.chunk_indexes)
    # each chunk closes right after the message that takes it past 10,000 bytes
    assert all(c.uncompressed_size <= 10_000 + 131 for c in summary.chunk_indexes)
    sequences = [m.sequence for _s, _c, m in reader.iter_messages()]
    assert sequences == list(range(5000))


def test_sequence_numbers_wrap_at_32_bits_instead_of_failing():
    out = io.BytesIO()
    writer = McapBlockWriter(out)
    writer.start("ros2", "test")
    writer.register_schema("pkg/msg/A", "ros2msg", b"")
    writer.register_channel("/a", "cdr", 1, {})
    writer.add_messages(1, np.array([1, 2, 3]), np.zeros((3, 4), dtype=np.uint8), 2**32 - 2)
    writer.finish()
    got = [m.sequence for _s, _c, m in make_reader(io.BytesIO(out.getvalue())).iter_messages()]
    assert got == [2**32 - 2, 2**32 - 1, 0]
