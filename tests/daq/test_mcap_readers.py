import numpy as np
import pytest
from mcap.writer import CompressionType, IndexType, Writer

from imunoise.core.blocks import SampleBlock
from imunoise.daq import ros2_msgs as m
from imunoise.daq.readers import mcap as bulk
from imunoise.daq.readers import mcap_decode, open_record
from imunoise.daq.readers.mcap import iter_blocks, read_mcap
from imunoise.daq.recorder import McapRecorder
from tests.mcap_helpers import make_blocks, record_blocks


def _write_plain(path, n, compression, index_types, chunk_size=20_000, topics=("/imu",)):
    rng = np.random.default_rng(5)
    t = 100.0 + np.arange(n) / 50.0
    data = {}
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=chunk_size, compression=compression, index_types=index_types)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(m.IMU, "ros2msg", m.SCHEMA_TEXT[m.IMU].encode())
        tsid = w.register_schema(m.TEMPERATURE, "ros2msg", m.SCHEMA_TEXT[m.TEMPERATURE].encode())
        cids = {tp: w.register_channel(tp, "cdr", sid) for tp in topics}
        tcid = w.register_channel("/temp", "cdr", tsid)
        for tp in topics:
            g, a = rng.normal(size=(n, 3)), rng.normal(size=(n, 3))
            data[tp] = (g, a)
        temps = m.encode_temperature(t, 20 + np.arange(n) * 0.01)
        recs = {tp: m.encode_imu(t, *data[tp]) for tp in topics}
        for i in range(n):
            for tp in topics:
                w.add_message(cids[tp], int(t[i] * 1e9), recs[tp][i].tobytes(), 0, i)
            w.add_message(tcid, int(t[i] * 1e9), temps[i].tobytes(), 0, i)
        w.finish()
    return t, data


@pytest.mark.parametrize("compression,index", [
    (CompressionType.LZ4, IndexType.ALL),
    (CompressionType.NONE, IndexType.ALL),
    (CompressionType.ZSTD, IndexType.CHUNK),  # no message indexes: chunks are walked
])
def test_bulk_reader_variants(tmp_path, compression, index):
    path = tmp_path / "v.mcap"
    t, data = _write_plain(path, 1500, compression, index)
    r = read_mcap(path)
    g, a = data["/imu"]
    assert np.array_equal(r.channels["gyro_x"].values, g[:, 0])
    assert np.array_equal(r.channels["accel_z"].values, a[:, 2])
    assert np.allclose(r.temperature.values, 20 + np.arange(1500) * 0.01)
    assert r.channels["gyro_x"].fs_hz == pytest.approx(50.0, rel=1e-9)
    assert r.warnings == []


def test_several_imu_topics_are_prefixed(tmp_path):
    path = tmp_path / "two.mcap"
    _t, data = _write_plain(path, 300, CompressionType.ZSTD, IndexType.ALL,
                            topics=("/left/imu", "/right/imu"))
    r = open_record(path)
    assert "/left/imu:gyro_x" in r.channels and "/right/imu:accel_y" in r.channels
    assert np.array_equal(r.channels["/right/imu:accel_y"].values, data["/right/imu"][1][:, 1])


