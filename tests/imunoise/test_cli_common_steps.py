"""``common_steps`` end to end through the real CLI: offered by ``diagnose`` where the
accelerometer axes step together, applied by ``fit``, refused where no other channel can
tell a step from the channel's own wander."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imunoise.analysis.noise_stream import simulate

FS = 50.0
N = int(2 * 3600 * FS)
NAMES = ["accel_x", "accel_y", "accel_z"]
MODEL = [("white", {"N": 4.7e-3}), ("bias_instability", {"B": 2.7e-3}),
         ("random_walk", {"K": 2.9e-4})]
BASE = "white,bias_instability,random_walk"
STEPS = [(1500.0, (0.03, -0.02, 0.025)), (3900.0, (-0.025, 0.03, 0.0)),
         (5600.0, (0.02, 0.02, -0.03))]
ADIS = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "adis16405"


def _run(*args):
    return subprocess.run([sys.executable, "-m", "imunoise", *map(str, args)],
                          capture_output=True, text=True, timeout=600)


def _csv(path: Path, x: np.ndarray, names: list[str]) -> Path:
    np.savetxt(path, np.column_stack([np.arange(len(x)) / FS, x]), delimiter=",",
               fmt="%.10g", comments="", header="t," + ",".join(names))
    return path


@pytest.fixture(scope="module")
def knocked(tmp_path_factory) -> Path:
    """Two hours of three accelerometer axes at rest, the bench knocked three times."""
    x = np.column_stack([simulate(MODEL, N, FS, rng=500 + c) for c in range(3)])
    t = np.arange(N) / FS
    for t0, sizes in STEPS:
        x += (t >= t0)[:, None] * np.array(sizes)
    return _csv(tmp_path_factory.mktemp("steps") / "knocked.csv", x, NAMES)


def test_diagnose_offers_the_steps_and_fit_takes_them_out(knocked):
    proc = _run("diagnose", knocked, "--channel", "accel_x", "--model", BASE, "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    top = next(s for s in doc["suggestions"] if s["significant"])
    assert top["term"] == "common_steps" and top["params"] == {}
    assert top["apply"] == {"model": BASE + ",common_steps", "args": []}
    assert "jump together 3 time(s), and 3 of the jumps leave a lasting step on accel_x" \
        in top["why"]
    assert top["chi2_per_dof_after"] < top["chi2_per_dof_before"]
    proc = _run("fit", knocked, "--channel", "accel_x", "--model", top["apply"]["model"],
                "--json")
    assert proc.returncode == 0, proc.stderr
    fit = json.loads(proc.stdout)
    # fit reports what the suggestion said, and lists the removal in its model
    assert fit["error"]["chi2_per_dof"] == pytest.approx(top["chi2_per_dof_after"], rel=1e-9)
    assert fit["model"][-1] == {"term": "common_steps", "params": {}, "ci95": {},
                                "unresolved": []}
    from tests.imunoise.test_json_schemas import validator

    validator("fit").validate(fit)  # the block follows docs/schemas
    validator("diagnose").validate(doc)
    steps = fit["common_steps"]
    assert [round(s["t_s"]) for s in steps["steps"]] == [1500, 3900, 5600]
    for s, (_, sizes) in zip(steps["steps"], STEPS, strict=True):
        assert s["size"] == pytest.approx(sizes[0], abs=4.0 * abs(s["size"] / s["z"]))
    assert steps["channels"] == NAMES and steps["found"] == 3
    # the random walk the steps posed as is gone with them
    k = next(t for t in fit["model"] if t["term"] == "random_walk")["params"]["K"]
    assert k < 1e-3
    text = _run("fit", knocked, "--channel", "accel_x", "--model", top["apply"]["model"])
    assert text.returncode == 0, text.stderr
    assert re.search(r"common_steps: 3 step\(s\) taken out of accel_x \(found together in "
                     r"accel_x, accel_y, accel_z\): 1500 s \+0\.0[23]\d* m/s\^2, 3900 s -0\.0",
                     text.stdout), text.stdout


def test_a_channel_the_steps_missed_keeps_its_samples(knocked):
    # accel_z did not move at 3900 s: two of the three steps are taken out of it
    proc = _run("fit", knocked, "--channel", "accel_z", "--model", BASE + ",common_steps",
                "--json")
    assert proc.returncode == 0, proc.stderr
    assert [round(s["t_s"]) for s in json.loads(proc.stdout)["common_steps"]["steps"]] \
        == [1500, 5600]


def test_diagnose_keeps_the_removal_in_what_it_suggests(knocked):
    proc = _run("diagnose", knocked, "--channel", "accel_y", "--model",
                BASE + ",common_steps", "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert all(s["apply"]["model"].split(",").count("common_steps") == 1
               for s in doc["suggestions"] if s["apply"]["model"])
    assert not any(s["term"] == "common_steps" for s in doc["suggestions"])
    assert doc["model"][-1]["term"] == "common_steps"


def test_a_still_record_gets_no_such_suggestion(tmp_path):
    x = np.column_stack([simulate(MODEL, N, FS, rng=600 + c) for c in range(3)])
    still = _csv(tmp_path / "still.csv", x, NAMES)
    proc = _run("diagnose", still, "--channel", "accel_y", "--model", BASE, "--json")
    assert proc.returncode == 0, proc.stderr
    assert not any(s["term"] == "common_steps" for s in json.loads(proc.stdout)["suggestions"])
    proc = _run("fit", still, "--channel", "accel_y", "--model", BASE + ",common_steps")
    assert proc.returncode == 0, proc.stderr
    assert "common_steps: no step found in accel_y, accel_x, accel_z; accel_y is fitted as " \
           "read" in proc.stdout


def test_the_removal_is_refused_where_it_cannot_be_told(tmp_path, knocked):
    single = _csv(tmp_path / "one.csv",
                  simulate(MODEL, 1 << 16, FS, rng=7)[:, None], ["accel_x"])
    proc = _run("fit", single, "--channel", "accel_x", "--model", BASE + ",common_steps")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].endswith(
        "common_steps: no other channel of this record shares accel_x's time base and units "
        "(m/s^2), so steps common to them cannot be told from accel_x's own wander")
    proc = _run("fit", knocked, "--channel", "accel_x", "--model",
                BASE + ",common_steps:size=0.1")
    assert proc.returncode == 2
    assert "common_steps takes no parameters" in proc.stderr
    proc = _run("diagnose", knocked, "--channel", "accel_x", "--model", "common_steps")
    assert proc.returncode == 2
    assert "name the noise terms to fit beside it" in proc.stderr


@pytest.mark.skipif(not (ADIS / "run1.npz").exists(),
                    reason="../shared/data (ADIS16405 recordings) is not beside this checkout")
def test_adis16405_run1_accel_z_loses_the_knock(tmp_path):
    d = np.load(ADIS / "run1.npz")
    a = d["accel_counts"] * float(d["accel_scale_g"]) * 9.80665
    path = tmp_path / "run1.csv"
    np.savetxt(path, np.column_stack([np.arange(len(a)) / float(d["fs_hz"]), a]),
               delimiter=",", fmt="%.10g", comments="", header="t," + ",".join(NAMES))
    model = BASE + ",moving_average,common_steps"
    proc = _run("fit", path, "--channel", "accel_z", "--model", model, "--json")
    assert proc.returncode == 0, proc.stderr
    steps = {round(s["t_s"]): s for s in json.loads(proc.stdout)["common_steps"]["steps"]}
    # it jumps by 10.3 standard scores and keeps 0.0098 m/s^2 of it (3.2 scores)
    assert steps[2149]["jump_z"] == pytest.approx(10.3, abs=0.05)
    assert steps[2149]["size"] == pytest.approx(0.0098, abs=5e-5)


def test_the_python_api_says_it_does_not_take_the_removal(knocked):
    import imunoise
    from imunoise.errors import UsageError

    rec = imunoise.read(str(knocked))
    with pytest.raises(UsageError, match="common_steps is a correction of the record, not a "
                                         "term: imunoise fit and diagnose apply it"):
        imunoise.fit(rec["accel_x"], BASE + ",common_steps")
