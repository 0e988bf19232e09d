"""The filter a recording's device configuration states, as the diagnose command reads it."""

from __future__ import annotations

import re

import pytest

from imunoise.pipeline.fitting import device_filter


def test_adis_bartlett_at_the_output_rate() -> None:
    md = {"config.device": "adis16350", "config.rate_hz": "819.2", "config.filter_taps": "4"}
    assert device_filter(md, "gyro_x") == ("bartlett", {"taps": pytest.approx(4.0)})
    md["config.rate_hz"] = "409.6"
    assert device_filter(md, "/adis16350/imu:accel_z") == ("bartlett",
                                                           {"taps": pytest.approx(2.0)})
    md["config.rate_hz"] = "102.4"  # the window is shorter than one output sample
    assert device_filter(md, "gyro_x") is None


def test_itg3200_low_pass_below_nyquist_only() -> None:
    md = {"config.device": "itg3200", "config.rate_hz": "100", "config.dlpf_bandwidth_hz": "42"}
    assert device_filter(md, "gyro_y") == ("lowpass", {"fc": 42.0})
    md["config.dlpf_bandwidth_hz"] = "98"
    assert device_filter(md, "gyro_y") is None
    assert device_filter({}, "gyro_x") is None


def test_apply_args_keep_the_cuts_already_made() -> None:
    from imunoise.pipeline.fitting import full_window_args

    assert full_window_args([], 0.0, []) == []
    assert full_window_args([], 300.0, [5000.0]) == ["--skip", "300", "--split", "5000"]
    # a step found 1000 s into a channel already cut at 300 s lies at 1300 s of the original
    assert full_window_args(["--split", "1000"], 300.0, [5000.0]) == \
        ["--skip", "300", "--split", "1300,5000"]
    assert full_window_args(["--skip", "120"], 300.0, []) == ["--skip", "420"]


def test_skip_and_split_on_the_command_line(tmp_path, capsys) -> None:
    import json

    import numpy as np

    from imunoise.cli import main

    rng = np.random.default_rng(4)
    n, fs = 60_000, 50.0
    x = rng.normal(0, 1e-2, n) + np.cumsum(rng.normal(0, 1e-5, n))
    x[30_000:] += 0.05
    path = tmp_path / "step.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / fs, x]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    assert main(["fit", str(path), "--channel", "gyro_x", "--model", "white,random_walk",
                 "--skip", "1e9"]) == 2
    assert "leaves no samples" in capsys.readouterr().err
    assert main(["fit", str(path), "--channel", "gyro_x", "--model", "white,random_walk",
                 "--split", "600", "--skip", "10", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["n_segments"] == 2 and doc["n_samples"] == n - 500
    assert not [w for w in doc["warnings"] if "--split" in w]
    # a split time before the skip's end or beyond the record cuts nothing, and says so
    assert main(["fit", str(path), "--channel", "gyro_x", "--model", "white,random_walk",
                 "--split", "5,600,1300", "--skip", "10", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["n_segments"] == 2
    assert [w for w in doc["warnings"] if "--split" in w] == [
        f"gyro_x: --split {t} s is outside the samples analysed (10 to 1200 s): it cuts nothing"
        for t in (5, 1300)]


def test_a_cut_suggestion_applies_as_stated(tmp_path, capsys) -> None:
    # CONTRACT: fit with apply.model and apply.args reports the suggestion's chi2_per_dof_after
    import json

    import numpy as np

    from imunoise.cli import main

    rng = np.random.default_rng(4)
    n, fs = 180_000, 50.0
    x = rng.normal(0, 1e-2, n) + np.cumsum(rng.normal(0, 2e-5, n))
    x[90_000:] += 0.05
    path = tmp_path / "knock.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / fs, x]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    common = [str(path), "--channel", "gyro_x", "--json"]
    assert main(["diagnose", *common, "--model", "white,random_walk", "--skip", "10"]) == 0
    doc = json.loads(capsys.readouterr().out)
    cuts = [s for s in doc["suggestions"] if s["term"] == "bias_step"]
    assert cuts and cuts[0]["apply"]["args"][:2] == ["--skip", "10"]
    assert cuts[0]["apply"]["args"][2] == "--split"
    assert abs(float(cuts[0]["apply"]["args"][3]) - 1800.0) <= 30.0  # within a block
    # the step's time, its interval and the cut all count from the start of the file
    step = cuts[0]
    assert set(step["ci95"]) == {"t_s", "size"}
    assert step["params"]["t_s"] == pytest.approx(float(step["apply"]["args"][3]), abs=1e-3)
    assert step["ci95"]["t_s"][0] <= 1800.0 <= step["ci95"]["t_s"][1]
    assert step["ci95"]["size"][0] <= 0.05 <= step["ci95"]["size"][1]
    # the text report lists a cut as a cut, with its parameters' units
    assert main(["diagnose", str(path), "--channel", "gyro_x", "--model", "white,random_walk",
                 "--skip", "10"]) == 0
    text = capsys.readouterr().out
    assert re.search(r"^ +[ *] ?\d+\. cut bias_step +chi2/dof", text, re.M), text
    assert re.search(r"t_s = 1[78]\d\d s, size = 0\.0\d+ rad/s", text), text
    for s in cuts:
        assert main(["fit", *common, "--model", s["apply"]["model"], *s["apply"]["args"]]) == 0
        fitted = json.loads(capsys.readouterr().out)
        assert fitted["error"]["chi2_per_dof"] == pytest.approx(s["chi2_per_dof_after"],
                                                                rel=1e-9)

