"""``chain_filter`` end to end through the real CLI: offered by ``diagnose`` where the other
channels measure a shared response, fitted by ``fit``, refused where there is none."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

GALAXY = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "galaxy_s5" \
    / "galaxy_s5_static_10hz.npz"
NAMES = ["gyro_x", "gyro_y", "accel_x", "accel_y"]


def _run(*args):
    return subprocess.run([sys.executable, "-m", "imunoise", *map(str, args)],
                          capture_output=True, text=True, timeout=600)


def _csv(path: Path, x: np.ndarray, names: list[str], fs: float) -> Path:
    np.savetxt(path, np.column_stack([np.arange(len(x)) / fs, x]), delimiter=",",
               fmt="%.10g", comments="", header="t," + ",".join(names))
    return path


@pytest.fixture(scope="module")
def decimated(tmp_path_factory) -> Path:
    # independent noise in each channel through one steep lowpass, as a decimating logger
    # leaves it (tests/analysis/test_chain_filter.py has the same record, longer)
    rng = np.random.default_rng(71)
    n = 1 << 16
    w = rng.standard_normal((n, 4)) * np.array([1e-3, 2e-3, 5e-2, 3e-2])
    x = signal.sosfilt(signal.butter(6, 5.0, fs=100.0, output="sos"), w, axis=0) \
        + 0.03 * w[::-1]
    return _csv(tmp_path_factory.mktemp("chain") / "decimated.csv", x, NAMES, 100.0)


def test_diagnose_offers_the_shared_response_and_fit_applies_it(decimated):
    proc = _run("diagnose", decimated, "--channel", "accel_x", "--model", "white", "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    top = next(s for s in doc["suggestions"] if s["significant"])
    assert top["term"] == "chain_filter"
    assert top["apply"]["model"] == "white,chain_filter"
    assert "The filter's power response is taken from the other channels" in top["why"]
    # the same model through fit: the error's three parts near 1 where before the PSD part
    # was far above it
    before = doc["error"]["psd"]["deviance_per_bin"]
    proc = _run("fit", decimated, "--channel", "accel_x", "--model", "white,chain_filter",
                "--json")
    assert proc.returncode == 0, proc.stderr
    fit = json.loads(proc.stdout)
    assert fit["error"]["chi2_per_dof"] < 2.5
    assert fit["error"]["psd"]["deviance_per_bin"] < 2.0 < before
    depth = next(t for t in fit["model"] if t["term"] == "chain_filter")["params"]["depth"]
    assert depth == pytest.approx(1.0, abs=0.1)
    shape = fit["chain_shape"]
    assert shape["channels"] == ["gyro_x", "gyro_y", "accel_y"]
    assert shape["reference_band_hz"] == [0.2, 1.0] and shape["fs_hz"] == 100.0
    # the 6th-order lowpass at 5 Hz: flat below it, 1e-3 (the floor) far above it
    f, power = np.array(shape["f_hz"]), np.array(shape["power"])
    assert np.all(np.abs(np.log(power[f < 2.0])) < 0.2)
    assert np.all(power[f > 30.0] < 3e-3)
    assert doc["chain_shape"]["channels"] == shape["channels"]  # the diagnosis states it too
    proc = _run("fit", decimated, "--channel", "accel_x", "--model", "white,chain_filter")
    assert proc.returncode == 0, proc.stderr
    assert "chain_filter      depth" in proc.stdout
    assert ("chain_filter: the response measured from gyro_x, gyro_y, accel_y of this record "
            "(their PSDs' geometric mean, each divided by its median over 0.2-1 Hz; 1 below "
            "1 Hz)") in proc.stdout


def test_a_record_without_a_shared_shape_is_a_usage_error(tmp_path):
    rng = np.random.default_rng(72)
    x = rng.standard_normal((1 << 14, 2)) * np.array([1e-3, 2e-3])  # white: no shape
    path = _csv(tmp_path / "white.csv", x, ["gyro_x", "gyro_y"], 100.0)
    for verb in ("fit", "diagnose"):
        proc = _run(verb, path, "--channel", "gyro_x", "--model", "white,chain_filter")
        assert proc.returncode == 2
        assert proc.stderr.strip().splitlines() == [
            "imunoise: chain_filter: no other channel of this record has gyro_x's spectral shape "
            "without a signal in common, so there is no shared response to measure "
            "(imunoise analyze lists shared shapes)"]
    proc = _run("diagnose", path, "--channel", "gyro_x", "--model", "white", "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert all(s["term"] != "chain_filter" for s in doc["suggestions"])
    assert "chain_shape" not in doc


@pytest.mark.skipif(not GALAXY.exists(), reason="needs ../shared/data (the Galaxy S5 record)")
def test_galaxy_s5_channels_are_described_through_their_shared_response(tmp_path):
    d = np.load(GALAXY)
    six = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    path = _csv(tmp_path / "galaxy.csv", np.column_stack([d["gyro"], d["accel"]]), six,
                float(d["fs"]))
    base = "white,bias_instability,random_walk"
    proc = _run("diagnose", path, "--channel", "accel_z", "--model", base, "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    top = next(s for s in doc["suggestions"] if s["significant"])
    assert top["term"] == "chain_filter"
    # measured: the base model's PSD part 195 per bin on accel_x (before any term); with the
    # shared response Allan 1.53, PSD 1.21, the hold-out 1.45 once the changes it names are
    # fitted (../shared/tools/real_loop.py)
    assert doc["error"]["psd"]["deviance_per_bin"] > 50.0
    proc = _run("fit", path, "--channel", "accel_z", "--model", top["apply"]["model"],
                "--json")
    assert proc.returncode == 0, proc.stderr
    err = json.loads(proc.stdout)["error"]
    assert err["chi2_per_dof"] < 2.5
    assert err["psd"]["deviance_per_bin"] < 2.0
    assert err["holdout"]["changes_free"]["chi2_per_dof"] < 3.0


def test_plan_and_the_live_service_refuse_the_term_and_say_why(decimated):
    for args in (("--model", "white:N=1e-3,chain_filter:depth=1", "--rate", "10"),
                 (decimated, "--channel", "accel_x", "--model", "white,chain_filter")):
        proc = _run("plan", *args, "--target", "N=1%")
        assert proc.returncode == 2
        assert proc.stderr.strip() == (
            "imunoise: plan: chain_filter is measured from a record's other channels "
            "(imunoise fit FILE --model ...,chain_filter); plan from the model without it")
    from imunoise.analysis.channel_state import check_terms

    with pytest.raises(ValueError, match="the chain_filter term needs the record's other "
                                         "channels and is fitted by 'imunoise fit FILE"):
        check_terms(["white", "chain_filter"])


def test_the_python_api_neither_offers_nor_fits_it(decimated):
    import imunoise
    from imunoise.errors import UsageError

    rec = imunoise.read(str(decimated))
    with pytest.raises(UsageError, match="chain_filter needs the record's other channels: "
                                         ".* none is available here"):
        imunoise.fit(rec["accel_x"], "white,chain_filter")
    d = imunoise.diagnose(rec["accel_x"], "white")
    assert d.suggestions and all(s["term"] != "chain_filter" for s in d.suggestions)


def test_a_gap_in_another_channel_still_measures_the_response(decimated, tmp_path):
    # gyro_y loses ten samples: it is no longer on accel_x's time base and is brought onto
    # it for the coherence; an unusable channel is left out of the response
    x = np.loadtxt(decimated, delimiter=",", skiprows=1)[:, 1:]
    x[1000:1010, 1] = np.nan
    gap = _csv(tmp_path / "gap.csv", x, NAMES, 100.0)
    x[:, 1] = np.nan
    dead = _csv(tmp_path / "dead.csv", x, NAMES, 100.0)
    for path, used in ((gap, {"gyro_x", "gyro_y", "accel_y"}), (dead, {"gyro_x", "accel_y"})):
        proc = _run("fit", path, "--channel", "accel_x", "--model", "white,chain_filter",
                    "--json")
        assert proc.returncode == 0, proc.stderr
        doc = json.loads(proc.stdout)
        assert set(doc["chain_shape"]["channels"]) == used
        assert doc["error"]["psd"]["deviance_per_bin"] < 2.0
