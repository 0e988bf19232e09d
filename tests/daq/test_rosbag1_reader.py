"""ROS 1 bags written by an independent writer (rosbags), read by imunoise."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.rosbag1 import Writer
from rosbags.typesys import Stores, get_typestore

from imunoise.daq.readers import ReadError, open_record

STORE = get_typestore(Stores.ROS1_NOETIC)
Imu = STORE.types["sensor_msgs/msg/Imu"]
Temperature = STORE.types["sensor_msgs/msg/Temperature"]
Header = STORE.types["std_msgs/msg/Header"]
Time = STORE.types["builtin_interfaces/msg/Time"]
Quaternion = STORE.types["geometry_msgs/msg/Quaternion"]
Vector3 = STORE.types["geometry_msgs/msg/Vector3"]
FS = 200.0
T0_NS = 1_600_000_000_000_000_000


def _imu(seq: int, t_ns: int, w, a, frame: str = "imu_link", no_accel: bool = False):
    cov = np.zeros(9)
    a_cov = np.full(9, -1.0) if no_accel else np.zeros(9)
    return Imu(header=Header(seq=seq, stamp=Time(sec=t_ns // 10**9, nanosec=t_ns % 10**9),
                             frame_id=frame),
               orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=cov,
               angular_velocity=Vector3(x=w[0], y=w[1], z=w[2]), angular_velocity_covariance=cov,
               linear_acceleration=Vector3(x=a[0], y=a[1], z=a[2]),
               linear_acceleration_covariance=a_cov)


def write_bag(path, n: int = 3000, *, compression=None, topics=("/imu/data",), lost=(),
              temperature: bool = True, seed: int = 0, chunk_bytes: int = 64 * 1024,
              frames=("imu_link",)):
    """A bag of ``n`` samples per IMU topic at 200 Hz; grid positions in ``lost`` are skipped
    (their seq numbers too). Returns {topic: (gyro (n, 3), accel (n, 3))} of what was written."""
    rng = np.random.default_rng(seed)
    written = {}
    bag = Writer(path)
    if compression:
        bag.set_compression(compression)
    bag.chunk_threshold = chunk_bytes
    with bag:
        conns = {tp: bag.add_connection(tp, Imu.__msgtype__, typestore=STORE) for tp in topics}
        tconn = (bag.add_connection("/imu/temperature", Temperature.__msgtype__, typestore=STORE)
                 if temperature else None)
        keep = [k for k in range(n + len(lost)) if k not in set(lost)]
        for tp, conn in conns.items():
            w = rng.normal(0.0, 1e-3, (len(keep), 3))
            a = rng.normal(0.0, 1e-2, (len(keep), 3)) + [0.0, 0.0, 9.81]
            written[tp] = (w, a)
            for i, k in enumerate(keep):
                t = T0_NS + int(k * 1e9 / FS)
                msg = _imu(k + 1, t, w[i], a[i], frame=frames[i % len(frames)])
                bag.write(conn, t, STORE.serialize_ros1(msg, Imu.__msgtype__))
        if tconn is not None:
            for s in range(0, n // int(FS)):
                t = T0_NS + s * 10**9
                msg = Temperature(header=Header(seq=s, stamp=Time(sec=t // 10**9, nanosec=0),
                                                frame_id="imu_link"),
                                  temperature=25.0 + 0.01 * s, variance=0.0)
                bag.write(tconn, t, STORE.serialize_ros1(msg, Temperature.__msgtype__))
    return written


@pytest.mark.parametrize("compression", [None, Writer.CompressionFormat.BZ2,
                                         Writer.CompressionFormat.LZ4],
                         ids=["plain", "bz2", "lz4"])
def test_imu_and_temperature_read_exactly(tmp_path, compression):
    path = tmp_path / "robot.bag"
    (w, a), = write_bag(path, compression=compression).values()
    rec = open_record(path)
    assert list(rec.channels) == ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    np.testing.assert_array_equal(rec.channels["gyro_y"].values, w[:, 1])
    np.testing.assert_array_equal(rec.channels["accel_z"].values, a[:, 2])
    g = rec.channels["gyro_x"]
    assert g.fs_hz == FS and list(g.segment_starts) == [0] and g.units == "rad/s"
    assert g.t0_s == pytest.approx(T0_NS * 1e-9)
    assert rec.temperature is not None and rec.temperature.n_samples == 15
    assert rec.temperature.values[3] == pytest.approx(25.03)
    assert rec.metadata["format"] == "rosbag1" and rec.warnings == []


def test_sequence_numbers_mark_the_lost_messages(tmp_path):
    path = tmp_path / "lossy.bag"
    write_bag(path, lost=(1000, 1001, 2500), temperature=False)
    rec = open_record(path)
    g = rec.channels["gyro_z"]
    assert list(g.segment_starts) == [0, 1000, 2498]
    assert any("3 sample(s) missing in 2 gap(s)" in w for w in rec.warnings)


def test_several_topics_and_frame_ids_and_missing_accel(tmp_path):
    path = tmp_path / "two.bag"
    written = write_bag(path, n=800, topics=("/a/imu", "/b/imu"), frames=("imu", "imu_link_2"),
                        temperature=False)
    rec = open_record(path)
    assert sorted(rec.channels) == sorted(f"{tp}:{c}" for tp in ("/a/imu", "/b/imu") for c in
                                          ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y",
                                           "accel_z"))
    np.testing.assert_array_equal(rec.channels["/b/imu:gyro_x"].values, written["/b/imu"][0][:, 0])


def test_a_bag_cut_short_is_read_to_its_last_complete_chunk(tmp_path):
    path = tmp_path / "crashed.bag"
    (w, _a), = write_bag(path, n=6000, temperature=False, chunk_bytes=32 * 1024).values()
    data = path.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) * 2 // 3])
    rec = open_record(cut)
    g = rec.channels["gyro_x"]
    assert 1000 < g.n_samples < 6000
    np.testing.assert_array_equal(g.values, w[: g.n_samples, 0])
    assert any("cut short" in m and "last complete chunk" in m for m in rec.warnings)


def test_not_a_bag_is_one_clear_error(tmp_path):
    path = tmp_path / "x.bag"
    path.write_bytes(b"hello")
    with pytest.raises(ReadError, match="not a ROS 1 bag"):
        open_record(path)
    empty = tmp_path / "empty.bag"
    with Writer(empty) as bag:
        bag.add_connection("/chatter", "std_msgs/msg/String", typestore=STORE)
    with pytest.raises(ReadError, match="no sensor_msgs/Imu"):
        open_record(empty)
