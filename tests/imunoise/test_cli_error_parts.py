"""The parts of the error (PSD, hold-out, time domain) and the psd block in fit and diagnose
JSON, through the real command line; a fully given model is evaluated as it stands."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from imunoise.analysis.noise_stream import simulate

FS = 100.0
MODEL = [("white", {"N": 1e-3}), ("gauss_markov", {"sigma": 1e-3, "T": 0.5}),
         ("random_walk", {"K": 1e-5})]
GIVEN = "white:N=1e-3,gauss_markov:sigma=1e-3:T=0.5,random_walk:K=1e-5"


@pytest.fixture(scope="module")
def csv(tmp_path_factory):
    x = simulate(MODEL, 1 << 17, FS, rng=31)
    path = tmp_path_factory.mktemp("parts") / "imu.csv"
    np.savetxt(path, np.column_stack([np.arange(x.size) / FS, x]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    return path


def _run(*args):
    p = subprocess.run([sys.executable, "-m", "imunoise", *args], capture_output=True,
                       text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    return p.stdout


def test_fit_json_carries_every_part_and_the_psd_block(csv):
    doc = json.loads(_run("fit", str(csv), "--channel", "gyro_x", "--model",
                          "white,gauss_markov,random_walk", "--json"))
    err = doc["error"]
    assert 0.6 < err["psd"]["deviance_per_bin"] < 1.5 and err["psd"]["bins"] > 100
    assert 0.0 <= err["psd"]["outside_95"] < 0.15
    assert err["holdout"]["parts"] == 2 and 0.2 < err["holdout"]["chi2_per_dof"] < 3.0
    assert err["holdout"]["changed"] == []
    assert err["time_domain"]["p"] > 0.001 and err["time_domain"]["test"]
    psd = doc["psd"]
    assert set(psd) >= {"f_hz", "psd", "dof", "ci_low", "ci_high", "model_psd", "z"}
    assert len(psd["model_psd"]) == len(psd["f_hz"]) == err["psd"]["bins"]


def test_a_fully_given_model_is_evaluated_as_it_stands(csv):
    doc = json.loads(_run("fit", str(csv), "--channel", "gyro_x", "--model", GIVEN, "--json"))
    assert [m["params"] for m in doc["model"]] == [p for _, p in MODEL]
    assert 0.2 < doc["error"]["chi2_per_dof"] < 3.0
    assert 0.6 < doc["error"]["psd"]["deviance_per_bin"] < 1.5
    text = _run("fit", str(csv), "--channel", "gyro_x", "--model", GIVEN)
    assert "psd deviance/bin" in text and "hold-out" in text


def test_diagnose_json_carries_the_parts_and_each_suggestions_error_after(csv):
    doc = json.loads(_run("diagnose", str(csv), "--channel", "gyro_x", "--model",
                          "white,random_walk", "--json"))
    assert set(doc["error"]) >= {"chi2_per_dof", "psd", "holdout", "time_domain"}
    assert "model_psd" in doc["psd"]
    top = doc["suggestions"][0]
    assert top["term"] == "gauss_markov" and top["significant"]
    after = top["error_after"]
    assert after["chi2_per_dof"] == top["chi2_per_dof_after"]
    assert after["psd"]["deviance_per_bin"] < doc["error"]["psd"]["deviance_per_bin"]
