"""Damaged files never crash a command, and ``repair`` never writes a file other tools reject.

Regression tests for each way a damaged file used to crash (a corrupt zstd or lz4 chunk in the
middle of a file, 1e308 values and times in a CSV, a rosbag2 whose stamps never increase, a
huge line, broken or hostile ``metadata.yaml``, repair keeping a damaged chunk), then a seeded
mutation campaign over seed files of every format (``tests/fuzzing.py``; ``bench/fuzz.py``
runs thousands).
"""

from __future__ import annotations

import json
import mmap
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from imunoise.daq import mcap_layout as ml
from tests import fuzzing as fz


def _strict_json(text: str) -> dict:
    return json.loads(text, parse_constant=fz._reject_constant)


def _clean(outcome: fz.Outcome) -> None:
    assert outcome.problems() == [], outcome.problems()


def _chunks(path: Path) -> list[ml.ChunkInfo]:
    with open(path, "rb") as f:
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            return list(ml.scan(buf).chunks)
        finally:
            buf.close()


def _damage_middle_chunk(path: Path) -> ml.ChunkInfo:
    """Zero 64 bytes in the middle of the compressed records of a chunk in the middle."""
    chunks = _chunks(path)
    assert len(chunks) >= 4
    chunk = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    at = chunk.data_offset + chunk.data_length // 2
    data[at:at + 64] = bytes(64)
    path.write_bytes(bytes(data))
    return chunk


@pytest.fixture(scope="module")
def seeds(tmp_path_factory) -> dict[str, Path]:
    return fz.write_seeds(tmp_path_factory.mktemp("seeds"))


def _copy(seed: Path, tmp_path: Path) -> Path:
    import shutil

    if seed.is_dir():
        return Path(shutil.copytree(seed, tmp_path / seed.name))
    return Path(shutil.copy(seed, tmp_path / seed.name))


# ---- a damaged chunk in the middle: its messages are lost, the rest is analysed -------------

@pytest.mark.parametrize("fmt", ["mcap-zstd", "mcap-lz4", "mcap-imunoise", "mcap-none"])
def test_a_damaged_middle_chunk_is_a_gap_in_every_command(fmt, seeds, tmp_path):
    path = _copy(seeds[fmt], tmp_path) if fmt != "mcap-imunoise" else \
        fz.write_mcap_imunoise(tmp_path / "rec", fz.clean_signals())
    chunk = _damage_middle_chunk(path)
    out = fz.run_cli(["analyze", str(path), "--json", "--channel", "gyro_x"])
    _clean(out)
    assert out.code == 0
    doc = _strict_json(out.stdout)
    note = [w for w in doc["warnings"] if f"chunk at byte {chunk.start} is damaged" in w]
    assert note and "lost (a gap)" in note[0], doc["warnings"]
    n = doc["channels"]["gyro_x"]["n_samples"]
    assert 0 < n < fz.N_SAMPLES
    for argv in (["fit", str(path), "--channel", "gyro_x", "--model", "white", "--json"],
                 ["diagnose", str(path), "--channel", "gyro_x", "--model", "white", "--json"],
                 ["analyze", str(path), "--json", "--channel", "gyro_x", "--stream", "always"],
                 ["replay", str(path), "--speed", "max", "--json", "--no-progress"],
                 ["export-kalibr", str(path), "-o", str(tmp_path / "imu.yaml")]):
        result = fz.run_cli(argv)
        _clean(result)
        assert result.code == 0, (argv[0], result.stderr)
        if argv[0] != "export-kalibr":
            warned = [w for w in _strict_json(result.stdout)["warnings"] if "is damaged" in w]
            assert len(warned) == 1, (argv[0], warned)
    repaired = tmp_path / "fixed.mcap"
    result = fz.run_cli(["repair", str(path), "-o", str(repaired)])
    _clean(result)
    assert result.code == 0 and "1 damaged chunk(s) dropped" in result.stderr, result.stderr
    assert fz.check_repaired(repaired) is None
    fixed = fz.run_cli(["analyze", str(repaired), "--json", "--channel", "gyro_x"])
    assert _strict_json(fixed.stdout)["channels"]["gyro_x"]["n_samples"] == n


