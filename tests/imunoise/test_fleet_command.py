"""``imunoise fleet`` on a real Dask scheduler and real workers, a worker killed mid-run.

Six simulated units, four nights each (MCAP files written by the recorder), one unit twice as
noisy as the others, and one corrupt file. The catalogue must end complete, the corrupt file a
failed row, the noisy unit the only outlier, and a second run must skip everything.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from imunoise.cli import main
from imunoise.daq.sim.fleet_units import SimUnit, write_recording
from imunoise.fleet.catalog import part_paths, read_catalog
from imunoise.fleet.view import fleet_summary
from imunoise.fleet_task import analyse_file, content_hash, unit_of
from tests.shared_paths import REPO

DASK = Path(sys.executable).parent / "dask"
NIGHTS = 4
SPREAD = (0.94, 1.0, 1.06, 0.97, 1.03)
"""Unit-to-unit spread of the noise density of the ordinary units."""
NOISY = "U5"


@pytest.fixture(scope="module")
def recordings(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fleet_recordings")
    units = [SimUnit(f"U{i}", n_gyro=3e-4 * s, n_accel=2e-3 * s) for i, s in enumerate(SPREAD)]
    units.append(SimUnit(NOISY, n_gyro=6e-4, n_accel=4e-3))
    for j, unit in enumerate(units):
        for night in range(NIGHTS):
            write_recording(out, unit, 1.76e9 + night * 86400 + j * 3600, 300,
                            seed=100 * j + night)
    (out / "U9_corrupt.mcap").write_bytes(b"\x89MCAP0\r\n" + os.urandom(5000))
    return out


def _wait(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(what)
        time.sleep(0.1)


def _fleet(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "imunoise", "fleet", *args],
                          capture_output=True, text=True, timeout=600, cwd=REPO)


@pytest.mark.slow
def test_fleet_on_a_dask_cluster_survives_a_killed_worker(recordings, tmp_path):
    from distributed import Client

    sched_file = tmp_path / "scheduler.json"
    catalog = tmp_path / "catalog"
    procs = [subprocess.Popen([str(DASK), "scheduler", "--scheduler-file", str(sched_file),
                               "--host", "127.0.0.1", "--port", "0", "--no-dashboard"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO)]
    try:
        _wait(sched_file.exists, 60, "scheduler did not start")
        _wait(lambda: "address" in json.loads(sched_file.read_text() or "{}"), 30,
              "scheduler file incomplete")
        address = json.loads(sched_file.read_text())["address"]
        for i in range(2):
            procs.append(subprocess.Popen(
                [str(DASK), "worker", address, "--nthreads", "1", "--no-nanny",
                 "--no-dashboard", "--host", "127.0.0.1", "--name", f"w{i}"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=REPO))
        with Client(address, timeout="30s") as watcher:
            _wait(lambda: len(watcher.scheduler_info()["workers"]) == 2, 60,
                  "workers did not join")
            fleet = subprocess.Popen(
                [sys.executable, "-m", "imunoise", "fleet", str(recordings), "--catalog",
                 str(catalog), "--scheduler", address, "--no-diagnose"],
                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
            def victim_busy() -> bool:  # worker w0 (procs[1]) is running a file
                info = watcher.scheduler_info()["workers"]
                busy = watcher.processing()
                return any(w.get("name") == "w0" and busy.get(addr) for addr, w in info.items())

            _wait(victim_busy, 120, "the worker never got a task")
            os.kill(procs[1].pid, signal.SIGKILL)
            killed_mid_run = fleet.poll() is None
            _out, err = fleet.communicate(timeout=600)
        assert fleet.returncode == 0, err[-2000:]
        assert killed_mid_run
    finally:
        for p in procs:
            p.kill()
            p.wait(10)

    files = sorted(str(p.resolve()) for p in recordings.glob("*.mcap"))
    assert len(files) == 6 * NIGHTS + 1
    table = read_catalog(catalog).to_pylist()
    by_file: dict[str, list[dict]] = {}
    for row in table:
        by_file.setdefault(row["file"], []).append(row)
    assert sorted(by_file) == files  # complete: every file, once
    corrupt = by_file[str((recordings / "U9_corrupt.mcap").resolve())]
    assert [r["status"] for r in corrupt] == ["failed"]
    assert "MCAP" in corrupt[0]["error"] and "\n" not in corrupt[0]["error"]
    for f, rows in by_file.items():
        if "corrupt" not in f:
            assert [r["status"] for r in rows] == ["ok"] * 6, f
            assert {r["unit"] for r in rows} == {Path(f).name.split("_")[0]}
    # the noisy unit, and only it, is an outlier in the white noise of every axis
    doc = fleet_summary(catalog)
    flagged = {(o["unit"], o["channel"]) for o in doc["outliers"] if o["coefficient"] == "N"}
    axes = {"gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"}
    assert flagged == {(NOISY, a) for a in axes}
    assert doc["files_failed"] == 1 and doc["files_ok"] == 6 * NIGHTS

    # a second run skips everything and writes nothing
    parts = part_paths(catalog)
    again = _fleet(str(recordings), "--catalog", str(catalog), "--no-diagnose")
    assert again.returncode == 0, again.stderr
    assert f"0 analysed, 0 failed, {len(files)} already in the catalogue" in again.stderr
    assert part_paths(catalog) == parts


def test_fleet_rows_carry_the_numbers_of_analyze(recordings, capsys):
    """One file analysed by the fleet task and by ``imunoise analyze --json``: the same N, B,
    K and intervals, chi2/dof, and the diagnosis ran."""
    path = sorted(recordings.glob("U1_*.mcap"))[0]
    out = analyse_file(str(path), version="test")
    assert out.status == "ok" and out.file_hash == content_hash(path)
    assert main(["analyze", str(path), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    rows = {r["channel"]: r for r in out.rows}
    assert set(rows) == set(doc["channels"])
    for name, ch in doc["channels"].items():
        row = rows[name]
        assert row["chi2_per_dof"] == ch["error"]["chi2_per_dof"]
        assert row["diagnosed"] is True and isinstance(row["significant_suggestions"], list)
        params = {p: (v, t["ci95"][p]) for t in ch["model"] for p, v in t["params"].items()}
        for coef in ("N", "B", "K"):
            value, (lo, hi) = params[coef]
            assert row[f"{coef}_hi95"] == hi
            if lo > 0:
                assert row[coef] == value and row[f"{coef}_lo95"] == lo
                assert row[f"{coef}_resolved"]
            else:  # an interval reaching zero is not exported as a measurement
                assert row[coef] is None and not row[f"{coef}_resolved"]
    n = rows["gyro_x"]
    assert n["N_conv"] == pytest.approx(n["N"] * 3437.7467707849396)
    assert (n["N_si_unit"], n["N_conv_unit"]) == ("rad/s/sqrt(Hz)", "deg/sqrt(h)")
    assert rows["accel_x"]["N_si_unit"] == "m/s^2/sqrt(Hz)"


def test_unit_identity_rules():
    assert unit_of("/bench/imu-A17/night3.mcap", {}, r"imu-(\w+)/") == ("A17", "pattern")
    assert unit_of("/x/n.mcap", {"config.unit_id": "U3"}, None) == ("U3", "metadata config.unit_id")
    assert unit_of("/x/n.mcap", {"serial": "S9"}, r"nomatch(\d)") == ("S9", "metadata serial")
    assert unit_of("/x/night1.mcap", {}, None) == ("night1", "file name")


def test_fleet_usage_errors(tmp_path, capsys):
    (tmp_path / "c").write_text("not a folder")
    (tmp_path / "a.csv").write_text("t,gyro_x\n0,1\n")
    for argv, message in [
            (["fleet", str(tmp_path / "*.mcap"), "--catalog", str(tmp_path / "d")],
             "no recording matches"),
            (["fleet", str(tmp_path / "a.csv"), "--catalog", str(tmp_path / "c")],
             "must be a folder"),
            (["fleet", str(tmp_path / "a.csv"), "--catalog", str(tmp_path / "d"),
              "--workers", "0"], "--workers must be at least 1"),
            (["fleet-report", str(tmp_path / "nothing"), "--json"], "no catalogue there")]:
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, err


def test_unreachable_scheduler_is_one_line(tmp_path, recordings):
    r = _fleet(str(next(recordings.glob("U0_*.mcap"))), "--catalog", str(tmp_path / "c"),
               "--scheduler", "tcp://127.0.0.1:9", "--connect-timeout", "2")
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].startswith("imunoise: fleet: cannot reach")
    assert "Traceback" not in r.stderr


def test_a_url_is_read_where_it_lies(recordings):
    """An fsspec URL (here the in-memory file system) is expanded by glob and analysed from a
    temporary copy on the worker, with the same hash and numbers as the local file."""
    import fsspec

    from imunoise.commands.fleet import expand_inputs

    local = sorted(recordings.glob("U2_*.mcap"))[0]
    fs = fsspec.filesystem("memory")
    fs.pipe("/fleet-test/night.mcap", local.read_bytes())
    (url,) = expand_inputs(["memory://fleet-test/*.mcap"])
    assert url.startswith("memory://") and url.endswith("/fleet-test/night.mcap")
    remote = analyse_file(url, version="t", diagnose=False)
    here = analyse_file(str(local), version="t", diagnose=False)
    assert remote.status == "ok" and remote.file_hash == here.file_hash
    assert [r["N"] for r in remote.rows] == [r["N"] for r in here.rows]
    assert remote.rows[0]["file"] == url and remote.rows[0]["file_size"] is None


def test_folder_recordings_hash_and_expand(tmp_path):
    """A rosbag2 folder is one recording whose hash covers its files' names and bytes."""
    from imunoise.commands.fleet import expand_inputs

    bag = tmp_path / "logs" / "run1"
    bag.mkdir(parents=True)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    (bag / "run1_0.mcap").write_bytes(b"abc")
    (tmp_path / "logs" / "other.csv").write_text("t,gyro_x\n")
    (tmp_path / "logs" / "notes.txt").write_text("x")
    found = expand_inputs([str(tmp_path / "logs")])
    assert found == [str(tmp_path / "logs" / "other.csv"), str(bag)]
    h1 = content_hash(bag)
    (bag / "run1_0.mcap").write_bytes(b"abd")
    assert content_hash(bag) != h1


