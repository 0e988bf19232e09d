"""Several devices at once: topic names, port pairing, one file with a topic per device."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.core.blocks import SampleBlock
from imunoise.daq.device_group import (
    SEED_STRIDE,
    DeviceGroup,
    member_seed,
    pair_devices,
    renamed,
    topic_names,
)
from imunoise.daq.readers.mcap import open_mcap, raw_counts, read_mcap
from imunoise.daq.recorder import McapRecorder
from imunoise.live.recorder_sink import GroupRecorderSink


def test_topic_names_number_repeats_and_keep_the_first():
    assert topic_names(["sim:adis16350", "sim:razor", "adis16350", "sim:adis16350"]) == \
        ["adis16350", "razor", "adis16350_2", "adis16350_3"]
    assert renamed("/razor/itg3200/imu", "razor_2") == "/razor_2/itg3200/imu"
    assert renamed("/adis16350/temperature", "adis16350") == "/adis16350/temperature"


def test_ports_and_buses_pair_in_device_order():
    members = pair_devices(["adis16350", "razor", "sim:adis16350", "adis16350", "itg3200"],
                           ports=["/dev/ttyUSB0", "/dev/ttyUSB1"], buses=[1, 3])
    assert [(m.name, m.port, m.bus) for m in members] == [
        ("adis16350", "/dev/ttyUSB0", None), ("razor", None, 1),
        ("adis16350_2", None, None), ("adis16350_3", "/dev/ttyUSB1", None),
        ("itg3200", None, 3)]
    assert member_seed(5, 0) == 5 and member_seed(5, 2) == 5 + 2 * SEED_STRIDE


@pytest.mark.parametrize("ports,buses,match", [
    ([], [1], "one --port per real adis16350"),
    (["/dev/ttyUSB0"], [], "one --bus per real"),
    (["/dev/ttyUSB0", "/dev/ttyUSB1"], [1], "2 --port"),
])
def test_unpaired_ports_and_buses_are_refused_with_the_rule(ports, buses, match):
    with pytest.raises(ValueError, match=match):
        pair_devices(["adis16350", "razor"], ports=ports, buses=buses)


class _Feed:
    """An acquisition stand-in: fixed batches of one stream, with counts in ``raw``."""

    def __init__(self, stream: str, fs: float, scale: float, n_blocks: int, seed: int):
        rng = np.random.default_rng(seed)
        self.rate_hz = fs
        self.config = {"model": stream}
        self.stats = type("S", (), {"state": "running", "reconnects": 0, "last_error": "",
                                    "samples": 0, "dropped": 0, "gaps": 0,
                                    "as_dict": lambda s: {"state": "running"}})()
        self._batches = []
        for k in range(n_blocks):
            counts = {c: rng.integers(-500, 500, 50) for c in ("gyro_x", "gyro_y", "gyro_z")}
            t = 100.0 + (k * 50 + np.arange(50)) / fs
            self._batches.append([SampleBlock(stream, t, {c: v * scale
                                                          for c, v in counts.items()},
                                              fs_hz=fs, raw=counts)])

    def open(self):
        pass

    def stop(self):
        pass

    def close(self):
        pass

    def batches(self, duration_s=None):
        yield from self._batches


def test_one_file_holds_a_topic_per_device_with_its_own_scales(tmp_path):
    a = _Feed("/itg3200/imu", 100.0, 1.2e-3, 8, 1)
    b = _Feed("/itg3200/imu", 200.0, 2.5e-4, 8, 2)
    group = DeviceGroup([("itg3200", a), ("itg3200_2", b)], ["sim:itg3200", "sim:itg3200"])
    rec = McapRecorder(tmp_path, "+".join(group.names), threaded=False, fsync=False,
                       devices={"itg3200": {"spec": "sim:itg3200", "rate_hz": 100.0},
                                "itg3200_2": {"spec": "sim:itg3200", "rate_hz": 200.0}})
    sink = GroupRecorderSink(rec, group)
    sent: dict[str, list[np.ndarray]] = {}
    for block in group.blocks():
        sink.write(block)
        sent.setdefault(block.stream, []).append(block.raw["gyro_x"])
    sink.close()
    path = rec.stats.files[-1]
    assert path.endswith(".mcap") and "itg3200_itg3200_2_" in path
    r = read_mcap(path)
    assert sorted(r.channels) == sorted(f"{t}:gyro_{a}" for t in ("/itg3200/imu",
                                                                    "/itg3200_2/imu")
                                        for a in "xyz")
    assert r.channels["/itg3200/imu:gyro_x"].fs_hz == pytest.approx(100.0)
    assert r.channels["/itg3200_2/imu:gyro_x"].fs_hz == pytest.approx(200.0)
    for topic in ("/itg3200/imu", "/itg3200_2/imu"):
        counts = raw_counts(r.channels[f"{topic}:gyro_x"].values, r.metadata, f"{topic}:gyro_x")
        np.testing.assert_array_equal(counts, np.concatenate(sent[topic]))
    assert r.metadata["devices"] == "itg3200,itg3200_2"
    assert r.metadata["device.itg3200_2.rate_hz"] == "200.0"
    frames = {ch.topic for ch in open_mcap(path).layout.channels.values()}
    assert {"/itg3200/imu", "/itg3200_2/imu"} <= frames