def test_a_damaged_record_length_skips_to_the_next_chunk_the_summary_lists(seeds, tmp_path):
    path = _copy(seeds["mcap-zstd"], tmp_path)
    chunks = _chunks(path)
    victim = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    data[victim.start + 1:victim.start + 9] = (2**63).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    out = fz.run_cli(["analyze", str(path), "--json", "--channel", "gyro_x"])
    _clean(out)
    doc = _strict_json(out.stdout)
    assert any(f"a damaged record at byte {victim.start}" in w for w in doc["warnings"])
    lost = sum(n for _p, n in victim.mi.values())
    assert doc["channels"]["gyro_x"]["n_samples"] == fz.N_SAMPLES - lost
    assert fz.run_cli(["repair", str(path), "-o", str(tmp_path / "out.mcap")]).code == 0
    assert fz.check_repaired(tmp_path / "out.mcap") is None


def test_fleet_reports_a_damaged_file_as_a_row(seeds, tmp_path):
    from imunoise.fleet_task import analyse_file

    path = _copy(seeds["mcap-zstd"], tmp_path)
    _damage_middle_chunk(path)
    outcome = analyse_file(str(path), version="test", diagnose=False)
    assert outcome.status == "ok" and outcome.rows
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(path.read_bytes()[:40])
    outcome = analyse_file(str(broken), version="test", diagnose=False)
    assert outcome.status == "failed" and "\n" not in outcome.rows[0]["error"]


# ---- repair never writes what other tools reject ------------------------------------------

def test_repair_of_a_complete_file_checks_its_chunks(seeds, tmp_path):
    """The old "already complete" shortcut copied a complete file whose middle chunk was
    damaged; the official reader then failed on the copy."""
    path = _copy(seeds["mcap-none"], tmp_path)
    chunks = _chunks(path)
    data = bytearray(path.read_bytes())
    at = chunks[1].data_offset + 100
    data[at:at + 8] = b"\xff" * 8  # inside a message: only the CRC tells
    path.write_bytes(bytes(data))
    out = fz.run_cli(["repair", str(path), "-o", str(tmp_path / "out.mcap")])
    _clean(out)
    assert "rebuilt" in out.stderr and "1 damaged chunk(s) dropped" in out.stderr
    assert fz.check_repaired(tmp_path / "out.mcap") is None


def test_repair_drops_a_tail_chunk_whose_records_are_misaligned(seeds, tmp_path):
    path = _copy(seeds["mcap-none"], tmp_path)
    last = _chunks(path)[-1]
    data = bytearray(path.read_bytes()[:last.end])  # crashed right after the last chunk
    data[last.data_offset + 1:last.data_offset + 9] = (10**6).to_bytes(8, "little")
    path.write_bytes(bytes(data))
    out = fz.run_cli(["repair", str(path), "-o", str(tmp_path / "out.mcap")])
    _clean(out)
    assert out.code == 0 and fz.check_repaired(tmp_path / "out.mcap") is None


def test_a_repaired_file_repairs_to_itself(seeds, tmp_path):
    path = _copy(seeds["mcap-lz4"], tmp_path)
    _damage_middle_chunk(path)
    assert fz.run_cli(["repair", str(path), "-o", str(tmp_path / "a.mcap")]).code == 0
    out = fz.run_cli(["repair", str(tmp_path / "a.mcap"), "-o", str(tmp_path / "b.mcap")])
    assert out.code == 0 and "already complete" in out.stderr
    assert (tmp_path / "a.mcap").read_bytes() == (tmp_path / "b.mcap").read_bytes()


# ---- values and times that are not finite or that overflow ---------------------------------

def test_csv_values_of_1e308_are_lost_samples(tmp_path):
    sig = fz.clean_signals()
    sig.gyro[[10, 200], 0] = [1e308, -1e308]
    sig.gyro[:, 1] = 1e308
    path = fz.write_csv(tmp_path / "huge.csv", sig)
    out = fz.run_cli(["analyze", str(path), "--json"])
    _clean(out)
    doc = _strict_json(out.stdout)
    assert doc["channels"]["gyro_x"]["n_samples"] == fz.N_SAMPLES - 2
    assert "gyro_y" not in doc["channels"]
    assert any("gyro_x: 2 missing or non-finite or beyond 1e+15" in w for w in doc["warnings"])


