"""A command whose optional extra is not installed says in one line which extra to install
and exits with 2 (the real command line, with the extra's modules made unimportable)."""

from __future__ import annotations

import pytest

from tests.blocked_imports import run_without

PIP_FLEET = "pip install 'imunoise[fleet]'"


@pytest.mark.parametrize("blocked", [["dask"], ["distributed"], ["pyarrow"], ["fsspec"]])
def test_fleet_without_its_extra(tmp_path, blocked):
    rec = tmp_path / "r.csv"
    rec.write_text("t,gyro_x\n0,0\n0.01,0\n")
    out = run_without(blocked, ["-m", "imunoise", "fleet", str(rec), "--catalog",
                                str(tmp_path / "cat")], tmp_path)
    assert out.returncode == 2, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr
    assert PIP_FLEET in lines[0] and blocked[0] in lines[0]
    assert not (tmp_path / "cat").exists()


def test_fleet_report_without_pyarrow(tmp_path):
    (tmp_path / "cat").mkdir()
    out = run_without(["pyarrow"], ["-m", "imunoise", "fleet-report", str(tmp_path / "cat"),
                                    "--json"], tmp_path)
    assert out.returncode == 2, out.stderr
    assert out.stderr.strip().splitlines() == [
        "imunoise fleet-report needs the optional 'fleet' extra (pyarrow is not "
        f"installed): {PIP_FLEET}"]


def test_the_block_itself_works(tmp_path):
    """The subprocess really cannot import a blocked module (so the tests above can fail)."""
    out = run_without(["dask"], ["-c", "import dask"], tmp_path)
    assert out.returncode == 1 and "No module named 'dask'" in out.stderr
