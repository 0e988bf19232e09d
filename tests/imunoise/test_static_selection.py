"""--static auto|all: the commands analyse the still stretches of a record that moved, say so,
and refuse to export noise numbers of a sensor that never rested."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

FS = 100.0


def _imu_csv(path, seconds: float, moving: tuple[float, float] | None, always: bool = False):
    rng = np.random.default_rng(3)
    n = int(seconds * FS)
    t = np.arange(n) / FS
    g = rng.normal(0, 3e-4 * np.sqrt(FS), (n, 3))
    a = rng.normal(0, 2e-3 * np.sqrt(FS), (n, 3)) + [0.0, 0.0, 9.80665]
    if moving is not None:
        sel = (t >= moving[0]) & (t < moving[1])
        g[sel] += rng.normal(0, 0.2, (sel.sum(), 3)) + [0.0, 0.0, 0.5]
        a[sel] += rng.normal(0, 1.0, (sel.sum(), 3))
    if always:
        g += rng.normal(0, 0.3, g.shape)
        a += rng.normal(0, 2.0, a.shape)
    np.savetxt(path, np.column_stack([t, g, a]), delimiter=",", comments="", fmt="%.10g",
               header="t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z")
    return path


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "imunoise", *args], capture_output=True,
                          text=True, timeout=300)


def test_a_record_that_moves_then_rests_is_analysed_on_its_still_part(tmp_path):
    path = _imu_csv(tmp_path / "robot.csv", 400, moving=(30, 90))
    out = _run("analyze", str(path), "--channel", "gyro_z", "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    motion = doc["motion"]["imu"]
    assert motion["moved"] and motion["static"] == "auto"
    assert motion["used"].startswith("2 still stretch(es)")
    moving = [s for s in motion["stretches"] if s["moving"]]
    assert len(moving) == 1 and moving[0]["start_s"] == pytest.approx(29, abs=1.5)
    assert moving[0]["shock"] is False
    assert moving[0]["stop_s"] == pytest.approx(91, abs=1.5)
    ch = doc["channels"]["gyro_z"]
    assert ch["n_samples"] == pytest.approx(motion["still_s"] * FS)
    assert ch["n_segments"] == 2
    assert any("analysing the 2 still stretch(es)" in w for w in doc["warnings"])
    # N of the still part is the sensor's white noise, not the motion's
    white = next(m for m in ch["model"] if m["term"] == "white")
    assert white["params"]["N"] == pytest.approx(3e-4, rel=0.1)
    every = json.loads(_run("analyze", str(path), "--channel", "gyro_z", "--json",
                            "--static", "all").stdout)
    assert every["channels"]["gyro_z"]["n_samples"] == 40_000
    assert every["motion"]["imu"]["used"] == "all"
    assert any("numbers from moving stretches are not noise" in w for w in every["warnings"])
    fit = json.loads(_run("fit", str(path), "--channel", "gyro_z", "--model", "white",
                          "--json").stdout)
    assert fit["motion"]["imu"]["moved"] and fit["n_samples"] == ch["n_samples"]


def test_export_refuses_a_sensor_that_never_rested(tmp_path):
    path = _imu_csv(tmp_path / "drive.csv", 120, moving=None, always=True)
    out = tmp_path / "imu.yaml"
    r = _run("export-kalibr", str(path), "-o", str(out))
    assert r.returncode == 2 and not out.exists()
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and "never rested" in err[0] and "--static all" in err[0]
    r = _run("export-kalibr", str(path), "-o", str(out), "--static", "all")
    assert r.returncode == 0, r.stderr
    text = out.read_text()
    assert "# recording: imu: the sensor moved" in text and "used: all" in text
    assert "# recording: csv: 100 Hz, 0 sample(s) missing" in text


def test_a_shock_is_cut_and_marked_in_json(tmp_path):
    # half a g ringing for 0.3 s on two accelerometer axes, 150.4 s into a still record
    path = _imu_csv(tmp_path / "bench.csv", 300, moving=None)
    data = np.loadtxt(path, delimiter=",", skiprows=1)
    t = np.arange(30) / FS
    ring = np.exp(-t / 0.08) * np.sin(2 * np.pi * 25 * t)
    data[15_040:15_070, 4] += 2.0 * ring
    data[15_040:15_070, 6] += 5.0 * ring
    np.savetxt(path, data, delimiter=",", comments="", fmt="%.10g",
               header="t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z")
    out = _run("analyze", str(path), "--channel", "accel_z", "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    moving = [s for s in doc["motion"]["imu"]["stretches"] if s["moving"]]
    assert [(s["start_s"], s["stop_s"], s["shock"]) for s in moving] == [(149.0, 152.0, True)]
    assert doc["channels"]["accel_z"]["n_samples"] == 29_700
    assert any("149.0-152.0 s (a shock)" in w for w in doc["warnings"])
