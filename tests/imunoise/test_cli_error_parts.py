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


def test_a_repeated_term_is_labelled_as_its_changes_are_named(csv):
    """``model[].term`` is the label (``gauss_markov#2``), as ``error.holdout.changed``
    names parameters; written back as a fully given model it reproduces the fit."""
    model = "white,gauss_markov:T=0.5,gauss_markov:T=20,random_walk"
    doc = json.loads(_run("fit", str(csv), "--channel", "gyro_x", "--model", model, "--json"))
    assert [m["term"] for m in doc["model"]] == ["white", "gauss_markov", "gauss_markov#2",
                                                 "random_walk"]
    given = ",".join(m["term"] + "".join(f":{k}={v:.15g}" for k, v in m["params"].items())
                     for m in doc["model"])
    again = json.loads(_run("fit", str(csv), "--channel", "gyro_x", "--model", given,
                            "--json"))
    assert [m["term"] for m in again["model"]] == [m["term"] for m in doc["model"]]
    # the same model curve (the chi2/dof differs by the degrees of freedom: nothing fitted)
    assert again["allan"]["model_adev"] == pytest.approx(doc["allan"]["model_adev"], rel=1e-9)
    text = _run("fit", str(csv), "--channel", "gyro_x", "--model", model)
    assert "gauss_markov#2" in text


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


def test_a_cut_reports_the_time_domain_part_that_fit_reports_after_the_cut(tmp_path):
    # the contract: a suggestion's error_after is what `fit` reports for the applied model;
    # for a cut that includes the time-domain part the cut is judged by
    fs, n = 50.0, int(2 * 3600 * 50.0)
    t = np.arange(n) / fs
    base = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
            ("random_walk", {"K": 2e-6})]
    x = simulate(base, n, fs, rng=700) + 1.2e-3 * (t >= 3030.0)
    path = tmp_path / "knock.csv"
    np.savetxt(path, np.column_stack([t, x]), delimiter=",", header="t,gyro_x", comments="",
               fmt="%.10g")
    spec = "white,bias_instability,random_walk"
    doc = json.loads(_run("diagnose", str(path), "--channel", "gyro_x", "--model", spec,
                          "--json"))
    top = doc["suggestions"][0]
    assert top["term"] == "bias_step" and top["significant"], top["why"]
    after = json.loads(_run("fit", str(path), "--channel", "gyro_x", "--model",
                            top["apply"]["model"], *top["apply"]["args"], "--json"))
    assert top["error_after"]["chi2_per_dof"] == pytest.approx(
        after["error"]["chi2_per_dof"], rel=1e-6)
    td, want = top["error_after"]["time_domain"], after["error"]["time_domain"]
    assert td["p"] >= 0.05 and doc["error"]["time_domain"]["p"] < 1e-4
    assert td["statistic"] == pytest.approx(want["statistic"], rel=1e-6)
    assert td["p"] == pytest.approx(want["p"], rel=1e-6)


def test_analyze_text_shows_the_psd_part_of_its_json_and_why_the_others_are_absent(csv):
    doc = json.loads(_run("analyze", str(csv), "--json"))
    err = doc["channels"]["gyro_x"]["error"]
    text = _run("analyze", str(csv))
    line = next(s.strip() for s in text.splitlines() if s.strip().startswith("error: allan"))
    why = "not computed by analyze: imunoise fit reports it"
    assert line == (f"error: allan chi2/dof {err['chi2_per_dof']:.3g} | psd deviance/bin "
                    f"{err['psd']['deviance_per_bin']:.3g} "
                    f"({100 * err['psd']['outside_95']:.0f} % of {err['psd']['bins']} bins "
                    f"outside 95 %) | hold-out chi2/dof n/a ({why}) | time domain n/a ({why})")
