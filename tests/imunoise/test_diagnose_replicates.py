"""``imunoise diagnose FILE1 FILE2 ...``: replicates of one unit, and the six ADIS16405 runs."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from imunoise.analysis.model_error import right_model_limit
from imunoise.analysis.noise_stream import NoiseStream
from imunoise.cli import main
from imunoise.core.units import DEG

FS = 100.0


def _write(path: Path, seed: int, f0: float) -> Path:
    model = [("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5}),
             ("resonance", {"sigma": 1e-2, "f0": f0, "Q": 50.0})]
    x = NoiseStream(model, FS, seed=seed).take(1 << 16)
    t = np.arange(x.size) / FS
    np.savetxt(path, np.column_stack([t, x]), delimiter=",", header="t,gyro_x", comments="",
               fmt="%.10g")
    return path


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> list[Path]:
    d = tmp_path_factory.mktemp("replicates")
    return [_write(d / f"run{i}.csv", 40 + i, f0) for i, f0 in enumerate([20.0, 20.0, 21.0])]


def test_json_names_the_moved_resonance(files, capsys) -> None:
    args = ["diagnose", *map(str, files), "--channel", "gyro_x", "--model",
            "white,random_walk,resonance", "--rounds", "0", "--json"]
    assert main(args) == 0
    doc = json.loads(capsys.readouterr().out)
    rep = doc["replicates"]
    assert [r["label"] for r in rep["runs"]] == list(map(str, files))
    assert rep["term_set"] == ["white", "random_walk", "resonance"]
    assert {(h["term"], h["param"]) for h in rep["shared"]} == {("resonance", "f0"),
                                                                ("resonance", "Q")}
    differ = {(h["term"], h["param"]): h for h in rep["differ"]}
    assert ("resonance", "f0") in differ
    f0 = [e["value"] for e in differ[("resonance", "f0")]["per_run"]]
    assert f0[2] / f0[0] == pytest.approx(1.05, abs=0.01)
    assert len(rep["per_run"]) == 3 and "white#0.N" in rep["per_run"][0]
    # a random walk of 1e-5 over 11 min is not resolved: an upper bound, flagged as such
    k = [run["random_walk#1.K"] for run in rep["per_run"]]
    assert all(e["unresolved"] and e["ci95"][0] == 0.0 for e in k)
    assert not any(run["white#0.N"]["unresolved"] for run in rep["per_run"])
    # each run's own fit of the model it was simulated from shows the parts of a right
    # model: PSD deviance about 1 (0.88-0.98 here over 139 bins) and a hold-out within
    # three standard deviations of 1 over its degrees of freedom
    for r in rep["runs"]:
        assert 0.7 < r["error"]["psd"]["deviance_per_bin"] < 1.4
        assert r["error"]["holdout"]["chi2_per_dof"] < right_model_limit(15)
        assert 0.0 < r["error"]["time_domain"]["p"] <= 1.0


def test_text_lists_shared_shapes_and_differences(files, capsys) -> None:
    assert main(["diagnose", *map(str, files[:2]), "--channel", "gyro_x", "--model",
                 "white,random_walk,resonance", "--rounds", "0"]) == 0
    out = capsys.readouterr().out
    assert "2 runs of one unit" in out and "shared shape parameters" in out
    assert "resonance         f0" in out
    assert "no parameter differs between runs beyond its interval" in out
    for f in files[:2]:
        assert re.search(rf"^    {re.escape(str(f))}: [0-9.]+ -> [0-9.]+ \| psd [0-9.]+ \| "
                         rf"hold-out [0-9.]+( \([0-9.]+ with [A-Za-z_.#0-9, ]+ fitted on each "
                         rf"half\))?$", out, re.M), out


def test_one_file_is_the_single_run_diagnosis(files, capsys) -> None:
    assert main(["diagnose", str(files[0]), "--channel", "gyro_x", "--model",
                 "white,random_walk,resonance", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert "replicates" not in doc and "suggestions" in doc


def test_each_runs_loop_is_that_files_own_loop(files, capsys) -> None:
    # the runs' loops run side by side in workers; each reaches what the loop on its file
    # alone reaches, one round from white,random_walk: the 20-21 Hz resonance
    from imunoise.analysis.replicates import Run, loop_terms

    assert main(["diagnose", *map(str, files), "--channel", "gyro_x", "--model",
                 "white,random_walk", "--rounds", "1", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)["replicates"]
    alone = []
    for f in files:
        x = np.loadtxt(f, delimiter=",", skiprows=1)[:, 1]
        alone.append(loop_terms(Run(str(f), x, FS, diagnose_kwargs={"units": "rad/s"}),
                                "white,random_walk", 1))
    assert [r["loop_terms"] for r in rep["runs"]] == alone
    assert alone == [["white", "random_walk", "resonance"]] * 3


def test_bad_rounds_is_a_usage_error(files, capsys) -> None:
    assert main(["diagnose", *map(str, files[:2]), "--channel", "gyro_x", "--model", "white",
                 "--rounds", "-1"]) == 2
    assert "--rounds '-1': a whole number >= 0" in capsys.readouterr().err


def test_one_file_twice_is_a_usage_error(files, tmp_path, capsys) -> None:
    # a run compared with itself agrees by construction; a link to it is the same file
    link = tmp_path / "again.csv"
    link.symlink_to(files[0])
    for second in (files[0], link):
        assert main(["diagnose", str(files[0]), str(second), "--channel", "gyro_x",
                     "--model", "white", "--rounds", "0"]) == 2
        err = capsys.readouterr().err
        assert f"{second} is {files[0]} again: replicates are different recordings" in err


def test_a_run_without_the_channel_or_too_short_for_the_skip_is_named(files, tmp_path,
                                                                      capsys) -> None:
    x = np.loadtxt(files[1], delimiter=",", skiprows=1)
    other = tmp_path / "accel.csv"
    np.savetxt(other, x, delimiter=",", header="t,accel_x", comments="", fmt="%.10g")
    assert main(["diagnose", str(files[0]), str(other), "--channel", "gyro_x", "--model",
                 "white", "--rounds", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"imunoise: {other}: unknown channel 'gyro_x'; valid channels: accel_x"]
    # a skip longer than one of the runs
    short = tmp_path / "short.csv"
    np.savetxt(short, x[:500], delimiter=",", header="t,gyro_x", comments="", fmt="%.10g")
    assert main(["diagnose", str(files[0]), str(short), "--channel", "gyro_x", "--model",
                 "white", "--rounds", "0", "--skip", "100"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"imunoise: {short}: gyro_x: --skip 100 s leaves no samples (the channel "
                   f"has 5 s)"]
    # a run too short to fit, with and without each run's loop
    tiny = tmp_path / "tiny.csv"
    np.savetxt(tiny, x[:3], delimiter=",", header="t,gyro_x", comments="", fmt="%.10g")
    for rounds in ("0", "1"):
        assert main(["diagnose", str(files[0]), str(tiny), "--channel", "gyro_x", "--model",
                     "white", "--rounds", rounds]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith(f"imunoise: gyro_x: {tiny}: the Allan "
                                                   f"curve has 1 usable taus"), err


def test_runs_at_different_rates_are_named_in_a_warning(files, tmp_path, capsys) -> None:
    # the same samples stamped at 50 Hz: a filter's taps mean another time at that rate
    x = np.loadtxt(files[1], delimiter=",", skiprows=1)
    slow = tmp_path / "slow.csv"
    np.savetxt(slow, np.column_stack([np.arange(len(x)) / 50.0, x[:, 1]]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    args = ["diagnose", str(files[0]), str(slow), "--channel", "gyro_x", "--model",
            "white,random_walk", "--rounds", "0"]
    assert main(args + ["--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    expected = (f"the runs' sample rates differ (100 Hz in {files[0]}, 50 Hz in {slow}): "
                f"shapes counted in samples")
    assert len(doc["warnings"]) == 1 and doc["warnings"][0].startswith(expected)
    assert main(args) == 0
    assert f"warning: {expected}" in capsys.readouterr().err
    # runs at one rate: no warning
    assert main(["diagnose", *map(str, files[:2]), "--channel", "gyro_x", "--model",
                 "white,random_walk", "--rounds", "0", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["warnings"] == []


def test_a_files_warning_names_the_file(files, tmp_path, capsys) -> None:
    x = np.loadtxt(files[1], delimiter=",", skiprows=1)
    x[1000, 1] = np.nan
    holed = tmp_path / "holed.csv"
    np.savetxt(holed, x, delimiter=",", header="t,gyro_x", comments="", fmt="%.10g")
    assert main(["diagnose", str(files[0]), str(holed), "--channel", "gyro_x", "--model",
                 "white,random_walk", "--rounds", "0", "--json"]) == 0
    warnings = json.loads(capsys.readouterr().out)["warnings"]
    assert warnings == [f"{holed}: gyro_x: 1 missing or non-finite value(s) removed; "
                        f"segments split around them"]


# The six ADIS16405 runs (2.8 h at 100 Hz each), one channel, the model the loop closes
# gyro_x with on run 1; what was measured on them (docs/replicates.md): the filter's length
# pooled 1.27 samples, but run 5 (1.32) against the others (1.17-1.20) is beyond the
# intervals, and the white level differs between nights (7.02e-4 to 7.70e-4 rad/s/sqrt(Hz),
# each to 0.2 %); B and K agree.
MEASURED_TAPS = (1.2, 1.35)
MEASURED_TAPS_DIFFER = True
MEASURED_DIFFER = {("moving_average", "taps"), ("white", "N")}


def test_six_adis16405_runs_gyro_x(shared_data) -> None:
    from imunoise.analysis.replicates import Run, fit_replicates

    runs = []
    for r in range(1, 7):
        d = np.load(shared_data / "adis16405" / f"run{r}.npz")
        g = d["gyro_counts"][:, 0] * float(d["gyro_scale_dps"]) * DEG
        runs.append(Run(f"run{r}", g, float(d["fs_hz"])))
    res = fit_replicates(runs, "white,bias_instability,random_walk,moving_average",
                         error_parts=False)
    taps = next(h for h in res.shared if h.param == "taps")
    assert MEASURED_TAPS[0] < taps.pooled < MEASURED_TAPS[1]
    assert taps.differs is MEASURED_TAPS_DIFFER
    n = next(h for h in res.amplitudes if h.param == "N")
    assert 6.9e-4 < n.pooled < 7.8e-4
    n_runs = [e.value for e in res.per_run_values(n)]
    assert max(n_runs) / min(n_runs) == pytest.approx(1.096, abs=0.01)  # run 5 against run 2
    assert {(h.term, h.param) for h in res.differ} == MEASURED_DIFFER


def test_six_adis16405_runs_gyro_z_compare_the_peak_where_the_spectrum_shows_it(
        shared_data) -> None:
    # the 20 Hz vibration: the Allan curve alone put it at 18.3 Hz in runs 2-4, whose
    # spectra peak at 19.76-19.95 Hz; held at the peak where that does not raise a run's
    # Allan misfit beyond its noise, with the spectrum's interval
    from imunoise.analysis.replicates import Run, fit_replicates

    runs = []
    for r in range(1, 7):
        d = np.load(shared_data / "adis16405" / f"run{r}.npz")
        g = d["gyro_counts"][:, 2] * float(d["gyro_scale_dps"]) * DEG
        runs.append(Run(f"run{r}", g, float(d["fs_hz"])))
    res = fit_replicates(runs, "white,bias_instability,random_walk,resonance,resonance",
                         intervals="jacobian", error_parts=False)
    f0 = next(h for h in res.shared if h.param == "f0" and h.pooled > 15.0)
    values = res.per_run_values(f0)
    at_peak = [e for e in values if e is not None and e.source == "psd"]
    assert len(at_peak) >= 3, values
    assert all(19.5 < e.value < 21.0 and e.ci95[1] - e.ci95[0] < 0.5 for e in at_peak), values
    assert f0.differs  # run 5's vibration sits near 17 Hz
    assert all(f.chi2_per_dof < 4.0 for f in res.free_fits), [f.chi2_per_dof
                                                               for f in res.free_fits]
