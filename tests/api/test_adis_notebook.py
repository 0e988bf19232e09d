"""The Python API on a real recording: ADIS16405 run 1 (2.8 h at 100 Hz, ../shared) written
as an imunoise MCAP file. The four-line cell gives ``imunoise analyze --json``'s numbers, and
the example notebook runs and keeps its plots."""

from __future__ import annotations

import contextlib
import io
import itertools
import json
from pathlib import Path

import numpy as np
import pytest

import imunoise
from imunoise.cli import main
from imunoise.core.blocks import SampleBlock
from imunoise.core.units import DEG, G0
from imunoise.daq.recorder import McapRecorder
from tests.shared_paths import REPO

NOTEBOOK = REPO / "examples" / "python_api.ipynb"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def adis_run1(shared_data, tmp_path_factory) -> str:
    """Run 1 as the recorder writes it: one topic, gyro in rad/s, accel in m/s^2."""
    d = np.load(shared_data / "adis16405" / "run1.npz")
    fs = float(d["fs_hz"])
    gyro = d["gyro_counts"] * float(d["gyro_scale_dps"]) * DEG
    acc = d["accel_counts"] * float(d["accel_scale_g"]) * G0
    out = tmp_path_factory.mktemp("adis_run1")
    start = 1.6e9
    clock = itertools.count(start)
    rec = McapRecorder(out, "adis16405_run1", config={"sensor_model": "adis16405"}, rate_hz=fs,
                       rotate_s=None, fsync=False, threaded=False, reserve_bytes=0,
                       clock=lambda: float(next(clock)))
    block = 20_000
    for k in range(0, gyro.shape[0], block):
        t = start + (k + np.arange(min(block, gyro.shape[0] - k))) / fs
        channels = {f"gyro_{a}": gyro[k:k + block, i].copy() for i, a in enumerate("xyz")}
        channels |= {f"accel_{a}": acc[k:k + block, i].copy() for i, a in enumerate("xyz")}
        rec.write(SampleBlock("/adis/imu", t, channels, fs))
    rec.close()
    (path,) = out.glob("*.mcap")
    return str(path)


def test_the_four_line_cell_gives_analyze_json_numbers(adis_run1):
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["analyze", adis_run1, "--channel", "gyro_x", "--json"]) == 0
    (cli,) = json.loads(out.getvalue())["channels"].values()

    rec = imunoise.read(adis_run1)
    curve = imunoise.oadev(rec["gyro_x"])
    model = imunoise.fit(curve, "white,bias_instability,random_walk")
    dx = imunoise.diagnose(rec["gyro_x"], "white,bias_instability,random_walk")

    allan = curve.document()
    for key in ("tau_s", "adev", "ci_low", "ci_high", "edf"):
        assert allan[key] == cli["allan"][key], key
    fitted = model.document()
    for key in ("model", "error", "failures", "allan", "n_samples", "duration_s"):
        assert fitted[key] == cli[key], key
    assert dx.document()["model"] == cli["model"]
    # the real unit's white noise: the data sheet's typical 0.05 deg/s/sqrt(Hz) is its order
    n = model.params["white"]["N"] / DEG
    assert 0.02 < n < 0.1


def test_the_example_notebook_runs_and_keeps_its_plots(adis_run1, tmp_path):
    import nbclient
    import nbformat

    nb = nbformat.read(NOTEBOOK, as_version=4)
    (params,) = [c for c in nb.cells if "parameters" in c.metadata.get("tags", [])]
    params.source = f"path = {adis_run1!r}"
    nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}}).execute()
    executed = tmp_path / "python_api.executed.ipynb"
    nbformat.write(nb, executed)

    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    assert len(images) >= 4, f"{len(images)} plots in {executed}"
    # the executed copy holds them too (what a reader of the file sees)
    again = nbformat.read(executed, as_version=4)
    assert sum("image/png" in o.get("data", {}) for c in again.cells
               if c.cell_type == "code" for o in c.outputs) == len(images)


def test_the_notebook_in_the_repository_carries_no_outputs():
    """The example is kept clean: outputs only in executed copies."""
    import nbformat

    nb = nbformat.read(NOTEBOOK, as_version=4)
    assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code")
    assert Path(NOTEBOOK).stat().st_size < 20_000
