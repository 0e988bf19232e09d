"""``imunoise analyze`` end to end: the real CLI in a subprocess on generated CSV files."""

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from imunoise.cli import main

FS = 100.0
SIGMA_G = 1e-3  # rad/s per sample -> N = sigma / sqrt(fs) = 1e-4 rad/s/sqrt(Hz)
SIGMA_A = 0.02  # m/s^2


def _run(*args):
    return subprocess.run([sys.executable, "-m", "imunoise", "analyze", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def imu_csv(tmp_path_factory):
    rng = np.random.default_rng(11)
    n = 60_000
    t = 50.0 + np.arange(n) / FS
    t[30_000:] += 2.0  # one gap
    cols = [t, *rng.normal(0, SIGMA_G, (3, n)), *rng.normal(0, SIGMA_A, (3, n)),
            25 + 0.01 * rng.normal(size=n), np.zeros(n)]
    cols[6] = cols[6] + 9.80665
    path = tmp_path_factory.mktemp("cli") / "imu.csv"
    np.savetxt(path, np.column_stack(cols), delimiter=",", fmt="%.10g", comments="",
               header="t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,temp,flags")
    return path


def _all_finite(obj):
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, dict):
        return all(_all_finite(v) for v in obj.values())
    if isinstance(obj, list):
        return all(_all_finite(v) for v in obj)
    return True


def test_json_document(imu_csv):
    proc = _run(imu_csv, "--json")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    doc = json.loads(proc.stdout)
    assert doc["file"] == str(imu_csv)
    assert list(doc["channels"]) == ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y",
                                     "accel_z"]
    assert any("gap" in w for w in doc["warnings"])
    assert _all_finite(doc)
    for key, ch in doc["channels"].items():
        for k in ("channel", "units", "fs_hz", "n_samples", "duration_s", "model", "error",
                  "failures", "allan", "psd"):
            assert k in ch, (key, k)
        assert ch["channel"] == key and ch["fs_hz"] == FS and ch["n_samples"] == 60_000
        assert ch["duration_s"] == pytest.approx(600.0) and ch["n_segments"] == 2
        assert [m["term"] for m in ch["model"]] == ["white", "bias_instability",
                                                    "random_walk"]
        assert ch["error"]["chi2_per_dof"] > 0 and isinstance(ch["failures"], list)
        assert ch["units"] == ("rad/s" if key.startswith("gyro") else "m/s^2")
        allan = ch["allan"]
        for k in ("tau_s", "adev", "ci_low", "ci_high", "model_adev", "z"):
            assert k in allan
        psd = ch["psd"]
        n = len(psd["f_hz"])
        assert n > 50 and all(len(psd[k]) == n for k in ("psd", "ci_low", "ci_high"))
        assert psd["ci"] == 0.95
        p = np.array(psd["psd"])
        assert np.all(np.array(psd["ci_low"]) < p) and np.all(p < np.array(psd["ci_high"]))
        sigma = SIGMA_G if key.startswith("gyro") else SIGMA_A
        # white level 2 sigma^2/fs: the top band holds thousands of dof, 3 % is > 5 sd
        top = np.array(psd["f_hz"]) > FS / 16
        assert np.median(p[top]) == pytest.approx(2 * sigma**2 / FS, rel=0.03)
        adev = np.array(allan["adev"])
        tau = np.array(allan["tau_s"])
        assert len(adev) >= 8 and allan["ci"] == 0.95
        assert len(tau) == len(adev) == len(allan["ci_low"]) == len(allan["ci_high"])
        np.testing.assert_allclose(tau[:3], [0.01, 0.02, 0.04])  # octave taus
        assert np.all(np.array(allan["ci_low"]) <= adev)
        assert np.all(adev <= np.array(allan["ci_high"]))
        # white noise: ADEV(tau) = sigma / sqrt(m); 60 000 samples, edf ~ 30 000 at tau0
        np.testing.assert_allclose(adev[:4] * np.sqrt([1, 2, 4, 8]), sigma, rtol=0.03)


