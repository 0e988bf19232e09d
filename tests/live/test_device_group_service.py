"""The live service on several devices in-process (``serve --acquisition thread``): channels
named by topic, /health per device, one file."""

from __future__ import annotations

import time

import pytest

from imunoise.analysis.noise_stream import stream_factory
from imunoise.daq.devices import open_devices
from imunoise.daq.readers.mcap import read_mcap
from imunoise.daq.recorder import McapRecorder
from imunoise.daq.sim.bench import BENCHES
from imunoise.live.recorder_sink import GroupRecorderSink
from imunoise.live.scheduler import RollingAnalyzer
from imunoise.live.service import LiveService

pytestmark = pytest.mark.realtime


def test_a_group_serves_every_device_channel_and_reports_each_device(tmp_path):
    group = open_devices(["sim:itg3200", "sim:itg3200", "sim:adxl345"], seed=2,
                         bench=BENCHES["sway"], noise=stream_factory)
    group.open()
    rec = McapRecorder(tmp_path, "+".join(group.names), fsync=False,
                       devices={n: {"spec": s, "rate_hz": a.rate_hz}
                                for (n, a), s in zip(group.members, group.specs, strict=True)})
    service = LiveService(group, RollingAnalyzer(qualified=True, refit_interval_s=60.0),
                          sinks=[GroupRecorderSink(rec, group)],
                          device={"spec": "+".join(group.specs),
                                  "devices": [{"name": n, "spec": s} for n, s in
                                              zip(group.names, group.specs, strict=True)]})
    service.start()
    try:
        time.sleep(6.0)
        health = service.health()
    finally:
        service.stop()
    assert [d["name"] for d in health["devices"]] == ["itg3200", "itg3200_2", "adxl345"]
    assert [d["spec"] for d in health["devices"]] == ["sim:itg3200", "sim:itg3200",
                                                      "sim:adxl345"]
    for d in health["devices"]:
        assert d["samples"] > 400 and d["state"] == "running", d
    assert health["devices"][1]["channels"] == [f"/itg3200_2/imu:gyro_{a}" for a in "xyz"]
    assert sorted(health["channels"]) == sorted(
        [f"/itg3200/imu:gyro_{a}" for a in "xyz"] + [f"/itg3200_2/imu:gyro_{a}" for a in "xyz"]
        + [f"/adxl345/imu:accel_{a}" for a in "xyz"])
    r = read_mcap(rec.stats.files[-1])
    assert {k.split(":")[0] for k in r.channels} == {"/itg3200/imu", "/itg3200_2/imu",
                                                     "/adxl345/imu"}
