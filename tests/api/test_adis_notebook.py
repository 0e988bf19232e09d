"""The Python API on a real recording: ADIS16405 run 1 (2.8 h at 100 Hz, ../shared) written
as an imunoise MCAP file. The four-line cell gives ``imunoise analyze --json``'s numbers, and
the example notebook runs and keeps its plots."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest

import imunoise
from imunoise.cli import main
from imunoise.core.units import DEG
from tests.adis_recording import write_adis_run
from tests.shared_paths import REPO

NOTEBOOK = REPO / "examples" / "python_api.ipynb"

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def adis_run1(shared_data, tmp_path_factory) -> str:
    return str(write_adis_run(shared_data / "adis16405" / "run1.npz",
                              tmp_path_factory.mktemp("adis_run1")))


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
    for key in ("model", "failures", "allan", "n_samples", "duration_s"):
        assert fitted[key] == cli[key], key
    # the Allan and PSD parts of the error; analyze leaves hold-out and time domain to fit
    for key in ("chi2_per_dof", "max_abs_z", "psd"):
        assert fitted["error"][key] == cli["error"][key], key
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