def test_text_output_and_channel_selection(imu_csv):
    proc = _run(imu_csv, "--channel", "accel_z", "--channel", "gyro_y")
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert out.index("accel_z  [m/s^2]") < out.index("gyro_y  [rad/s]")
    assert "gyro_x" not in out
    assert "ug/sqrt(Hz)" in out and "deg/h/sqrt(Hz)" in out
    # N read-out from the PSD: 1e-4 rad/s/sqrt(Hz) = 0.344 deg/sqrt(h)
    line = next(s for s in out.splitlines() if "N from PSD" in s and "deg/sqrt(h)" in s)
    n_si = float(line.split(":")[1].split()[0])
    assert n_si == pytest.approx(SIGMA_G / math.sqrt(FS), rel=0.03)
    assert "warning: 200 sample(s) missing in 1 gap(s) (largest 2.01 s" in proc.stderr


def test_temperature_channel_and_rate_option(tmp_path):
    path = tmp_path / "norate.csv"
    rng = np.random.default_rng(2)
    np.savetxt(path, np.column_stack([rng.normal(0, 1e-3, 5000), 20 + rng.normal(0, 0.1, 5000)]),
               delimiter=",", header="gyro_z,temp", comments="", fmt="%.8g")
    assert main(["analyze", str(path), "--rate", "50", "--json", "--channel", "temp"]) == 0


def test_bad_inputs_exit_2_with_one_line(tmp_path):
    missing = _run(tmp_path / "nope.csv", "--json")
    assert missing.returncode == 2 and missing.stdout == ""
    assert missing.stderr.count("\n") == 1 and "no such file" in missing.stderr
    noise = tmp_path / "noise.csv"
    noise.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    proc = _run(noise, "--json")
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "not a CSV" in proc.stderr
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("content, args, message", [
    ("", [], "empty file"),
    ("a,b\n1,2\n", [], "no IMU channel columns"),
    ("gyro_x\n1\n2\n", [], "--rate"),
    ("gyro_x\n1\n2\n", ["--rate", "-3"], "bad rate"),
    ("gyro_x\n1\n2\n", ["--rate", "abc"], "bad rate"),
    ("t,gyro_x\n0,1\n0.01,2\n", ["--channel", "accel_q"], "unknown channel 'accel_q'; valid "
                                                         "channels: gyro_x"),
    ("t,gyro_x\n0,1\n0.01,x\n", [], "line 3, column 2"),
])
def test_bad_input_cases(tmp_path, capsys, content, args, message):
    path = tmp_path / "bad.csv"
    path.write_text(content)
    assert main(["analyze", str(path), "--json", *args]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    err = captured.err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_unsupported_and_folder(tmp_path, capsys):
    (tmp_path / "x.bin").write_bytes(b"\x00")
    assert main(["analyze", str(tmp_path / "x.bin")]) == 2
    assert "unsupported file type" in capsys.readouterr().err
    assert main(["analyze", str(tmp_path)]) == 2
    assert "not a rosbag2" in capsys.readouterr().err


def test_too_short_record_still_reports(tmp_path, capsys):
    path = tmp_path / "short.csv"
    path.write_text("t,gyro_x\n" + "".join(f"{i / 10},{(-1) ** i}\n" for i in range(20)))
    assert main(["analyze", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    ch = doc["channels"]["gyro_x"]
    assert ch["psd"]["f_hz"] == [] and any("no PSD" in w for w in ch["warnings"])


def test_progress_bar_goes_to_stderr_only(capsys):
    from imunoise.core.record import Record
    from imunoise.core.series import ChannelSeries
    from imunoise.pipeline.channel_analysis import analyze_record

    rec = Record(source="mem", channels={"gyro_x": ChannelSeries(
        "gyro_x", "rad/s", FS, np.random.default_rng(0).normal(size=20_000))})
    results = analyze_record(rec, ["gyro_x"], show_progress=True)
    assert results[0].psd is not None
    assert capsys.readouterr().out == ""


def test_progress_displays_do_not_touch_json(imu_csv, capsys, monkeypatch):
    from imunoise.commands import analyze
    from imunoise.pipeline import channel_analysis

    monkeypatch.setattr(analyze, "_PROGRESS_FILE_BYTES", 0)
    monkeypatch.setattr(channel_analysis, "_PROGRESS_SAMPLES", 0)
    assert main(["analyze", str(imu_csv), "--json", "--channel", "gyro_x"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert list(doc["channels"]) == ["gyro_x"]
