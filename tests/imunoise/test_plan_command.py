"""imunoise plan: from a model with values, and from a recording under way."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from imunoise.analysis.noise_stream import simulate


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "imunoise", "plan", *args], capture_output=True,
                          text=True, timeout=300)


def test_plan_from_a_model_json_and_text():
    out = _run("--model", "white:N=1e-3,random_walk:K=1e-4", "--rate", "10", "--target",
               "K=20%,N=2%", "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    k, n = doc["targets"]
    assert (k["term"], k["param"], k["target_relative_halfwidth"]) == ("random_walk", "K", 0.2)
    assert k["record_s"] == pytest.approx(1990, rel=0.02) and k["reachable"]
    assert n["record_s"] < k["record_s"]
    assert "stationary" in doc["assumption"] and "Allan fit" in doc["assumption"]
    text = _run("--model", "white:N=1e-3,random_walk:K=1e-4", "--rate", "10", "--target", "K=20%")
    assert "K (random_walk) = 0.0001: 95 % interval within +-20 % after 33.2 min" in text.stdout


@pytest.mark.parametrize(("args", "needle"), [
    (["--model", "white,random_walk", "--rate", "10", "--target", "K=20%"], "give N"),
    (["--model", "white:N=1e-3", "--target", "N=2%"], "--rate HZ"),
    (["--model", "white:N=1e-3", "--rate", "10", "--target", "K=20%"], "no parameter 'K'"),
    (["--model", "whyte:N=1e-3", "--rate", "10", "--target", "N=20%"], "whyte"),
])
def test_bad_plans_are_one_line_exit_2(args, needle):
    out = _run(*args)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert needle in out.stderr


def test_plan_from_a_recording_says_how_far_it_is(tmp_path):
    fs, n = 10.0, 6000  # ten minutes of a 33-minute plan for K
    y = simulate([("white", {"N": 1e-3}), ("random_walk", {"K": 1e-4})], n, fs, rng=5)
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / fs, y]), delimiter=",", comments="",
               header="t,gyro_x", fmt="%.12g")
    out = _run(str(path), "--channel", "gyro_x", "--model", "white,random_walk", "--target",
               "K=20%,N=5%", "--json")
    assert out.returncode == 0, out.stderr
    k, n_ = json.loads(out.stdout)["targets"]
    assert k["recorded_s"] == pytest.approx(600) and k["now_relative_halfwidth"] > 0.2
    assert k["more_s"] == pytest.approx(k["record_s"] - 600)
    assert 900 < k["record_s"] < 5000  # the fitted K of ten minutes is uncertain
    assert n_["more_s"] == 0.0  # N is already known to +-5 %
