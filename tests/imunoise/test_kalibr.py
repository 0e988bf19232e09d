"""Kalibr imu.yaml: values from fitted N and K, exact key names, read back by a YAML parser."""

import json
import math
import subprocess
import sys

import pytest
import yaml

from imunoise.cli import main
from imunoise.export.kalibr import KalibrError, kalibr_values, render_yaml

KALIBR_KEYS = {"accelerometer_noise_density", "accelerometer_random_walk",
               "gyroscope_noise_density", "gyroscope_random_walk", "rostopic", "update_rate"}

# Known per-axis fits (SI): gyro N in rad/s/sqrt(Hz), K in rad/s/sqrt(s); accel in m/s^2.
GYRO = {"x": (2.0e-4, 1.0e-6), "y": (2.5e-4, 3.0e-6), "z": (1.5e-4, 2.0e-6)}
ACCEL = {"x": (1.0e-3, 4.0e-5), "y": (2.0e-3, 1.0e-5), "z": (3.0e-3, 2.0e-5)}


def _channel(n: float, k: float, fs: float = 200.0, k_ci=None) -> dict:
    return {
        "units": "rad/s", "fs_hz": fs, "n_samples": 720000, "duration_s": 3600.0,
        "model": [
            {"term": "white", "params": {"N": n}, "ci95": {"N": [0.98 * n, 1.02 * n]}},
            {"term": "bias_instability", "params": {"B": 1e-5}, "ci95": {"B": [8e-6, 1.2e-5]}},
            {"term": "random_walk", "params": {"K": k},
             "ci95": {"K": k_ci if k_ci is not None else [0.7 * k, 1.3 * k]}},
        ],
        "error": {"chi2_per_dof": 1.0, "max_abs_z": 1.5}, "failures": [],
    }


def _doc(prefix: str = "") -> dict:
    ch = {}
    for a, (n, k) in GYRO.items():
        ch[f"{prefix}gyro_{a}"] = _channel(n, k)
    for a, (n, k) in ACCEL.items():
        ch[f"{prefix}accel_{a}"] = _channel(n, k)
    return {"file": "night.mcap", "channels": ch}


def test_values_max_rms_mean_and_inflation():
    ch = _doc()["channels"]
    imu = kalibr_values(ch)
    assert imu.gyroscope_noise_density == 2.5e-4
    assert imu.gyroscope_random_walk == 3.0e-6
    assert imu.accelerometer_noise_density == 3.0e-3
    assert imu.accelerometer_random_walk == 4.0e-5
    assert imu.update_rate == 200.0 and imu.rostopic == "/imu0"
    rms = kalibr_values(ch, combine="rms")
    assert rms.gyroscope_noise_density == pytest.approx(
        math.sqrt((2e-4**2 + 2.5e-4**2 + 1.5e-4**2) / 3), rel=1e-12)
    mean = kalibr_values(ch, combine="mean", inflate=10.0)
    assert mean.accelerometer_random_walk == pytest.approx(10 * (4e-5 + 1e-5 + 2e-5) / 3)
    assert mean.inflate == 10.0


def test_yaml_reads_back_with_exact_keys_and_comments():
    imu = kalibr_values(_doc()["channels"], inflate=2.0, rostopic="/imu/data")
    text = render_yaml(imu, source="night.mcap")
    data = yaml.safe_load(text)
    assert set(data) == KALIBR_KEYS
    assert data["gyroscope_noise_density"] == pytest.approx(5.0e-4, rel=1e-6)
    assert data["gyroscope_random_walk"] == pytest.approx(6.0e-6, rel=1e-6)
    assert data["accelerometer_noise_density"] == pytest.approx(6.0e-3, rel=1e-6)
    assert data["accelerometer_random_walk"] == pytest.approx(8.0e-5, rel=1e-6)
    assert data["rostopic"] == "/imu/data" and data["update_rate"] == 200.0
    assert all(isinstance(data[k], float) for k in KALIBR_KEYS - {"rostopic"})
    assert "inflation factor 2" in text
    # per-axis values and intervals as comments, before inflation
    assert ("#   gyro_y: N = 2.500000e-04 rad/s/sqrt(Hz) (95 % [2.450000e-04, 2.550000e-04]; "
            "from the Allan fit, white term)") in text
    # every Kalibr value carries its interval (axes' interval ends combined, inflated) and source
    assert ("gyroscope_noise_density: 5.000000e-04  # rad/s/sqrt(Hz)\n"
            "#   95 % [4.900000e-04, 5.100000e-04]; from the Allan fit, white term") in text
    assert "#   95 % [4.200000e-06, 7.800000e-06]; from the Allan fit, random_walk term" in text
    assert "#   accel_x: K = 4.000000e-05 m/s^3/sqrt(Hz)" in text


