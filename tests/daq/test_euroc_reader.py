"""EuRoC/ASL and TUM-VI ``imu0/data.csv``: recognised by the header, ns stamps, sensor.yaml."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import yaml

from imunoise.daq.readers import open_record

EUROC_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
# TUM-VI exports seen without the units
BARE_HEADER = "#timestamp,w_RS_S_x,w_RS_S_y,w_RS_S_z,a_RS_S_x,a_RS_S_y,a_RS_S_z"
SENSOR_YAML = """sensor_type: imu
comment: VI-Sensor IMU (ADIS16448)
T_BS:
  cols: 4
  rows: 4
  data: [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]
rate_hz: 200
gyroscope_noise_density: 1.6968e-04
gyroscope_random_walk: 1.9393e-05
accelerometer_noise_density: 2.0000e-3
accelerometer_random_walk: 3.0000e-3
"""
T0_NS = 1403636579758555392  # a EuRoC MH_01 stamp: 1.4e18 ns


def _write(folder, header: str, n: int = 6000, period_ns: int = 5_000_000, seed: int = 3,
           with_yaml: bool = True):
    rng = np.random.default_rng(seed)
    fs = 1e9 / period_ns  # white densities N: per-sample sigma N sqrt(fs)
    gyro = rng.normal(0.0, 1.7e-4 * np.sqrt(fs), (n, 3))
    accel = rng.normal(0.0, 2e-3 * np.sqrt(fs), (n, 3)) + [0.0, 0.0, 9.81]
    stamps = T0_NS + np.arange(n, dtype=np.int64) * period_ns
    folder.mkdir(parents=True, exist_ok=True)
    lines = [header] + [f"{s}," + ",".join(repr(float(v)) for v in (*g, *a))
                        for s, g, a in zip(stamps, gyro, accel, strict=True)]
    path = folder / "data.csv"
    path.write_text("\n".join(lines) + "\n")
    if with_yaml:
        (folder / "sensor.yaml").write_text(SENSOR_YAML)
    return path, gyro, accel


@pytest.mark.parametrize("header", [EUROC_HEADER, BARE_HEADER], ids=["euroc", "tum-vi-bare"])
def test_asl_layout_is_read_by_its_header(tmp_path, header):
    path, gyro, accel = _write(tmp_path / "mav0" / "imu0", header)
    rec = open_record(path)
    assert list(rec.channels) == ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    g = rec.channels["gyro_y"]
    assert g.fs_hz == 200.0 and g.units == "rad/s"  # integer ns stamps: the rate is exact
    assert len(g.segment_starts) == 1 and g.n_samples == 6000
    np.testing.assert_array_equal(g.values, gyro[:, 1])
    np.testing.assert_array_equal(rec.channels["accel_z"].values, accel[:, 2])
    assert rec.channels["accel_z"].units == "m/s^2"
    assert g.t0_s == pytest.approx(T0_NS * 1e-9, abs=1e-6)
    assert rec.metadata["format"] == "euroc-asl csv"
    assert float(rec.metadata["dataset_gyroscope_noise_density"]) == 1.6968e-04
    assert float(rec.metadata["dataset_accelerometer_random_walk"]) == 3.0e-3
    assert float(rec.metadata["dataset_rate_hz"]) == 200.0


def test_a_missing_sample_in_ns_stamps_is_one_gap(tmp_path):
    path, _, _ = _write(tmp_path, EUROC_HEADER, with_yaml=False)
    lines = path.read_text().splitlines()
    del lines[3001]  # one row gone: 10 ms between two stamps
    path.write_text("\n".join(lines) + "\n")
    rec = open_record(path)
    g = rec.channels["gyro_x"]
    np.testing.assert_array_equal(g.segment_starts, [0, 3000])
    assert any("1 sample(s) missing in 1 gap(s) (largest 0.01 s, before sample 3001)" in w
               for w in rec.warnings)
    assert "dataset_sensor_yaml" not in rec.metadata


def test_command_line_shows_the_stated_values_beside_the_measured_ones(tmp_path):
    path, _, _ = _write(tmp_path / "imu0", EUROC_HEADER)
    run = subprocess.run([sys.executable, "-m", "imunoise", "analyze", str(path), "--channel",
                          "gyro_x"], capture_output=True, text=True, check=True, timeout=300)
    assert "fs 200 Hz" in run.stdout
    # N of 6000 samples: fit spread about 1.5 % (1 sd); 5 % is over three of them
    assert ("(not measured): gyroscope_noise_density 0.0001697 rad/s/sqrt(Hz), "
            "gyroscope_random_walk 1.939e-05 rad/s^2/sqrt(Hz)") in run.stdout
    # one minute cannot resolve a random walk: said, not printed as a tiny number
    assert "random_walk       K     = not resolved (95 % upper bound" in run.stdout
    out = tmp_path / "imu.yaml"
    subprocess.run([sys.executable, "-m", "imunoise", "export-kalibr", str(path), "-o", str(out)],
                   capture_output=True, text=True, check=True, timeout=300)
    text = out.read_text()
    data = yaml.safe_load(text)
    assert data["update_rate"] == pytest.approx(200.0)
    assert data["gyroscope_noise_density"] == pytest.approx(1.7e-4, rel=0.05)
    assert "#   gyroscope_noise_density: 1.696800e-04" in text
    assert text.count("upper bound: the random walk is not resolved") == 2
