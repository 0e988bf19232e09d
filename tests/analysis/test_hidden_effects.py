"""Hidden-effect suite: data simulated from a base model plus one effect X; given the base
model, diagnose must rank X first and significant, the fit with X must bring the misfit back
to consistency, and X's parameters must land within their intervals of the truth.

Records are 2 h at 50 Hz of white noise, bias instability and rate random walk at levels of a
consumer MEMS gyro; each effect is at a level that is visible in the Allan curve or spectrum
but does not dominate it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.noise_stream import simulate

FS = 50.0
N = int(2 * 3600 * FS)
BASE = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
        ("random_walk", {"K": 2e-6})]
BASE_NAMES = [t for t, _ in BASE]
HIDDEN = {
    "quantization": ("quantization", {"Q": 2e-5}),
    "rate_ramp": ("rate_ramp", {"R": 5e-7}),
    "gauss_markov": ("gauss_markov", {"sigma": 2e-4, "T": 10.0}),
    "sinusoid": ("sinusoid", {"A": 3e-4, "f": 2.7}),
    "temperature": ("temperature", {"coef": 1e-4}),
}
SEEDS = (11, 12, 13)


def temperature_profile(t_s: np.ndarray) -> np.ndarray:
    """Warm-up of the sensor and a slow room cycle, degC."""
    dur = float(t_s[-1])
    return 24.0 + 8.0 * (1 - np.exp(-t_s / (0.15 * dur))) \
        + 1.5 * np.sin(2 * np.pi * t_s / (0.4 * dur))


def make_case(model, seed: int):
    t = np.arange(N) / FS
    temp = temperature_profile(t)
    x = simulate(model, N, FS, rng=seed, temperature=temp)
    return t, x, temp


def consistent(chi2_per_dof: float, dof: int) -> bool:
    """The misfit is what a correct model gives 99.9 % of the time."""
    return bool(stats.chi2.sf(chi2_per_dof * dof, dof) > 1e-3)


def run_diagnosis(model, given, seed):
    t, x, temp = make_case(model, seed)
    return diagnose(x, FS, given, temperature=(t[::50], temp[::50]))


@pytest.mark.parametrize("name", list(HIDDEN))
def test_hidden_effect_found_first_and_fitted(name):
    term, truth = HIDDEN[name]
    inside = 0
    for seed in SEEDS:
        d = run_diagnosis(BASE + [(term, truth)], BASE_NAMES, seed)
        top = d.suggestions[0]
        assert top.term == term, [(s.term, s.p_value) for s in d.suggestions[:3]]
        if term == "temperature":
            # the thermal drift is plain in the correlation with the record, but a model
            # that already explains the curve (chi2/dof near 1) may not fit the corrected
            # series better: significant means applying it lowers the error
            ev = next(f for f in d.findings if f.term == "temperature")
            assert ev.significant
            assert top.significant == (top.chi2_per_dof_after < top.chi2_per_dof_before)
        else:
            assert top.significant
            assert top.chi2_per_dof_after < top.chi2_per_dof_before
        assert consistent(top.chi2_per_dof_after, top.fit.misfit.dof), top.chi2_per_dof_after
        inside += all(top.ci95[p][0] <= v <= top.ci95[p][1] for p, v in truth.items())
    assert inside >= 2, f"{name}: truth inside the intervals in {inside} of {len(SEEDS)} seeds"


# The random walk at the base level barely shows in 2 h; a noisier unit shows it clearly.
STRONG_WALK = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
               ("random_walk", {"K": 1e-5})]


@pytest.mark.parametrize("missing", BASE_NAMES)
def test_model_missing_one_of_its_own_terms(missing):
    given = [t for t in BASE_NAMES if t != missing]
    model = STRONG_WALK if missing == "random_walk" else BASE
    truth = dict(model)[missing]
    inside = 0
    for seed in SEEDS[:2]:
        d = run_diagnosis(model, given, seed)
        top = d.suggestions[0]
        assert top.term == missing and top.significant
        assert consistent(top.chi2_per_dof_after, top.fit.misfit.dof)
        inside += all(top.ci95[p][0] <= v <= top.ci95[p][1] for p, v in truth.items())
    assert inside >= 1


def test_control_nothing_significant():
    """Data the model fully explains: no suggestion significant (family level 5 %: at most
    one of ten seeds may show one)."""
    flagged = []
    for seed in range(100, 110):
        d = run_diagnosis(BASE, BASE_NAMES, seed)
        flagged += [(seed, s.term) for s in d.suggestions if s.significant]
    assert len({seed for seed, _ in flagged}) <= 1, flagged


def test_control_with_an_output_filter_and_lost_samples_nothing_significant():
    """The sensor's 4-tap moving-average filter in the model and 20 runs of lost samples in
    each record: still nothing significant (at most one of ten seeds), the misfit consistent
    with the model in every seed. (Seeds 1003 and 1005 once showed a line at the filter's
    notch.)"""
    model = BASE + [("moving_average", {"taps": 4})]
    given = BASE_NAMES + ["moving_average:taps=4"]
    flagged, chis = [], []
    for seed in range(1000, 1010):
        x = simulate(model, N, FS, rng=seed)
        rng = np.random.default_rng(seed)
        keep = np.ones(N, dtype=bool)
        for start in rng.integers(0, N - 100, 20):
            keep[start:start + rng.integers(1, 50)] = False
        kept = np.flatnonzero(keep)
        starts = np.concatenate(([0], np.flatnonzero(np.diff(kept) > 1) + 1))
        d = diagnose(x[keep], FS, given, segment_starts=starts)
        flagged += [(seed, s.term) for s in d.suggestions if s.significant]
        assert consistent(d.fit.chi2_per_dof, d.fit.misfit.dof), (seed, d.fit.chi2_per_dof)
        chis.append(d.fit.chi2_per_dof)
    assert len({seed for seed, _ in flagged}) <= 1, flagged
    # the mean of ten chi2/dof with about 14 dof each has a standard deviation near 0.12
    assert abs(np.mean(chis) - 1.0) < 0.3, chis


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "imunoise", *args], capture_output=True,
                          text=True, timeout=300)


def test_csv_file_through_the_command_line(tmp_path: Path):
    term, truth = HIDDEN["sinusoid"]
    t, x, temp = make_case(BASE + [(term, truth)], 21)
    path = tmp_path / "still.csv"
    np.savetxt(path, np.column_stack([t, x, temp]), delimiter=",", header="t,gyro_x,temp",
               comments="", fmt="%.9g")
    out = _cli("diagnose", str(path), "--channel", "gyro_x", "--model",
               ",".join(BASE_NAMES), "--json")
    assert out.returncode == 0, out.stderr
    doc = json.loads(out.stdout)
    for key in ("channel", "units", "fs_hz", "n_samples", "duration_s", "model", "error",
                "failures", "allan", "suggestions"):
        assert key in doc
    top = doc["suggestions"][0]
    assert top["term"] == "sinusoid" and top["significant"]
    assert abs(top["params"]["f"] - 2.7) < 0.01
    assert top["chi2_per_dof_after"] < doc["error"]["chi2_per_dof"]
    assert "2.7" in top["why"] and "chi2/dof" in top["why"]
    text = _cli("diagnose", str(path), "--channel", "gyro_x", "--model", ",".join(BASE_NAMES))
    assert text.returncode == 0 and "add sinusoid" in text.stdout


def test_mcap_file_with_slow_temperature_topic(tmp_path: Path):
    from imunoise.core.blocks import SampleBlock
    from imunoise.daq.recorder import McapRecorder

    term, truth = HIDDEN["temperature"]
    t, x, temp = make_case(BASE + [(term, truth)], 22)
    t0 = 1.7e9
    rec = McapRecorder(tmp_path, "sim:adis16350", config={"model": "ADIS16350"},
                       threaded=False, fsync=False, rotate_s=None)
    other = ("gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
    step = 50_000
    for a in range(0, N, step):
        sl = slice(a, a + step)
        chans = {c: np.zeros(len(t[sl])) for c in other}
        chans["gyro_x"] = x[sl]
        rec.write(SampleBlock("/imu/data", t0 + t[sl], chans, FS))
        # The thermometer reports once a second.
        rec.write(SampleBlock("/imu/temperature", t0 + t[sl][:: int(FS)],
                              {"temp": temp[sl][:: int(FS)]}, 1.0))
    rec.close()
    path = next(tmp_path.glob("*.mcap"))
    out = _cli("diagnose", str(path), "--channel", "gyro_x", "--model",
               ",".join(BASE_NAMES), "--json")
    assert out.returncode == 0, out.stderr
    top = json.loads(out.stdout)["suggestions"][0]
    # found first on the correlation's strength; significant only if the refit's error falls
    assert top["term"] == "temperature" and top["p_value"] < 0.05
    assert top["significant"] == (top["chi2_per_dof_after"] < top["chi2_per_dof_before"])
    assert top["apply"]["model"] == ",".join(BASE_NAMES) + ",temperature"
    lo, hi = top["ci95"]["coef"]
    assert lo <= truth["coef"] <= hi


def test_bad_usage_is_one_line_exit_2(tmp_path: Path):
    path = tmp_path / "tiny.csv"
    np.savetxt(path, np.column_stack([np.arange(2000) / FS, np.zeros(2000)]), delimiter=",",
               header="t,gyro_x", comments="")
    for args, needle in ((["--model", "white,bogus"], "bogus"),
                         (["--model", "white", "--channel", "accel_q"], "accel_q")):
        argv = ["diagnose", str(path)] + (args if "--channel" in args
                                          else ["--channel", "gyro_x"] + args)
        out = _cli(*argv)
        assert out.returncode == 2, out.stderr
        lines = out.stderr.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0]