def test_unresolved_random_walk_uses_the_allan_band_bound():
    ch = _doc()["channels"]
    # K on its lower bound with a collapsed interval, as a fit reports an unresolved term
    ch["gyro_z"] = _channel(1.5e-4, 5.8e-19, k_ci=[5.8e-19, 5.8e-19])
    ch["gyro_z"]["allan"] = {"tau_s": [1.0, 10.0, 100.0, 1000.0],
                             "ci_high": [2e-4, 7e-5, 3e-5, 2e-5]}
    imu = kalibr_values(ch)
    # bound = min sqrt(3 hi^2 / tau) = sqrt(3) * min(2e-4, 2.21e-5, 3e-6, 6.32e-7)
    bound = math.sqrt(3.0) * 2e-5 / math.sqrt(1000.0)
    assert imu.axes["gyro"][2].K == pytest.approx(bound, rel=1e-12)
    assert imu.gyroscope_random_walk == 3.0e-6  # gyro_y's resolved K is still the largest
    text = render_yaml(imu)
    assert "gyro_z: K = 1.095445e-06" in text
    assert "(random walk not resolved: largest K inside the measured Allan band)" in text
    ch["gyro_z"]["allan"] = {}
    with pytest.raises(KalibrError, match="gyro_z: random walk K is not resolved"):
        kalibr_values(ch)


def test_missing_parts_are_clear_errors():
    ch = _doc()["channels"]
    gyro_only = {k: v for k, v in ch.items() if k.startswith("gyro")}
    with pytest.raises(KalibrError, match="no accel channels"):
        kalibr_values(gyro_only)
    no_rw = dict(ch)
    no_rw["accel_y"] = {"model": [{"term": "white", "params": {"N": 1e-3}}], "fs_hz": 200.0}
    with pytest.raises(KalibrError, match="accel_y: the fitted model has no random_walk term"):
        kalibr_values(no_rw)
    two = {**_doc("/a:")["channels"], **_doc("/b:")["channels"]}
    with pytest.raises(KalibrError, match="several IMU topics"):
        kalibr_values(two)
    assert kalibr_values(two, topic="/b").rostopic == "/b"
    with pytest.raises(KalibrError, match="inflation factor"):
        kalibr_values(ch, inflate=0.0)


def test_cli_from_analyze_json(tmp_path, capsys):
    src = tmp_path / "analysis.json"
    src.write_text(json.dumps(_doc()))
    out = tmp_path / "imu.yaml"
    assert main(["export-kalibr", str(src), "-o", str(out), "--inflate", "3"]) == 0
    data = yaml.safe_load(out.read_text())
    assert set(data) == KALIBR_KEYS
    assert data["gyroscope_noise_density"] == pytest.approx(7.5e-4, rel=1e-6)
    assert main(["export-kalibr", str(src), "-o", "-", "--combine", "mean"]) == 0
    data = yaml.safe_load(capsys.readouterr().out)
    assert data["accelerometer_noise_density"] == pytest.approx(2.0e-3, rel=1e-6)


