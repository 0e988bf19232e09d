"""The Parquet catalogue: atomic parts, concurrent appends, what it has seen, readers."""

from __future__ import annotations

import multiprocessing
from datetime import UTC, datetime

import pyarrow.parquet as pq
import pytest

from imunoise.fleet.catalog import SCHEMA, CatalogError, part_paths, read_catalog, seen, write_part
from imunoise.fleet.view import LimitsError, fleet_summary, load_limits


def _row(file: str, unit: str = "U1", status: str = "ok", n: float = 1e-3, **kw) -> dict:
    row = {"file": file, "file_hash": f"h-{file}", "file_size": 10, "file_mtime_ns": 5,
           "status": status, "unit": unit, "sensor_model": "m", "channel": "gyro_x",
           "kind": "gyro", "start_time": datetime(2026, 1, 1, tzinfo=UTC),
           "N": n, "N_lo95": n * 0.95, "N_hi95": n * 1.05, "N_resolved": True,
           "B_resolved": False, "K_resolved": False, "significant_suggestions": ["sinusoid"]}
    if status == "failed":
        row = {"file": file, "file_hash": None, "file_size": 10, "file_mtime_ns": 5,
               "status": "failed", "error": "not an MCAP file (bad magic)"}
    row.update(kw)
    return row


def test_part_is_written_whole_with_the_schema(tmp_path):
    path = write_part(tmp_path, [_row("a.mcap"), _row("b.mcap", status="failed")])
    assert path is not None and path.name.startswith("part-")
    assert not list(tmp_path.glob(".*"))  # no temporary file left behind
    assert pq.read_schema(path).equals(SCHEMA)
    t = read_catalog(tmp_path)
    assert t.num_rows == 2 and t.column("N").to_pylist() == [1e-3, None]
    assert write_part(tmp_path, []) is None


def test_empty_and_bad_catalogue(tmp_path):
    assert read_catalog(tmp_path / "none").num_rows == 0
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(CatalogError, match="must be a folder"):
        read_catalog(f)


def _append(args: tuple[str, int]) -> None:
    folder, k = args
    for j in range(5):
        write_part(folder, [_row(f"w{k}-{j}-{i}.mcap") for i in range(50)])


def test_concurrent_appends_lose_nothing(tmp_path):
    """Four processes append at once: every row arrives, every part is readable."""
    with multiprocessing.get_context("spawn").Pool(4) as pool:
        pool.map(_append, [(str(tmp_path), k) for k in range(4)])
    assert len(part_paths(tmp_path)) == 20
    files = read_catalog(tmp_path, ["file"]).column("file").to_pylist()
    assert len(files) == len(set(files)) == 4 * 5 * 50


def test_seen_tells_hashes_stamps_and_failures(tmp_path):
    write_part(tmp_path, [_row("a.mcap"), _row("b.mcap", status="failed")])
    s = seen(tmp_path)
    assert s.hashes == {"h-a.mcap"}
    assert s.has_stamp("a.mcap", 10, 5) and s.has_stamp("b.mcap", 10, 5)
    assert not s.has_stamp("a.mcap", 11, 5)
    assert s.failed_files == {"b.mcap"}
    write_part(tmp_path, [_row("b.mcap")])  # analysed again, now fine
    assert seen(tmp_path).failed_files == frozenset()


def test_duckdb_and_pandas_read_the_catalogue(tmp_path):
    duckdb = pytest.importorskip("duckdb")
    pd = pytest.importorskip("pandas")
    write_part(tmp_path, [_row("a.mcap", n=2e-3), _row("b.mcap", n=4e-3)])
    write_part(tmp_path, [_row("c.mcap", status="failed")])
    (got,) = duckdb.sql(f"SELECT count(*), avg(N) FROM '{tmp_path}/*.parquet' "
                        "WHERE status = 'ok'").fetchall()
    assert got == (2, pytest.approx(3e-3))
    df = pd.read_parquet(tmp_path)
    assert sorted(df["status"]) == ["failed", "ok", "ok"]


def test_limits_file_units_and_errors(tmp_path):
    good = tmp_path / "limits.yaml"
    good.write_text('"*":\n  gyro:\n    N: {max: 0.3, unit: "deg/sqrt(h)"}\n'
                    "m:\n  gyro_x:\n    B: {max: 1.0e-4}\n")
    limits = load_limits(good)
    assert limits["*"]["gyro"]["N"]["max"] == pytest.approx(0.3 / 3437.7467707849396)
    assert limits["m"]["gyro_x"]["B"]["max"] == 1e-4
    for text, message in [("m:\n  gyro:\n    X: {max: 1}\n", "unknown coefficient"),
                          ("m:\n  gyro:\n    N: {max: 1, unit: furlong}\n", "furlong"),
                          ("m:\n  gyro:\n    N: {unit: deg/sqrt(h)}\n", "max and/or min"),
                          ("m:\n  wheel:\n    N: {max: 1}\n", "gyro, accel or a channel"),
                          ("[1, 2]\n", "expected a mapping")]:
        bad = tmp_path / "bad.yaml"
        bad.write_text(text)
        with pytest.raises(LimitsError, match=message):
            load_limits(bad)


def test_summary_verdicts_and_failed_files(tmp_path):
    write_part(tmp_path, [_row("a.mcap", n=1e-4), _row("b.mcap", unit="U2", n=1e-3),
                          _row("c.mcap", status="failed")])
    doc = fleet_summary(tmp_path, {"*": {"gyro": {"N": {"max": 5e-4}}}})
    verdicts = {r["file"]: r["verdict"] for r in doc["limits"]}
    assert verdicts == {"a.mcap": "pass", "b.mcap": "fail"}
    assert doc["failed"] == [{"file": "c.mcap", "error": "not an MCAP file (bad magic)"}]
    assert (doc["files"], doc["files_ok"], doc["files_failed"]) == (3, 2, 1)
    # two units are too few for an outlier test: nothing is flagged
    assert doc["outliers"] == []


def test_the_same_recording_twice_counts_once(tmp_path):
    """Two runs over the same file (or a copy): the view keeps the latest analysis only."""
    early = datetime(2026, 1, 1, tzinfo=UTC)
    late = datetime(2026, 2, 1, tzinfo=UTC)
    write_part(tmp_path, [_row("a.mcap", n=1e-3, analysed_at=early)])
    write_part(tmp_path, [_row("copy-of-a.mcap", n=2e-3, analysed_at=late,
                               file_hash="h-a.mcap")])
    doc = fleet_summary(tmp_path)
    (unit,) = doc["units"]
    assert unit["recordings"] == 1
    assert unit["coefficients"]["N"]["history"][0]["value"] == 2e-3
