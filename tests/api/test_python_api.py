"""The Python API on a small recording: the same numbers and documents as the command line,
the conversions and plots, the docstrings' examples, and a lazy ``import imunoise``."""

from __future__ import annotations

import contextlib
import dataclasses
import doctest
import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import imunoise
from imunoise.cli import main
from imunoise.errors import UsageError
from tests.blocked_imports import run_without

FS = 100.0


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> str:
    """A CSV of a gyro with white noise and a rate random walk, and a second channel, 20 min
    at 100 Hz."""
    rng = np.random.default_rng(42)
    n = 120_000
    gyro = rng.normal(0.0, 0.01, n) + np.cumsum(rng.normal(0.0, 2e-5, n))
    accel = rng.normal(0.0, 0.02, n)
    path = tmp_path_factory.mktemp("api") / "imu.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / FS, gyro, accel]), delimiter=",",
               header="t,gyro_x,accel_x", comments="", fmt="%.10g")
    return str(path)


def _cli_json(args: list[str]) -> dict:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(args) == 0
    return json.loads(out.getvalue())


def test_analyze_document_equals_the_command_line(recording):
    assert imunoise.analyze(recording) == _cli_json(["analyze", recording, "--json"])


def test_the_four_lines_give_analyze_numbers(recording):
    cli = _cli_json(["analyze", recording, "--json"])["channels"]["gyro_x"]
    rec = imunoise.read(recording)
    curve = imunoise.oadev(rec["gyro_x"])
    model = imunoise.fit(curve, "white,bias_instability,random_walk")
    dx = imunoise.diagnose(rec["gyro_x"], "white,bias_instability,random_walk")
    allan = curve.document()
    for key in ("tau_s", "adev", "ci_low", "ci_high", "edf", "alpha", "ci"):
        assert allan[key] == cli["allan"][key], key
    doc = model.document()
    for key in ("model", "failures", "allan", "channel", "units", "fs_hz", "n_samples"):
        assert doc[key] == cli[key], key
    # analyze reports the Allan and PSD parts of its default model's error; fit adds the
    # hold-out and time-domain parts, which analyze leaves to fit
    for key in ("chi2_per_dof", "max_abs_z", "psd"):
        assert doc["error"][key] == cli["error"][key], key
    # the measured PSD; analyze adds the default model's expected PSD and z beside it
    measured = imunoise.psd(rec["gyro_x"]).document()
    assert measured == {k: cli["psd"][k] for k in measured}
    assert set(cli["psd"]) - set(measured) == {"model_psd", "z"}
    # the diagnosis fits the same model to the same curve
    assert dx.document()["model"] == cli["model"]


def test_fit_and_diagnose_documents_equal_the_commands(recording):
    rec = imunoise.read(recording)
    model = "white,random_walk"
    fit_doc = _cli_json(["fit", recording, "--channel", "gyro_x", "--model", model, "--json"])
    report = imunoise.fit(rec["gyro_x"], model)
    assert report.document() == fit_doc
    # the error in its parts without the whole document
    assert report.error == fit_doc["error"]
    assert set(report.error) == {"chi2_per_dof", "max_abs_z", "psd", "holdout", "time_domain"}
    diagnose_doc = _cli_json(["diagnose", recording, "--channel", "gyro_x", "--model", model,
                              "--json"])
    dx = imunoise.diagnose(rec["gyro_x"], model)
    assert dx.document() == diagnose_doc
    assert dx.error == diagnose_doc["error"]
    # a curve of an array has the Allan part alone
    assert set(imunoise.fit(imunoise.oadev(rec["gyro_x"].values, 100.0), model).error) == {
        "chi2_per_dof", "max_abs_z"}


def test_fit_of_a_channel_and_of_its_curve_agree(recording):
    rec = imunoise.read(recording)
    of_channel = imunoise.fit(rec["gyro_x"], "white,random_walk")
    of_curve = imunoise.fit(imunoise.oadev(rec["gyro_x"]), "white,random_walk")
    assert of_channel.document() == of_curve.document()


