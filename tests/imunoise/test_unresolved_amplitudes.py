"""An amplitude whose 95 % interval reaches zero is no estimate: every output says "not
resolved" with its upper bound (fit and diagnose text, their JSON's ``unresolved``)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np


def _run(argv: list[str]) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "imunoise", *argv], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return proc


def test_a_suggested_amplitude_whose_interval_reaches_zero_is_not_printed_as_a_number() -> None:
    from imunoise.commands.diagnose import _suggested_param

    # a refit that leaves the added ramp at zero: its interval reaches zero, so no estimate
    assert _suggested_param("rate_ramp", "R", 1.516e-24, (0.0, 2.164e-7), "rad/s^2") == \
        "R not resolved (95 % upper bound 2.164e-07 rad/s^2)"
    assert _suggested_param("quantization", "Q", 1.5e-6, (0.0, 3.0e-6), "rad") == \
        "Q not resolved (95 % upper bound 3e-06 rad)"
    # a resonance's Q is a quality factor, not the amplitude; a Markov time is shown as it is
    assert _suggested_param("resonance", "Q", 1.461, (0.0, 5.0), "1") == "Q = 1.461"
    assert _suggested_param("gauss_markov", "T", 146.1, (0.0, 900.0), "s") == "T = 146.1 s"
    assert _suggested_param("gauss_markov", "sigma", 1e-4, (5e-5, 2e-4), "rad/s") == \
        "sigma = 0.0001 rad/s"
    assert _suggested_param("rate_ramp", "R", 3e-7, None, "rad/s^2") == "R = 3e-07 rad/s^2"


def test_a_suggestion_names_its_unresolved_amplitudes_in_json() -> None:
    from imunoise.analysis.diagnosis import Suggestion

    s = Suggestion(term="rate_ramp", params={"R": 1.5e-24}, ci95={"R": (0.0, 2.2e-7)},
                   chi2_per_dof_before=1.58, chi2_per_dof_after=1.7, p_value=1.0, log_p=0.0,
                   significant=False, why="")
    assert s.to_dict()["unresolved"] == ["R"]
    s = Suggestion(term="resonance", params={"sigma": 5e-5, "f0": 0.003, "Q": 1.5},
                   ci95={"sigma": (2e-5, 9e-5), "f0": (0.001, 0.01), "Q": (0.0, 9.0)},
                   chi2_per_dof_before=1.58, chi2_per_dof_after=1.7, p_value=1.0, log_p=0.0,
                   significant=False, why="")
    assert s.to_dict()["unresolved"] == []
    cut = Suggestion(term="bias_step", params={"t_s": 30.0, "size": 1e-3}, ci95={},
                     chi2_per_dof_before=1.0, chi2_per_dof_after=0.9, p_value=0.01,
                     log_p=-4.6, significant=True, why="")
    assert cut.to_dict()["unresolved"] == []
    # a cut's signed size is no measurement when its interval holds zero
    for ci, want in (((-1e-3, 3e-3), ["size"]), ((1e-4, 2e-3), []), ((-2e-3, -1e-4), [])):
        cut.ci95 = {"size": ci}
        assert cut.to_dict()["unresolved"] == want, ci


def test_fit_json_names_the_amplitudes_the_text_calls_not_resolved(tmp_path) -> None:
    # 20 min of white noise fitted with flicker and random walk: neither is resolved
    fs, n = 100.0, 120_000
    x = np.random.default_rng(3).normal(0.0, 1e-3 * np.sqrt(fs), n)
    path = tmp_path / "white.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / fs, x]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    args = ["fit", str(path), "--channel", "gyro_x", "--model",
            "white,bias_instability,random_walk"]
    doc = json.loads(_run(args + ["--json"]).stdout)
    unresolved = {m["term"]: m["unresolved"] for m in doc["model"]}
    assert unresolved == {"white": [], "bias_instability": ["B"], "random_walk": ["K"]}
    assert all(m["ci95"][k][0] == 0.0 for m in doc["model"] for k in m["unresolved"])
    text = _run(args).stdout
    assert "N     =   0.000998" in text
    assert "B     = not resolved (95 % upper bound" in text
    assert "K     = not resolved (95 % upper bound" in text