def test_a_copied_file_is_known_by_its_hash(recordings, tmp_path):
    """The same bytes under another name are skipped on the worker, before any analysis."""
    import shutil

    original = sorted(recordings.glob("U3_*.mcap"))[0]
    copy = tmp_path / "renamed.mcap"
    shutil.copy(original, copy)
    out = analyse_file(str(copy), version="t", known_hashes=frozenset({content_hash(original)}))
    assert out.status == "skipped" and out.rows == []


class _CancellingClient:
    """A real Dask client whose submissions of one file the cluster "cancels" (as it does the
    tasks that depended on a worker which died) the first ``times`` times."""

    def __init__(self, client, victim: str, times: int) -> None:
        self._client, self.victim, self.left = client, victim, times

    def submit(self, fn, loc, **kwargs):
        fut = self._client.submit(fn, loc, **kwargs)
        if loc == self.victim and self.left > 0:
            self.left -= 1
            fut.cancel()
        return fut

    def __getattr__(self, name):
        return getattr(self._client, name)


@pytest.mark.parametrize("times, status", [(1, "ok"), (2, "failed")])
def test_a_task_the_cluster_cancels_is_run_once_more(recordings, tmp_path, times, status):
    """A cancelled task is no verdict on its file: it is submitted once more; a second
    cancellation is recorded as the file's failure, with the cluster's reason."""
    import argparse

    from distributed import Client, LocalCluster

    from imunoise.commands.fleet import _run_on, _Sink

    files = [str(p.resolve()) for p in sorted(recordings.glob("U1_*.mcap"))[:3]]
    victim = files[1]
    args = argparse.Namespace(unit=None, static=None, no_diagnose=True)
    sink = _Sink(str(tmp_path / "catalog"))
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      dashboard_address=None) as cluster, Client(cluster) as client:
        proxy = _CancellingClient(client, victim, times)
        counts = _run_on(proxy, files, args, frozenset(), sink)
    sink.flush()
    assert proxy.left == 0
    assert counts["ok"] == (3 if status == "ok" else 2)
    assert counts["failed"] == (0 if status == "ok" else 1)
    rows = {}
    for row in read_catalog(tmp_path / "catalog").to_pylist():
        rows.setdefault(row["file"], []).append(row)
    assert sorted(rows) == sorted(files)  # every file once: no row for the cancelled try
    assert {r["status"] for r in rows[victim]} == {status}
    if status == "failed":
        assert len(rows[victim]) == 1 and "Cancelled" in rows[victim][0]["error"]
    else:
        assert len(rows[victim]) == 6