def test_repeated_terms_come_in_one_order_from_a_channel_and_from_its_curve(recording):
    # the solver puts the 12 s Markov term in the first entry here; both report it second
    rec = imunoise.read(recording)
    model = "white,gauss_markov,gauss_markov,random_walk"
    of_channel = imunoise.fit(rec["gyro_x"], model).document()
    of_curve = imunoise.fit(imunoise.oadev(rec["gyro_x"]), model).document()
    assert of_channel == of_curve
    entries = {m["term"]: m["params"] for m in of_curve["model"]}
    assert entries["gauss_markov"]["T"] < entries["gauss_markov#2"]["T"]


def test_recovers_the_simulated_noise(recording):
    """White N = 0.01 rad/s / sqrt(100 Hz) = 1e-3 rad/s/sqrt(Hz), K = 2e-5 rad/s * sqrt(100 Hz)
    = 2e-4 rad/s/sqrt(s): each inside the fit's own 95 % interval."""
    report = imunoise.fit(imunoise.read(recording)["gyro_x"], "white,random_walk")
    table = report.to_pandas().set_index(["term", "param"])
    for (term, param), truth in {("white", "N"): 1e-3, ("random_walk", "K"): 2e-4}.items():
        row = table.loc[(term, param)]
        assert row.ci95_low <= truth <= row.ci95_high, (term, param, row.to_dict())
        assert row.resolved


def test_arrays_are_analysed_like_channels(recording):
    ch = imunoise.read(recording)["accel_x"]
    assert imunoise.oadev(ch.values, fs_hz=ch.fs_hz).document() == imunoise.oadev(ch).document()
    assert imunoise.psd(ch.values, fs_hz=ch.fs_hz).document() == imunoise.psd(ch).document()
    with pytest.raises(TypeError, match="fs_hz"):
        imunoise.oadev(ch.values)


def test_tables_and_labelled_arrays(recording):
    rec = imunoise.read(recording)
    curve = imunoise.oadev(rec["gyro_x"])
    frame = curve.to_pandas()
    assert frame.index.name == "tau_s" and np.array_equal(frame["adev"], curve.adev)
    ds = curve.to_xarray()
    assert ds["adev"].attrs["units"] == "rad/s" and ds["tau_s"].attrs["units"] == "s"
    assert np.array_equal(ds["adev"].values, curve.adev)
    spectrum = imunoise.psd(rec["gyro_x"])
    assert spectrum.to_pandas().index.name == "f_hz"
    assert spectrum.to_xarray()["psd"].attrs["units"] == "(rad/s)^2/Hz"
    dx = imunoise.diagnose(rec["gyro_x"], "white")
    table = dx.to_pandas()
    assert list(table["term"]) == [s["term"] for s in dx.suggestions]
    assert list(table["action"]) == [s["action"] for s in dx.suggestions]
    # a pair of terms suggested together is one row named by both
    first = dx.diagnosis.suggestions[0]
    pair = dataclasses.replace(first, label=f"{first.term} and resonance")
    dx.diagnosis.suggestions[0] = pair
    assert dx.to_pandas()["term"][0] == f"{first.term} and resonance"
    assert set(table["action"]) <= {"add", "cut", "remove"}


def test_plots_draw_the_curves(recording):
    import matplotlib

    matplotlib.use("Agg")
    rec = imunoise.read(recording)
    curve = imunoise.oadev(rec["gyro_x"])
    ax = curve.plot()
    assert np.array_equal(ax.lines[0].get_ydata(), curve.adev)
    ax = imunoise.fit(curve, "white,random_walk").plot()
    labels = [line.get_label() for line in ax.lines]
    assert labels[:4] == ["gyro_x", "model", "white", "random_walk"]
    assert imunoise.psd(rec["gyro_x"]).plot().get_xscale() == "log"
    assert "gyro_x" in imunoise.diagnose(rec["gyro_x"], "white").plot().get_title()


def test_bad_input_raises_the_command_lines_message(tmp_path, recording):
    with pytest.raises(UsageError, match="does not exist|no such|not found"):
        imunoise.read(str(tmp_path / "missing.mcap"))
    rec = imunoise.read(recording)
    with pytest.raises(UsageError, match="gyro_x"):
        rec["gyro_q"]
    with pytest.raises(UsageError, match="unknown term"):
        imunoise.fit(rec["gyro_x"], "white,pink")
    with pytest.raises(TypeError, match="channel"):
        imunoise.diagnose(imunoise.oadev(rec["gyro_x"]))


def test_docstring_examples():
    """The examples in the public functions' docstrings (run as written)."""
    import imunoise.api

    result = doctest.testmod(imunoise.api, optionflags=doctest.NORMALIZE_WHITESPACE)
    assert result.attempted >= 25 and result.failed == 0


