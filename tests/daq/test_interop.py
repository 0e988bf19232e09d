"""Files we write are read by independent readers; files others write are read by us."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2Writer
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as BagWriter
from rosbags.typesys import Stores, get_typestore

from imunoise.daq import ros2_msgs as m
from imunoise.daq.readers import open_record
from imunoise.daq.readers.mcap import UnsupportedLayout, read_mcap
from tests.mcap_helpers import make_blocks, record_blocks

FS = 200.0


@pytest.fixture(scope="module")
def ours(tmp_path_factory):
    out = tmp_path_factory.mktemp("ours")
    blocks = make_blocks(3, 400, fs=FS, skip={1: 4})
    rec = record_blocks(out, blocks)
    cat = {k: np.concatenate([b.channels[k] for b in blocks]) for k in blocks[0].channels}
    t = np.concatenate([b.t for b in blocks])
    return Path(rec.stats.files[0]), t, cat


def test_rosbags_reads_our_file(ours):
    path, t, cat = ours
    with AnyReader([path]) as reader:
        conns = {c.topic: c for c in reader.connections}
        assert conns["/adis16350/imu"].msgtype == m.IMU
        assert conns["/adis16350/imu"].msgcount == len(t)
        assert conns["/adis16350/temperature"].msgcount == len(t)
        assert conns["/diagnostics"].msgtype == m.DIAGNOSTIC_ARRAY
        stamps, gx, az, temp = [], [], [], []
        for conn, _ts, raw in reader.messages(connections=[conns["/adis16350/imu"],
                                                           conns["/adis16350/temperature"]]):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.msgtype == m.IMU:
                stamps.append(msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec)
                gx.append(msg.angular_velocity.x)
                az.append(msg.linear_acceleration.z)
                assert msg.header.frame_id == "adis16350_link"
            else:
                temp.append(msg.temperature)
    assert np.array_equal(gx, cat["gyro_x"]) and np.array_equal(az, cat["accel_z"])
    assert np.array_equal(temp, cat["temp"])
    assert np.array_equal(stamps, np.rint(t * 1e9).astype(np.int64))


def test_mcap_reader_with_ros2_decoder_reads_our_file(ours):
    path, t, cat = ours
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        got = [(msg.header.stamp.sec, msg.angular_velocity.y, msg.linear_acceleration.x)
               for _s, _c, _m, msg in reader.iter_decoded_messages(topics=["/adis16350/imu"])]
    assert len(got) == len(t)
    assert np.array_equal([g[1] for g in got], cat["gyro_y"])
    assert np.array_equal([g[2] for g in got], cat["accel_x"])


def _imu_dict(stamp_ns, g, a, frame):
    return {"header": {"stamp": {"sec": int(stamp_ns // 10**9),
                                 "nanosec": int(stamp_ns % 10**9)}, "frame_id": frame},
            "orientation": {"w": 1.0}, "orientation_covariance": [-1.0] + [0.0] * 8,
            "angular_velocity": dict(zip("xyz", g, strict=True)),
            "angular_velocity_covariance": [0.0] * 9,
            "linear_acceleration": dict(zip("xyz", a, strict=True)),
            "linear_acceleration_covariance": [0.0] * 9}


def _signals(n, seed=1):
    rng = np.random.default_rng(seed)
    ns = 1_600_000_000 * 10**9 + np.arange(n, dtype=np.int64) * 5_000_000  # 200 Hz
    return ns, rng.normal(size=(n, 3)), rng.normal(9.8, 0.1, size=(n, 3))


@pytest.mark.parametrize("frames", [("imu_link",), ("base", "imu_link_long_name")])
def test_we_read_mcap_ros2_support_files(tmp_path, frames):
    ns, g, a = _signals(600)
    path = tmp_path / "other.mcap"
    with open(path, "wb") as f, Ros2Writer(f) as w:
        schema = w.register_msgdef(m.IMU, m.SCHEMA_TEXT[m.IMU])
        for i in range(len(ns)):
            w.write_message("/robot/imu/data_raw", schema,
                            _imu_dict(ns[i], g[i], a[i], frames[i % len(frames)]),
                            log_time=int(ns[i]), sequence=i)
    if len(frames) > 1:  # frame_id length varies: bulk reader declines, rosbags takes over
        with pytest.raises(UnsupportedLayout):
            read_mcap(path)
    r = open_record(path)
    assert np.array_equal(r.channels["gyro_z"].values, g[:, 2])
    assert np.array_equal(r.channels["accel_y"].values, a[:, 1])
    assert r.channels["gyro_x"].fs_hz == pytest.approx(200.0, rel=1e-9)
    assert r.channels["gyro_x"].t0_s == pytest.approx(1.6e9)


def _rosbags_bag(path: Path, ns, g, a, topic="/imu/data"):
    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    with BagWriter(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conn = w.add_connection(topic, m.IMU, typestore=ts)
        tconn = w.add_connection("/imu/temperature", m.TEMPERATURE, typestore=ts)
        for i in range(len(ns)):
            hdr = T["std_msgs/msg/Header"](
                stamp=T["builtin_interfaces/msg/Time"](sec=int(ns[i] // 10**9),
                                                      nanosec=int(ns[i] % 10**9)),
                frame_id="imu")
            vec = T["geometry_msgs/msg/Vector3"]
            cov = np.zeros(9)
            msg = T[m.IMU](header=hdr,
                           orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0,
                                                                         w=1.0),
                           orientation_covariance=cov, angular_velocity=vec(*g[i]),
                           angular_velocity_covariance=cov, linear_acceleration=vec(*a[i]),
                           linear_acceleration_covariance=cov)
            w.write(conn, int(ns[i]), ts.serialize_cdr(msg, m.IMU))
            if i % 20 == 0:
                temp = T[m.TEMPERATURE](header=hdr, temperature=30.0 + i / 1000, variance=0.0)
                w.write(tconn, int(ns[i]), ts.serialize_cdr(temp, m.TEMPERATURE))


def test_we_read_a_rosbags_written_rosbag2_folder_and_its_mcap(tmp_path):
    ns, g, a = _signals(500, seed=2)
    bag = tmp_path / "bag"
    _rosbags_bag(bag, ns, g, a)
    assert (bag / "metadata.yaml").is_file()
    r = open_record(bag)
    assert np.array_equal(r.channels["gyro_x"].values, g[:, 0])
    assert r.temperature.n_samples == 25 and r.temperature.values[1] == 30.02
    (mcap_file,) = bag.glob("*.mcap")
    r2 = read_mcap(mcap_file)  # the bulk reader takes rosbag2's own layout
    assert np.array_equal(r2.channels["accel_z"].values, a[:, 2])


def test_we_read_a_split_rosbag2_folder(tmp_path):
    ns, g, a = _signals(800, seed=3)
    _rosbags_bag(tmp_path / "part1", ns[:400], g[:400], a[:400])
    _rosbags_bag(tmp_path / "part2", ns[400:], g[400:], a[400:])
    bag = tmp_path / "part1"
    (second,) = (tmp_path / "part2").glob("*.mcap")
    second.rename(bag / "part1_1.mcap")
    meta = yaml.safe_load((bag / "metadata.yaml").read_text())
    meta2 = yaml.safe_load((tmp_path / "part2" / "metadata.yaml").read_text())
    info, info2 = meta["rosbag2_bagfile_information"], meta2["rosbag2_bagfile_information"]
    info["relative_file_paths"].append("part1_1.mcap")
    info2["files"][0]["path"] = "part1_1.mcap"
    info["files"].extend(info2["files"])
    info["message_count"] += info2["message_count"]
    for t1, t2 in zip(info["topics_with_message_count"], info2["topics_with_message_count"],
                      strict=True):
        t1["message_count"] += t2["message_count"]
    info["duration"]["nanoseconds"] = int(ns[-1] - ns[0])
    (bag / "metadata.yaml").write_text(yaml.safe_dump(meta))
    r = open_record(bag)
    assert r.channels["gyro_y"].n_samples == 800
    assert np.array_equal(r.channels["gyro_y"].values, g[:, 1])
    assert r.channels["gyro_y"].segment_starts.tolist() == [0]


def test_we_read_an_unchunked_file_through_the_fallback(tmp_path):
    ns, g, a = _signals(300, seed=4)
    path = tmp_path / "fastwrite.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f, use_chunking=False)
        w.start(profile="ros2", library="test")
        sid = w.register_schema(m.IMU, "ros2msg", m.SCHEMA_TEXT[m.IMU].encode())
        cid = w.register_channel("/imu", "cdr", sid)
        rec = m.encode_imu(ns * 1e-9, g, a, "imu")
        for i in range(len(ns)):
            w.add_message(cid, int(ns[i]), rec[i].tobytes(), int(ns[i]), i)
        w.finish()
    r = open_record(path)
    assert r.warnings and "message by message" in r.warnings[0]
    assert np.array_equal(r.channels["accel_x"].values, a[:, 0])
