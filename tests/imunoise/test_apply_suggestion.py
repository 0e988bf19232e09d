"""A suggestion's ``apply`` is what the user runs next: ``imunoise fit --model apply.model``
reports exactly the ``chi2_per_dof_after`` the suggestion stated, and it is lower."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imunoise.analysis.noise_stream import NoiseStream

FS = 100.0


def _imunoise(*argv: str) -> dict:
    proc = subprocess.run([sys.executable, "-m", "imunoise", *argv], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


@pytest.fixture(scope="module")
def csv(tmp_path_factory: pytest.TempPathFactory) -> Path:
    # white noise, a Markov bias and a vibration line: the starting model lacks both
    model = [("white", {"N": 2e-3}), ("gauss_markov", {"sigma": 3e-3, "T": 4.0}),
             ("sinusoid", {"A": 2e-3, "f": 7.3})]
    n = 1 << 17
    y = NoiseStream(model, FS, 11).take(n)
    path = tmp_path_factory.mktemp("apply") / "gm.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / FS, y]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.12g")
    return path


def test_applied_suggestions_report_the_stated_error_and_it_falls(csv: Path) -> None:
    model = "white,random_walk"
    seen = 0
    for _ in range(2):
        d = _imunoise("diagnose", str(csv), "--channel", "gyro_x", "--model", model, "--json")
        ch = d["channels"]["gyro_x"] if "channels" in d else d
        sig = [s for s in ch["suggestions"] if s["significant"]]
        for s in ch["suggestions"]:
            if s["action"] != "add":
                continue
            # every suggestion says how to apply it: the full model, the term appended
            assert s["apply"]["model"].split(",")[:len(model.split(","))] == model.split(",")
            assert s["apply"]["model"].split(",")[-1].split(":")[0] == s["term"]
            assert s["apply"]["args"] == []
            if s["significant"]:
                assert s["chi2_per_dof_after"] < s["chi2_per_dof_before"]
        if not sig:
            break
        top = sig[0]
        f = _imunoise("fit", str(csv), "--channel", "gyro_x", "--model", top["apply"]["model"],
                      "--json")
        fch = f["channels"]["gyro_x"] if "channels" in f else f
        # the same number, not a similar one
        assert fch["error"]["chi2_per_dof"] == pytest.approx(top["chi2_per_dof_after"],
                                                             rel=1e-9)
        model = top["apply"]["model"]
        seen += 1
    assert seen >= 1


def test_a_removal_applied_reports_the_stated_error(tmp_path: Path) -> None:
    """A Markov term the record does not hold (white noise, flicker and random walk at 50 Hz,
    seed 0): the top suggestion removes it, its apply.model is the model without it, and
    ``fit`` of that model reports the stated chi2/dof; the text names the action."""
    from imunoise.analysis.noise_stream import simulate

    base = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
            ("random_walk", {"K": 2e-6})]
    x = simulate(base, 1 << 18, 50.0, rng=0)
    path = tmp_path / "base.csv"
    np.savetxt(path, np.column_stack([np.arange(x.size) / 50.0, x]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    given = "white,bias_instability,random_walk,gauss_markov"
    d = _imunoise("diagnose", str(path), "--channel", "gyro_x", "--model", given, "--json")
    top = d["suggestions"][0]
    assert (top["action"], top["term"], top["label"], top["significant"]) == \
        ("remove", "gauss_markov", "gauss_markov", True)
    assert top["apply"] == {"model": "white,bias_instability,random_walk", "args": []}
    assert "sigma" in top["unresolved"]
    f = _imunoise("fit", str(path), "--channel", "gyro_x", "--model", top["apply"]["model"],
                  "--json")
    assert f["error"]["chi2_per_dof"] == pytest.approx(top["chi2_per_dof_after"], rel=1e-9)
    text = subprocess.run([sys.executable, "-m", "imunoise", "diagnose", str(path),
                           "--channel", "gyro_x", "--model", given],
                          capture_output=True, text=True, timeout=600).stdout
    assert "* 1. remove gauss_markov" in text
    assert "next: imunoise fit" in text and "--model white,bias_instability,random_walk\n" \
        in text