@pytest.mark.parametrize("bad_time", [1e308, -1e300, float("inf")])
def test_csv_times_of_1e308_drop_their_row(tmp_path, bad_time):
    sig = fz.clean_signals()
    sig.t_s = (sig.ns - fz.T0_NS) * 1e-9
    sig.t_s[123] = bad_time
    path = fz.write_csv(tmp_path / "times.csv", sig)
    out = fz.run_cli(["analyze", str(path), "--json", "--channel", "gyro_x"])
    _clean(out)
    doc = _strict_json(out.stdout)
    assert any("1 row(s) without a valid time" in w for w in doc["warnings"])
    assert doc["channels"]["gyro_x"]["n_samples"] == fz.N_SAMPLES - 1


def test_estimators_refuse_values_that_would_overflow():
    from imunoise.analysis.allan import oadev
    from imunoise.analysis.psd import log_psd

    x = np.random.default_rng(0).normal(size=1000)
    x[500] = 1e308
    with pytest.raises(ValueError, match="beyond"):
        oadev(x, 100.0)
    with pytest.raises(ValueError, match="beyond"):
        log_psd(x, 100.0)


def test_mcap_huge_values_are_lost_samples(tmp_path):
    sig = fz.clean_signals()
    sig.accel[50:60, 2] = 1.7e308
    path = fz.write_mcap_official(tmp_path / "huge.mcap", sig, "zstd")
    out = fz.run_cli(["analyze", str(path), "--json", "--channel", "accel_z"])
    _clean(out)
    doc = _strict_json(out.stdout)
    assert doc["channels"]["accel_z"]["n_samples"] == fz.N_SAMPLES - 10


# ---- time stamps that never increase -------------------------------------------------------

@pytest.mark.parametrize("fmt", ["rosbag2-sqlite3", "rosbag2-mcap", "mcap-zstd", "ros1", "csv"])
def test_stamps_that_never_increase_are_one_line(fmt, tmp_path):
    sig = fz.clean_signals()
    sig.ns[:] = sig.ns[0]
    path = fz.write_seed(fmt, tmp_path / "w", sig)
    out = fz.run_cli(["analyze", str(path), "--json"])
    _clean(out)
    assert out.code == 2 and "cannot infer a sampling rate" in out.stderr


def test_diagnose_of_a_record_too_short_for_a_term_exits_cleanly(tmp_path):
    """A truncated CSV (83 rows) left a candidate term without a starting shape: an
    AssertionError in the fit."""
    path = fz.write_csv(tmp_path / "short.csv", fz.clean_signals())
    path.write_bytes(path.read_bytes()[:11583])
    out = fz.run_cli(["diagnose", str(path), "--channel", "gyro_x", "--model", "white",
                      "--json"])
    _clean(out)


# ---- messages stay short -------------------------------------------------------------------

def test_a_huge_line_is_not_echoed(tmp_path):
    path = tmp_path / "line.csv"
    path.write_bytes(b"t,gyro_x\n" + b"1" * 2_000_000 + b",x,\n0,1\n")
    out = fz.run_cli(["analyze", str(path), "--json"])
    _clean(out)
    assert out.code == 2
    path.write_bytes(b"9" * 3_000_000)
    out = fz.run_cli(["analyze", str(path), "--json"])
    _clean(out)
    assert out.code == 2


def test_an_error_line_is_cut_to_300_characters(tmp_path):
    folder = tmp_path / ("d" * 200) / ("e" * 200)
    folder.mkdir(parents=True)
    path = folder / "x.csv"
    path.write_text("t,gyro_x\n0,abc\n")
    out = fz.run_cli(["analyze", str(path), "--json"])
    _clean(out)
    assert out.code == 2 and out.stderr.endswith("...\n")


# ---- rosbag2 metadata checked against the folder -------------------------------------------

def _edit_metadata(bag: Path, edit) -> None:
    meta = bag / "metadata.yaml"
    doc = yaml.safe_load(meta.read_text())
    edit(doc["rosbag2_bagfile_information"])
    meta.write_text(yaml.safe_dump(doc))


@pytest.mark.parametrize("target", ["../../../../etc/passwd", "/etc/passwd", "../x.db3",
                                    "sub/../../x.db3"])
