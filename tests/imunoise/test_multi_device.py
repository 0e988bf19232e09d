"""`record` and `serve` with two simulated sensors on one simulated bench: one file, a topic per
device at its rate, and the bench's sway coherent across the two."""

from __future__ import annotations

import re
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from scipy import signal

from imunoise.cli import main
from imunoise.daq.readers.mcap import read_mcap
from tests.live_helpers import free_port, interrupt

ROOT = Path(__file__).resolve().parents[2]
SWAY_HZ = 0.56
TOPICS = {"/adis16350/imu": 102.4, "/razor/itg3200/imu": 100.0, "/razor/adxl345/imu": 100.0}

pytestmark = pytest.mark.realtime


def _sway_coherence(path: str) -> tuple[float, float]:
    """Coherence at the sway line between the ADIS16350 and the razor (both nearly aligned
    with the bench), gyro x and accelerometer y (the sway's stronger axes), on the ADIS16350's
    stamps."""
    r = read_mcap(path)
    ch = r.channels

    def on_grid(name: str, t: np.ndarray) -> np.ndarray:
        s = ch[name]
        ts = s.t0_s + np.arange(s.n_samples) / s.fs_hz
        return np.interp(t, ts, s.values)

    a = ch["/adis16350/imu:gyro_x"]
    t = a.t0_s + np.arange(a.n_samples) / a.fs_hz
    t = t[(t > t[0] + 1) & (t < t[-1] - 1)]
    out = []
    for a_name, r_name in (("/adis16350/imu:gyro_x", "/razor/itg3200/imu:gyro_x"),
                           ("/adis16350/imu:accel_y", "/razor/adxl345/imu:accel_y")):
        f, c = signal.coherence(on_grid(a_name, t), on_grid(r_name, t), fs=a.fs_hz,
                                nperseg=512)
        near = np.abs(f - SWAY_HZ) <= f[1]
        _, p = signal.welch(on_grid(a_name, t), fs=a.fs_hz, nperseg=512)
        k = np.flatnonzero(near)[np.argmax(p[near])]
        out.append(float(c[k]))
    return out[0], out[1]


def _check_file(path: str, seconds: float) -> None:
    r = read_mcap(path)
    timing = r.facts["timing"]
    assert set(timing) == set(TOPICS), timing
    for topic, fs in TOPICS.items():
        assert timing[topic]["fs_hz"] == pytest.approx(fs, rel=2e-3), (topic, timing[topic])
        n = r.channels[next(k for k in r.channels if k.startswith(topic + ":"))].n_samples
        # the whole run is recorded, less what a loaded machine loses: up to 0.6 % of a
        # simulated ADIS16350's samples in 2-minute runs here under a load average of 17 on
        # 2 cores (bench/multi.py); 2 % catches one device starving the other
        assert n >= 0.9 * seconds * fs, (topic, n)
        assert timing[topic]["missing_samples"] <= 0.02 * n, (topic, timing[topic])
    assert set(r.metadata["devices"].split(",")) == {"adis16350", "razor"}
    gyro, accel = _sway_coherence(path)
    # the bench's sway is seen by both: coherence near 1 (strong line, 0.2 Hz bins); accel
    # 0.865-0.910 in seven `serve` runs, five of them beside two or three busy processes, and
    # 0.668 once, not reproduced. The timing facts go with a failure: a device's clock
    # drifting against the other's, or samples lost without a gap in the stamps, show there.
    assert gyro > 0.9 and accel > 0.8, (gyro, accel, timing)


def test_record_two_simulated_sensors_on_one_bench(tmp_path, capsys):
    seconds = 40.0
    assert main(["record", "--device", "sim:adis16350", "--device", "sim:razor",
                 "--bench", "sway", "--seed", "4", "--duration", f"{seconds:g}s",
                 "--out", str(tmp_path)]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    m = re.match(r"record: done: (\d+) samples in (\S+\.mcap) \(adis16350 (\d+), razor (\d+)\)$",
                 err[-1])
    assert m, err
    assert len(list(tmp_path.glob("*.mcap"))) == 1
    assert Path(m.group(2)).name.startswith("adis16350_razor_")
    _check_file(m.group(2), seconds)


def test_record_refuses_unpaired_ports(tmp_path, capsys):
    assert main(["record", "--device", "adis16350", "--device", "razor", "--bus", "1",
                 "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "one --port per real adis16350" in err[0]


def test_serve_two_simulated_sensors_on_one_bench(tmp_path):
    port = free_port()
    out = tmp_path / "data"
    proc = subprocess.Popen(
        [sys.executable, "-m", "imunoise", "serve", "--device", "sim:adis16350", "--device",
         "sim:razor", "--bench", "sway", "--seed", "4", "--out", str(out), "--port", str(port)],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    base = f"http://127.0.0.1:{port}"
    seconds = 40.0
    health = None
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60 and proc.poll() is None:
            try:
                health = httpx.get(base + "/health", timeout=5).json()
            except httpx.HTTPError:
                health = None
            if health and len(health.get("channels") or []) == 12:
                break
            time.sleep(0.5)
        assert health and health.get("devices"), health
        time.sleep(seconds)
        health = httpx.get(base + "/health", timeout=5).json()
        assert [d["name"] for d in health["devices"]] == ["adis16350", "razor"]
        for d in health["devices"]:
            assert d["state"] == "running" and d["samples"] > 0, d
            assert set(d["losses"]) == {"device", "handover", "analysis", "recording"}
        assert sorted(health["devices"][1]["channels"]) == sorted(
            [f"/razor/itg3200/imu:gyro_{a}" for a in "xyz"]
            + [f"/razor/adxl345/imu:accel_{a}" for a in "xyz"])
        allan = httpx.get(base + "/allan", params={"channel": "/razor/itg3200/imu:gyro_x"},
                          timeout=10)
        assert allan.status_code == 200 and allan.json()["tau_s"]
    finally:
        err = interrupt(proc)
    assert proc.returncode == 0, err
    files = list(out.glob("*.mcap"))
    assert len(files) == 1 and files[0].name.startswith("adis16350_razor_"), files
    _check_file(str(files[0]), seconds)