def test_import_imunoise_loads_no_numerics():
    """``import imunoise`` (and so the command line's start) imports neither numpy nor the
    API; the first use of an API name does."""
    code = ("import sys, imunoise; before = 'numpy' in sys.modules; imunoise.read; "
            "print(before, 'numpy' in sys.modules, 'imunoise.api' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["False", "True", "True"]


def test_plot_without_matplotlib_names_the_extra(tmp_path):
    code = ("import numpy as np, imunoise; "
            "imunoise.oadev(np.random.default_rng(0).normal(size=4000), fs_hz=100.0).plot()")
    out = run_without(["matplotlib"], ["-c", code], tmp_path)
    assert out.returncode == 1
    assert out.stderr.strip().splitlines()[-1] == (
        "imunoise.extras.MissingExtra: plot() needs the optional 'plot' extra (matplotlib is "
        "not installed): pip install 'imunoise[plot]'")


def test_a_windowed_channel_is_fit_and_diagnosed_as_with_skip_and_split(recording):
    rec = imunoise.read(recording)
    cut = rec["gyro_x"].window(skip_s=120.0, split_s=[600.0])
    assert cut.series.n_samples == rec["gyro_x"].series.n_samples - 12_000
    assert len(cut.series.segment_starts) == 2
    assert rec["gyro_x"].series.n_samples == 120_000  # the recording is left as it was
    args = ["--channel", "gyro_x", "--model", "white,random_walk", "--skip", "120",
            "--split", "600", "--json"]
    assert imunoise.fit(cut, "white,random_walk").document() == _cli_json(
        ["fit", recording, *args])
    assert imunoise.diagnose(cut, "white,random_walk").document() == _cli_json(
        ["diagnose", recording, *args])
    with pytest.raises(UsageError, match="leaves no samples"):
        rec["gyro_x"].window(skip_s=1e6)


@pytest.fixture(scope="module")
def second_run(tmp_path_factory) -> str:
    """Another recording of the gyro of :func:`recording` (another noise draw, the same
    levels), 20 min at 100 Hz."""
    rng = np.random.default_rng(43)
    n = 120_000
    gyro = rng.normal(0.0, 0.01, n) + np.cumsum(rng.normal(0.0, 2e-5, n))
    path = tmp_path_factory.mktemp("api2") / "imu.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / FS, gyro]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    return str(path)


def test_replicates_document_equals_the_command_line(recording, second_run):
    runs = [imunoise.read(recording)["gyro_x"], imunoise.read(second_run)["gyro_x"]]
    rep = imunoise.replicates(runs, "white,random_walk", rounds=1)
    assert rep.document() == _cli_json(["diagnose", recording, second_run, "--channel",
                                        "gyro_x", "--model", "white,random_walk", "--rounds",
                                        "1", "--json"])
    assert rep.runs == [recording, second_run]
    assert rep.term_set == ["white", "random_walk"]
    # one unit's levels on both runs: the pooled white level is the simulated one
    doc = rep.document()["replicates"]
    white = next(h for h in doc["amplitudes"] if h["term"] == "white")
    assert white["value"] == pytest.approx(0.01 / np.sqrt(FS), rel=0.01)  # N = sigma sqrt(dt)
    assert rep.differ == doc["differ"]
    table = rep.to_pandas()
    assert list(table["run"]) == rep.runs
    assert table["chi2_per_dof"].between(0.2, 3.0).all()
    named = ", ".join(f"{d['term']}.{d['param']}" for d in doc["differ"])
    assert repr(rep) == ("<Replicates gyro_x: 2 runs, model white,random_walk, "
                         + (f"differ: {named}>" if named else "no parameter differs>"))


def test_replicates_text_and_plot(recording, second_run, capsys):
    import matplotlib

    matplotlib.use("Agg")
    runs = [imunoise.read(recording)["gyro_x"], imunoise.read(second_run)["gyro_x"]]
    rep = imunoise.replicates(runs, "white,random_walk")
    assert main(["diagnose", recording, second_run, "--channel", "gyro_x", "--model",
                 "white,random_walk", "--rounds", "0"]) == 0
    assert rep.text() + "\n" == capsys.readouterr().out
    ax = rep.plot()
    # per run: the measured points, then its model with the shared shapes held
    measured, model = ax.lines[0::2], ax.lines[1::2]
    assert [line.get_label() for line in measured] == rep.runs
    for line, fit in zip(measured, rep.result.tied_fits, strict=True):
        assert np.allclose(line.get_ydata(), np.sqrt(fit.avar_measured))
    for line, fit in zip(model, rep.result.tied_fits, strict=True):
        assert np.allclose(line.get_ydata(), np.sqrt(fit.avar_fit))
    assert [m.get_color() for m in model] == [m.get_color() for m in measured]
    assert ax.get_title() == "gyro_x: 2 runs, model white,random_walk"
    assert ax.get_ylabel() == "Allan deviation [rad/s]"


def test_replicates_of_cut_runs_name_their_cuts(recording, second_run):
    first = imunoise.read(recording)["gyro_x"]
    runs = [first.window(skip_s=60.0), first.window(split_s=[600.0]),
            first.window(skip_s=30.0, split_s=[300.0, 900.0]),
            imunoise.read(second_run)["gyro_x"]]
    rep = imunoise.replicates(runs, "white,random_walk")
    assert rep.runs == [f"{recording} (skip 60 s)", f"{recording} (split 600 s)",
                        f"{recording} (skip 30 s; split 300, 900 s)", second_run]


def test_replicates_refuse_what_cannot_be_compared(recording, second_run):
    rec = imunoise.read(recording)
    other = imunoise.read(second_run)["gyro_x"]
    with pytest.raises(UsageError, match="two or more runs of one unit, got 1"):
        imunoise.replicates([rec["gyro_x"]])
    with pytest.raises(UsageError, match="is given twice"):
        imunoise.replicates([rec["gyro_x"], other, imunoise.read(recording)["gyro_x"]])
    with pytest.raises(UsageError, match="one channel across runs, got accel_x, gyro_x"):
        imunoise.replicates([rec["accel_x"], other])
    with pytest.raises(UsageError, match="unknown term"):
        imunoise.replicates([rec["gyro_x"], other], "white,pink")
    with pytest.raises(UsageError, match="rounds -1: a whole number >= 0"):
        imunoise.replicates([rec["gyro_x"], other], rounds=-1)
    with pytest.raises(TypeError, match="channels of imunoise.read"):
        imunoise.replicates([rec["gyro_x"], other.values])


def test_the_examples_leave_no_file_behind(tmp_path):
    """The docstring examples' recordings go in one temporary folder per process, removed when
    the process ends."""
    code = ("import numpy as np, imunoise.api as api; "
            "a = api._example_csv(np.zeros(10)); b = api._example_csv(np.ones(10)); "
            "print(a); print(b)")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env={**os.environ, "TMPDIR": str(tmp_path)})
    assert run.returncode == 0, run.stderr
    a, b = (Path(p) for p in run.stdout.split())
    assert a != b and a.parent == b.parent and a.parent.parent == tmp_path
    assert not a.parent.exists() and list(tmp_path.iterdir()) == []


