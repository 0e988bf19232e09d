"""The wheel as a user gets it: built from the repository, installed with its base dependencies
(no extra) into a fresh virtual environment, used from a folder outside the repository.

It must hold one top-level package, ``imunoise``; the Python API must work there and give the
numbers of that install's own ``imunoise analyze --json``; the optional parts must say which
extra they need. pip fetches the dependencies from the package index (a minute or two).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import venv
import zipfile
from pathlib import Path

import numpy as np
import pytest

from tests.adis_recording import write_adis_run
from tests.shared_paths import REPO, SHARED_DATA

pytestmark = pytest.mark.slow

# The four lines of the notebook cell, then the numbers they give as JSON on stdout.
CELL = """
import json, sys
import imunoise
rec = imunoise.read(sys.argv[1])
curve = imunoise.oadev(rec["gyro_x"])
model = imunoise.fit(curve, "white,bias_instability,random_walk")
dx = imunoise.diagnose(rec["gyro_x"], "white,bias_instability,random_walk")
print(json.dumps({"allan": curve.document(), "fit": model.document(),
                  "diagnosis": dx.document()}))
"""


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w",
                    str(out), str(REPO)], check=True, timeout=600)
    (path,) = out.glob("imunoise-*.whl")
    return path


@pytest.fixture(scope="module")
def fresh(wheel, tmp_path_factory) -> Path:
    """A new virtual environment holding the wheel and its base dependencies only."""
    env = tmp_path_factory.mktemp("fresh") / "venv"
    venv.create(env, with_pip=True)
    python = env / "bin" / "python"
    subprocess.run([str(python), "-m", "pip", "install", "--quiet", str(wheel)], check=True,
                   timeout=1200)
    return env


def _run(env: Path, args: list[str], cwd: Path) -> subprocess.CompletedProcess[str]:
    clean = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    return subprocess.run(args, capture_output=True, text=True, cwd=cwd, env=clean,
                          timeout=600)


def test_the_wheel_holds_only_the_imunoise_package(wheel):
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        (top_level,) = [n for n in names if n.endswith(".dist-info/top_level.txt")]
        assert zf.read(top_level).decode().split() == ["imunoise"]
        (record,) = [n for n in names if n.endswith(".dist-info/RECORD")]
        paths = [line.split(",")[0] for line in zf.read(record).decode().splitlines() if line]
    tops = {p.split("/")[0] for p in paths}
    assert {t for t in tops if not t.endswith(".dist-info")} == {"imunoise"}
    for package in ("analysis", "core", "daq", "live", "fleet", "web", "pipeline", "export",
                    "api"):
        assert any(p.startswith(f"imunoise/{package}/") for p in paths), package
    assert any(p.startswith("imunoise/web/static/") for p in paths)


def _synthetic(folder: Path) -> Path:
    rng = np.random.default_rng(7)
    n = 60_000
    gyro = rng.normal(0.0, 0.01, n) + np.cumsum(rng.normal(0.0, 2e-5, n))
    path = folder / "imu.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / 100.0, gyro]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """ADIS16405 run 1 when ../shared is there, else a synthetic CSV."""
    folder = tmp_path_factory.mktemp("recording")
    if SHARED_DATA.is_dir():
        return write_adis_run(SHARED_DATA / "adis16405" / "run1.npz", folder)
    return _synthetic(folder)


def test_the_api_works_outside_the_repository_and_equals_analyze(fresh, recording, tmp_path):
    python = str(fresh / "bin" / "python")
    where = _run(fresh, [python, "-c", "import importlib.util, imunoise; "
                         "print(imunoise.__file__); "
                         "print(sorted(m for m in ('analysis', 'core', 'daq', 'web') "
                         "if importlib.util.find_spec(m)))"], tmp_path)
    assert where.returncode == 0, where.stderr
    location, bare = where.stdout.splitlines()
    assert str(fresh) in location and str(REPO) not in location
    assert bare == "[]"  # no top-level 'analysis', 'core' ... installed

    cell = _run(fresh, [python, "-c", CELL, str(recording)], tmp_path)
    assert cell.returncode == 0, cell.stderr
    api = json.loads(cell.stdout)
    cli = _run(fresh, [str(fresh / "bin" / "imunoise"), "analyze", str(recording),
                       "--channel", "gyro_x", "--json"], tmp_path)
    assert cli.returncode == 0, cli.stderr
    (channel,) = json.loads(cli.stdout)["channels"].values()
    for key in ("tau_s", "adev", "ci_low", "ci_high", "edf"):
        assert api["allan"][key] == channel["allan"][key], key
    for key in ("model", "failures", "allan"):
        assert api["fit"][key] == channel[key], key
    # the Allan and PSD parts of the error; analyze leaves hold-out and time domain to fit
    for key in ("chi2_per_dof", "max_abs_z", "psd"):
        assert api["fit"]["error"][key] == channel["error"][key], key
    assert api["diagnosis"]["model"] == channel["model"]


def test_the_base_install_names_the_extras_it_lacks(fresh, tmp_path):
    """Without the extras (a real absence here): a plot and the fleet command name theirs."""
    python = str(fresh / "bin" / "python")
    plot = _run(fresh, [python, "-c", "import numpy as np, imunoise; imunoise.oadev("
                        "np.random.default_rng(0).normal(size=4000), fs_hz=100.0).plot()"],
                tmp_path)
    assert plot.returncode == 1
    assert plot.stderr.strip().splitlines()[-1].endswith("pip install 'imunoise[plot]'")
    fleet = _run(fresh, [str(fresh / "bin" / "imunoise"), "fleet", str(tmp_path), "--catalog",
                         str(tmp_path / "cat")], tmp_path)
    assert fleet.returncode == 2
    assert len(fleet.stderr.strip().splitlines()) == 1
    assert "pip install 'imunoise[fleet]'" in fleet.stderr