def test_crashed_file_reads_to_last_complete_chunk(tmp_path):
    rec = record_blocks(tmp_path, make_blocks(10, 100))  # one chunk per block (1 s flushes)
    path = rec.stats.files[0]
    full = open(path, "rb").read()
    src = bulk.open_mcap(path)
    imu_cid = next(c for c, tp in src.topics.items() if tp.kind == "imu")
    chunk = src.layout.chunks[6]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full[:chunk.start + (chunk.end - chunk.start) // 2])
    r = open_record(cut)
    want = sum(c.mi[imu_cid][1] for c in src.layout.chunks[:6])
    assert want == 600
    assert r.channels["gyro_z"].n_samples == want
    assert any("truncated" in w for w in r.warnings)


def test_streaming_blocks_match_bulk_read_with_small_batches(tmp_path, monkeypatch):
    rec = record_blocks(tmp_path, make_blocks(12, 250, skip={5: 2, 9: 1}))
    path = rec.stats.files[0]
    monkeypatch.setattr(mcap_decode, "BATCH_BYTES", 50_000)
    blocks = [b for b in iter_blocks(path) if b.stream.endswith("/imu")]
    assert len(blocks) > 3
    whole = read_mcap(path)
    assert np.array_equal(np.concatenate([b.channels["gyro_y"] for b in blocks]),
                          whole.channels["gyro_y"].values)
    assert sum(b.gap_before for b in blocks) == 3
    for b in blocks:
        assert np.allclose(np.diff(b.t), 1 / 100.0, atol=1e-6)


def _record_values(tmp_path, t, gyro_x):
    rec = McapRecorder(tmp_path, "dev", threaded=False, fsync=False, rotate_s=None)
    ch = {c: np.zeros(len(t)) for c in ("gyro_x", "gyro_y", "gyro_z")}
    ch["gyro_x"] = gyro_x
    rec.write(SampleBlock("/dev/imu", t, ch, 100.0))
    rec.close()
    return rec.stats.files[0]


def test_nan_samples_dropped_with_warning_and_segment_break(tmp_path):
    t = 10.0 + np.arange(1000) / 100.0
    x = np.ones(1000)
    x[[100, 101, 500]] = np.nan
    r = open_record(_record_values(tmp_path, t, x))
    s = r.channels["gyro_x"]
    assert s.n_samples == 997 and np.all(np.isfinite(s.values))
    assert s.segment_starts.tolist() == [0, 100, 498]
    assert any("3 non-finite samples dropped" in w for w in r.warnings)
    assert r.channels["gyro_y"].segment_starts.tolist() == [0]


def test_time_going_backwards_starts_a_new_segment_with_warning(tmp_path):
    t = 10.0 + np.arange(1000) / 100.0
    t[600:] -= 3.0
    r = open_record(_record_values(tmp_path, t, np.ones(1000)))
    assert r.channels["gyro_x"].segment_starts.tolist() == [0, 600]
    assert any("backwards" in w for w in r.warnings)
    assert r.channels["gyro_x"].fs_hz == pytest.approx(100.0, rel=1e-6)


def test_rate_override_sets_rate_and_judges_gaps_by_it(tmp_path):
    rec = record_blocks(tmp_path, make_blocks(2, 300, fs=100.0, skip={1: 5}))
    r = open_record(rec.stats.files[0], rate_hz=102.4)
    assert r.channels["gyro_x"].fs_hz == 102.4
    assert r.channels["gyro_x"].segment_starts.tolist() == [0, 300]
    assert r.metadata["format"] == "mcap"


def _same_record(a, b):
    assert a.channels.keys() == b.channels.keys()
    for k in a.channels:
        assert np.array_equal(a.channels[k].values, b.channels[k].values), k
        assert np.array_equal(a.channels[k].segment_starts, b.channels[k].segment_starts), k
    assert np.array_equal(a.temperature.values, b.temperature.values)


@pytest.mark.parametrize("ahead", [True, False])
def test_read_ahead_and_batch_decompression_change_nothing(tmp_path, monkeypatch, ahead):
    rec = record_blocks(tmp_path, make_blocks(40, 100, skip={7: 3}))
    path = rec.stats.files[0]
    monkeypatch.setattr(mcap_decode, "BATCH_BYTES", 60_000)  # many batches of several chunks
    monkeypatch.setattr(mcap_decode, "READ_AHEAD", ahead)
    assert mcap_decode.read_ahead() is ahead
    fast = read_mcap(path)
    # reference: every chunk decompressed on its own
    monkeypatch.setattr(bulk.ml, "decompress_zstd_frames", lambda frames, sizes: None)
    _same_record(fast, read_mcap(path))
    assert fast.channels["gyro_x"].n_samples == 40 * 100
    assert fast.channels["gyro_x"].segment_starts.tolist() == [0, 700]


def test_chunk_with_wrong_declared_size_is_still_read_whole(tmp_path, monkeypatch):
    """A chunk header that understates its uncompressed size fails the batched zstd call;
    the chunks are then decompressed one by one and every message is kept."""
    rec = record_blocks(tmp_path, make_blocks(12, 100))
    path = rec.stats.files[0]
    monkeypatch.setattr(mcap_decode, "BATCH_BYTES", 1 << 20)  # one batch holds every chunk
    want = read_mcap(path)
    src = bulk.open_mcap(path)
    chunk = src.layout.chunks[-1]
    data = bytearray(open(path, "rb").read())
    at = chunk.start + 9 + 16  # record prefix, start and end times -> uncompressed_size
    declared = int.from_bytes(data[at:at + 8], "little")
    assert declared == chunk.uncompressed_size
    data[at:at + 8] = (declared - 64).to_bytes(8, "little")
    bad = tmp_path / "understated.mcap"
    bad.write_bytes(bytes(data))
    results = []
    batched = bulk.ml.decompress_zstd_frames

    def spy(frames, sizes):
        results.append(batched(frames, sizes))
        return results[-1]

    monkeypatch.setattr(bulk.ml, "decompress_zstd_frames", spy)
    _same_record(want, read_mcap(bad))
    assert results and results[-1] is None  # the one-by-one path read the last batch