@pytest.mark.parametrize("argv,needle", [
    (["--inflate", "-2"], "must be a positive number"),
    (["--inflate", "abc"], "not a number"),
    (["--combine", "median"], "invalid choice"),
])
def test_cli_bad_options_exit_2_one_line(tmp_path, capsys, argv, needle):
    src = tmp_path / "analysis.json"
    src.write_text(json.dumps(_doc()))
    assert main(["export-kalibr", str(src), "-o", str(tmp_path / "x.yaml"), *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]
    assert not (tmp_path / "x.yaml").exists()


def test_cli_bad_inputs_exit_2_nothing_written(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    gyro_only = tmp_path / "gyro.json"
    doc = _doc()
    doc["channels"] = {k: v for k, v in doc["channels"].items() if k.startswith("gyro")}
    gyro_only.write_text(json.dumps(doc))
    out = tmp_path / "imu.yaml"
    for path, needle in [(tmp_path / "missing.csv", "no such file"),
                         (bad, "not an analyze JSON document"),
                         (gyro_only, "no accel channels")]:
        r = subprocess.run([sys.executable, "-m", "imunoise", "export-kalibr", str(path),
                            "-o", str(out)], capture_output=True, text=True)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and needle in lines[0], r.stderr
        assert not out.exists()
    assert list(tmp_path.glob(".imu.yaml.*")) == []


def test_cli_output_folder_missing_or_unwritable(tmp_path, capsys):
    src = tmp_path / "analysis.json"
    src.write_text(json.dumps(_doc()))
    assert main(["export-kalibr", str(src), "-o", str(tmp_path / "nope" / "imu.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]
    # a folder in place of the output file: the rename fails, exit 1, temporary removed
    (tmp_path / "imu.yaml").mkdir()
    assert main(["export-kalibr", str(src), "-o", str(tmp_path / "imu.yaml")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot write" in err[0]
    assert list(tmp_path.glob(".imu.yaml.*")) == []


# --- end to end on recordings ----------------------------------------------------------------

@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    from tests.outputs_inputs import write_csv, write_mcap

    d = tmp_path_factory.mktemp("rec")
    return {"csv": write_csv(d / "still.csv"), "mcap": write_mcap(d / "mcap")}


@pytest.mark.parametrize("kind", ["csv", "mcap"])
def test_export_from_recording(recordings, kind, tmp_path):
    from tests.outputs_inputs import ACCEL_MODEL, GYRO_MODEL

    out = tmp_path / "imu.yaml"
    assert main(["export-kalibr", str(recordings[kind]), "-o", str(out)]) == 0
    text = out.read_text()
    data = yaml.safe_load(text)
    assert set(data) == KALIBR_KEYS
    assert data["update_rate"] == pytest.approx(100.0, rel=1e-8)
    assert data["rostopic"] == ("/adis16350/imu" if kind == "mcap" else "/imu0")
    # 40,000 samples pin N to well under 1 % per axis; the largest of three axes is within 2 %.
    assert data["gyroscope_noise_density"] == pytest.approx(GYRO_MODEL[0][1]["N"], rel=0.02)
    assert data["accelerometer_noise_density"] == pytest.approx(ACCEL_MODEL[0][1]["N"], rel=0.02)
    # K is poorly determined by 400 s of data; the largest axis value must still be of the
    # right order (the truth lies inside the widest per-axis interval or the Allan bound).
    for key, model in (("gyroscope_random_walk", GYRO_MODEL),
                       ("accelerometer_random_walk", ACCEL_MODEL)):
        k_true = model[2][1]["K"]
        assert k_true / 3 < data[key] < k_true * 4, (key, data[key])
    for ch in ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"):
        assert f"#   {ch}: N = " in text and f"#   {ch}: K = " in text
    # the same file from the analyze JSON of the recording gives the same values
    j = tmp_path / "a.json"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["analyze", str(recordings[kind]), "--json"]) == 0
    j.write_text(buf.getvalue())
    out2 = tmp_path / "imu2.yaml"
    assert main(["export-kalibr", str(j), "-o", str(out2)]) == 0
    again = yaml.safe_load(out2.read_text())
    for key in KALIBR_KEYS - {"rostopic"}:
        assert again[key] == pytest.approx(data[key], rel=1e-6)


def _psd_doc(level: float, n_points: int = 40, dof: float = 30.0) -> dict:
    """A flat one-sided PSD top band of ``level`` units^2/Hz, as analyze --json writes it."""
    return {"f_hz": list(range(1, n_points + 1)), "psd": [level] * n_points,
            "ci_low": [level / 2] * n_points, "ci_high": [level * 2] * n_points,
            "dof": [dof] * n_points, "method": ["welch"] * n_points, "ci": 0.95}


def _unresolved_white(ch: dict, key: str) -> None:
    """The fit of ``key`` puts N on its lower bound, interval reaching zero (a host-stamped log)."""
    ch[key]["model"][0] = {"term": "white", "params": {"N": 6.6e-30},
                           "ci95": {"N": [0.0, 3.0e-4]}}


def test_unresolved_white_noise_comes_from_the_psd_with_its_interval():
    from scipy import stats

    ch = _doc()["channels"]
    _unresolved_white(ch, "gyro_x")
    ch["gyro_x"]["psd"] = _psd_doc(2 * (1.7e-4) ** 2)  # white N = 1.7e-4 -> S = 2 N^2
    imu = kalibr_values(ch)
    ax = imu.axes["gyro"][0]
    assert ax.N == pytest.approx(1.7e-4, rel=1e-12)
    nu = 0.5 * 40 * 30.0  # half the summed dof (neighbouring Hann bins are correlated)
    lo = 1.7e-4 * math.sqrt(nu / stats.chi2.ppf(0.975, nu))
    hi = 1.7e-4 * math.sqrt(nu / stats.chi2.ppf(0.025, nu))
    assert ax.N_ci == pytest.approx((lo, hi), rel=1e-9)
    text = render_yaml(imu)
    assert "gyro_x: N = 1.700000e-04" in text
    assert "from the PSD white level of the top band (the Allan fit does not resolve N: its 95 % " \
           "interval reaches zero)" in text
    assert "6.6e-30" not in text and "6.600000e-30" not in text


def test_unresolved_white_noise_without_a_psd_is_refused_exit_2(tmp_path, capsys):
    doc = _doc()
    _unresolved_white(doc["channels"], "accel_y")
    with pytest.raises(KalibrError, match="accel_y: the white noise N is not resolved"):
        kalibr_values(doc["channels"])
    src = tmp_path / "fit.json"
    src.write_text(json.dumps(doc))
    out = tmp_path / "imu.yaml"
    assert main(["export-kalibr", str(src), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "its 95 % interval reaches zero" in err[0]
    assert not out.exists()


def test_a_fit_failing_at_the_shortest_taus_does_not_give_n():
    ch = _doc()["channels"]
    ch["gyro_z"]["allan"] = {"tau_s": [0.005, 0.01, 0.02, 0.04], "ci_high": [1e-3] * 4}
    ch["gyro_z"]["failures"] = [{"tau_s": [0.005, 0.02], "max_abs_z": 9.0,
                                 "direction": "measured below model"}]
    ch["gyro_z"]["psd"] = _psd_doc(2 * (1.2e-4) ** 2)
    ax = kalibr_values(ch).axes["gyro"][2]
    assert ax.N == pytest.approx(1.2e-4, rel=1e-12)
    assert "fails at the shortest averaging times" in ax.N_source