def test_metadata_paths_must_stay_inside_the_bag(seeds, tmp_path, target):
    bag = _copy(seeds["rosbag2-sqlite3"], tmp_path)
    _edit_metadata(bag, lambda info: info.update(relative_file_paths=[target]))
    out = fz.run_cli(["analyze", str(bag), "--json"])
    _clean(out)
    assert out.code == 2 and ("outside the bag folder" in out.stderr
                              or "absolute path" in out.stderr), out.stderr


@pytest.mark.parametrize("fmt", ["rosbag2-sqlite3", "rosbag2-mcap"])
def test_metadata_disagreeing_with_the_storage_is_a_warning(seeds, tmp_path, fmt):
    bag = _copy(seeds[fmt], tmp_path)

    def edit(info):
        info["relative_file_paths"].append("lost_1.db3")
        info["message_count"] = 10**20
        info["duration"] = {"nanoseconds": -5}

    _edit_metadata(bag, edit)
    out = fz.run_cli(["analyze", str(bag), "--json", "--channel", "gyro_x"])
    _clean(out)
    doc = _strict_json(out.stdout)
    assert doc["channels"]["gyro_x"]["n_samples"] == fz.N_SAMPLES
    assert any("do not exist" in w for w in doc["warnings"]), doc["warnings"]
    _edit_metadata(bag, lambda info: info["relative_file_paths"].pop())
    doc = _strict_json(fz.run_cli(["analyze", str(bag), "--json", "--channel", "gyro_x"]).stdout)
    assert any("says 1e+20 messages" in w for w in doc["warnings"]), doc["warnings"]
    assert any("says the bag lasts" in w for w in doc["warnings"]), doc["warnings"]


def test_broken_metadata_yaml_is_one_line(seeds, tmp_path):
    bag = _copy(seeds["rosbag2-mcap"], tmp_path)
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  a: [1, {\n  b: '\n")
    out = fz.run_cli(["analyze", str(bag), "--json"])
    _clean(out)
    assert out.code == 2 and "not valid YAML" in out.stderr


# ---- the fuzzing campaign ------------------------------------------------------------------

PER_FORMAT = 20  # 12 formats: 240 mutants


def test_mutants_of_every_format_exit_cleanly(tmp_path):
    """Seeded mutants of every seed: each command exits 0 with strict JSON or 2 with one
    short line, with no Python warning, in bounded processor time (a mutant that sends a
    reader round a loop, or after a size it claims, shows there; the wall time also shows
    what else the machine runs); every MCAP file repair accepts reads in the official reader
    with CRC validation and in rosbags."""
    problems: list[str] = []
    counts: dict[str, int] = {}
    for case in fz.iter_cases(tmp_path, PER_FORMAT, seed=20261128):
        counts[case.fmt] = counts.get(case.fmt, 0) + 1
        for argv in fz.commands_for(case, tmp_path):
            out = fz.run_cli(argv)
            found = out.problems()
            if out.cpu_seconds > 10:
                found.append(f"took {out.cpu_seconds:.1f} s of processor time")
            if argv[0] == "repair" and out.code == 0:
                bad = fz.check_repaired(Path(argv[-1]))
                if bad:
                    found.append(f"repaired file unreadable: {bad}")
            problems += [f"{case.fmt} [{case.mutation}] {argv[0]}: {p}" for p in found]
    assert set(counts) == set(fz.FORMATS) and min(counts.values()) == PER_FORMAT
    assert problems == [], "\n".join(problems[:10])


# ---- the real exit path --------------------------------------------------------------------

def test_the_command_line_process_exits_2_with_one_line(seeds, tmp_path):
    bag = _copy(seeds["rosbag2-mcap"], tmp_path)
    _edit_metadata(bag, lambda info: info.update(relative_file_paths=["../../../etc/passwd"]))
    damaged = _copy(seeds["mcap-zstd"], tmp_path)
    _damage_middle_chunk(damaged)
    run = subprocess.run([sys.executable, "-m", "imunoise", "analyze", str(bag), "--json"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.count("\n") == 1 and len(run.stderr) < fz.MAX_MESSAGE
    run = subprocess.run([sys.executable, "-m", "imunoise", "analyze", str(damaged), "--json",
                          "--channel", "gyro_x"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stderr == ""
    assert "is damaged" in " ".join(_strict_json(run.stdout)["warnings"])
