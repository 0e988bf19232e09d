import time

import numpy as np
from mcap.reader import make_reader

from imunoise.daq import ros2_msgs as m
from imunoise.daq.readers import open_record
from imunoise.daq.readers.mcap import iter_blocks, raw_counts
from imunoise.daq.recorder import McapRecorder
from tests.mcap_helpers import ACCEL_LSB, GYRO_LSB, TEMP_LSB, make_blocks, record_blocks


def test_file_is_a_ros2_bag_with_rosbag2_channel_metadata(tmp_path):
    rec = record_blocks(tmp_path, make_blocks(5, 100, skip={3: 7}))
    (path,) = rec.stats.files
    assert path.endswith(".mcap") and "adis16350_" in path
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {"/adis16350/imu", "/adis16350/temperature", "/diagnostics"}
        for topic, msgtype in [("/adis16350/imu", m.IMU),
                               ("/adis16350/temperature", m.TEMPERATURE)]:
            ch = topics[topic]
            schema = summary.schemas[ch.schema_id]
            assert (schema.name, schema.encoding, ch.message_encoding) == (msgtype, "ros2msg",
                                                                          "cdr")
            assert schema.data.decode() == m.SCHEMA_TEXT[msgtype]
            assert ch.metadata["topic_type_hash"] == m.TYPE_HASH[msgtype]
            assert ch.metadata["offered_qos_profiles"].startswith("- history: 3\n  depth: 0\n")
        assert all(ci.compression == "zstd" for ci in summary.chunk_indexes)
        assert all(ci.message_index_offsets for ci in summary.chunk_indexes)
        assert summary.statistics.channel_message_counts[topics["/adis16350/imu"].id] == 500
        md = {r.name: r.metadata for r in reader.iter_metadata()}["imunoise"]
        assert md["device"] == "sim:adis16350" and md["config.model"] == "ADIS16350"
        assert md["rate_hz"] == "100.0" and md["software"].startswith("imunoise")
        assert abs(float(md["scale.gyro_x"]) / GYRO_LSB - 1) < 1e-12
        events = list(reader.iter_messages(topics=["/diagnostics"]))
    assert len(events) == 1


def test_values_stamps_and_raw_counts_round_trip_exactly(tmp_path):
    blocks = make_blocks(4, 250, skip={2: 3})
    rec = record_blocks(tmp_path, blocks)
    r = open_record(rec.stats.files[0])
    t = np.concatenate([b.t for b in blocks])
    for name in ("gyro_x", "accel_z"):
        want = np.concatenate([b.channels[name] for b in blocks])
        assert np.array_equal(r.channels[name].values, want)
        counts = raw_counts(r.channels[name].values, r.metadata, name)
        assert np.array_equal(counts, np.concatenate([b.raw[name] for b in blocks]))
    assert r.channels["gyro_x"].segment_starts.tolist() == [0, 500]
    assert abs(r.channels["gyro_x"].fs_hz - 100.0) < 1e-5  # float64 epoch stamps: 0.24 us steps
    assert abs(r.channels["gyro_x"].t0_s - t[0]) < 1e-6
    temp_counts = raw_counts(r.temperature.values, r.metadata, "temp")
    assert np.array_equal(temp_counts, np.concatenate([b.raw["temp"] for b in blocks]))
    assert abs(float(r.metadata["scale.temp"]) - TEMP_LSB) < 1e-12
    assert abs(float(r.metadata["scale.accel_z"]) - ACCEL_LSB) < 1e-15
    assert rec.stats.raw_mismatch == 0


def test_stream_blocks_carry_gaps_and_raw_counts(tmp_path):
    blocks = make_blocks(4, 250, skip={2: 3})
    rec = record_blocks(tmp_path, blocks)
    got = [b for b in iter_blocks(rec.stats.files[0]) if b.stream.endswith("/imu")]
    assert [len(b) for b in got] == [500, 500]
    assert [b.gap_before for b in got] == [0, 3]
    assert np.array_equal(got[1].raw["gyro_y"], np.concatenate([blocks[2].raw["gyro_y"],
                                                                blocks[3].raw["gyro_y"]]))


def test_gyro_only_device_marks_acceleration_missing(tmp_path):
    rec = record_blocks(tmp_path, make_blocks(2, 100, accel=False, stream="/itg3200/imu"))
    r = open_record(rec.stats.files[0])
    assert sorted(r.channels) == ["gyro_x", "gyro_y", "gyro_z"]


def test_rotation_names_files_by_start_time(tmp_path):
    clock = iter(np.arange(1_800_000_000.0, 1_800_010_000.0, 0.5)).__next__
    blocks = make_blocks(6, 100, t0=0.0)  # 1 s per block
    rec = McapRecorder(tmp_path, "adis16350", threaded=False, fsync=False, rotate_s=2.0,
                       clock=clock)
    for b in blocks:
        rec.write(b)
    rec.close()
    assert len(rec.stats.files) == 3
    names = [p.rsplit("/", 1)[1] for p in rec.stats.files]
    assert names[0].startswith("adis16350_20270115T") and names == sorted(names)
    total = sum(open_record(p).channels["gyro_x"].n_samples for p in rec.stats.files)
    assert total == 600


def test_threaded_recorder_makes_data_durable_within_a_second(tmp_path):
    rec = McapRecorder(tmp_path, "adis16350", fsync=True, rotate_s=None, flush_s=0.5)
    t0 = time.time()
    for b in make_blocks(3, 100, t0=t0):
        rec.write(b)
    deadline = time.time() + 1.5
    n = 0
    while time.time() < deadline:
        if rec.stats.files:
            try:
                n = open_record(rec.stats.files[0]).channels["gyro_x"].n_samples
            except ValueError:
                n = 0
            if n == 300:
                break
        time.sleep(0.05)
    assert n == 300, "unflushed data after 1.5 s"
    rec.close()
    assert open_record(rec.stats.files[0]).warnings == []


def test_malformed_block_stops_recording_with_message_and_keeps_file(tmp_path):
    from imunoise.core.blocks import SampleBlock

    rec = McapRecorder(tmp_path, "adis16350", fsync=False, rotate_s=None)
    good = make_blocks(2, 100)
    rec.write(good[0])
    rec.write(SampleBlock("/adis16350/imu", np.arange(5.0), {"gyro_x": np.ones(3),
                                                            "gyro_y": np.ones(5),
                                                            "gyro_z": np.ones(5)}, 100.0))
    rec.write(good[1])
    rec.flush()
    rec.close()
    assert rec.error and rec.error.startswith("recording stopped: ValueError")
    r = open_record(rec.stats.files[0])
    assert r.channels["gyro_x"].n_samples == 100 and r.warnings == []


def test_two_chip_board_records_one_topic_per_stream(tmp_path):
    gyro = make_blocks(2, 100, stream="/razor/itg3200/imu", accel=False, seed=1)
    accel = make_blocks(2, 100, stream="/razor/adxl345/imu", gyro=False, seed=2)
    rec = record_blocks(tmp_path, [gyro[0], accel[0], gyro[1], accel[1]])
    r = open_record(rec.stats.files[0])
    assert sorted(r.channels) == sorted(
        [f"/razor/itg3200/imu:gyro_{a}" for a in "xyz"]
        + [f"/razor/adxl345/imu:accel_{a}" for a in "xyz"])
    assert np.array_equal(r.channels["/razor/adxl345/imu:accel_y"].values,
                          np.concatenate([b.channels["accel_y"] for b in accel]))
    assert rec.stats.samples == 400