def test_findings_read_as_the_text_prints_them(tmp_path):
    # a rate random walk through the first half only: the halves name it as changed
    rng = np.random.default_rng(7)
    n = 120_000
    walk = np.cumsum(rng.normal(0.0, 2e-5, n))
    walk[n // 2:] = walk[n // 2]
    path = tmp_path / "changed.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / FS, rng.normal(0.0, 0.01, n) + walk]),
               delimiter=",", header="t,gyro_x", comments="", fmt="%.10g")
    rec = imunoise.read(str(path))
    report = imunoise.fit(rec["gyro_x"], "white,random_walk")
    assert report.findings
    assert report.findings[0].startswith("random_walk.K changed between the first and "
                                         "second half: ")
    text = io.StringIO()
    with contextlib.redirect_stdout(text):
        assert main(["fit", str(path), "--channel", "gyro_x", "--model",
                     "white,random_walk"]) == 0
    printed = [line.strip().removeprefix("finding: ") for line in text.getvalue().splitlines()
               if line.strip().startswith("finding: ")]
    assert printed == report.findings
    assert imunoise.diagnose(rec["gyro_x"], "white,random_walk").findings == report.findings
    # a curve of an array has no halves
    assert imunoise.fit(imunoise.oadev(rec["gyro_x"].values, FS), "white,random_walk"
                        ).findings == []
