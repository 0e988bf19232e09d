"""Bad input gives one line on stderr and exit code 2, never a traceback."""

import os

import numpy as np
import pytest
from mcap.writer import Writer

from imunoise.cli import main
from imunoise.daq import ros2_msgs as m
from imunoise.daq.readers import ReadError, open_record
from tests.mcap_helpers import make_blocks, record_blocks


def _bad_inputs(tmp_path):
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    rand = tmp_path / "random.mcap"
    rand.write_bytes(np.random.default_rng(0).bytes(5000))
    notbag = tmp_path / "notabag"
    notbag.mkdir()
    (notbag / "readme.txt").write_text("hello")
    header_only = tmp_path / "header_only.mcap"
    with open(header_only, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="x")
        w.finish()
    other = tmp_path / "other_types.mcap"
    with open(other, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="x")
        sid = w.register_schema("std_msgs/msg/String", "ros2msg", b"string data\n")
        cid = w.register_channel("/chatter", "cdr", sid)
        w.add_message(cid, 1, b"\x00\x01\x00\x00\x03\x00\x00\x00hi\x00", 1)
        w.finish()
    magic_garbage = tmp_path / "magic_garbage.mcap"
    magic_garbage.write_bytes(b"\x89MCAP0\r\n" + b"\x01" + b"\xff" * 8 + b"junk")
    return {"empty file": empty, "random bytes": rand, "not a bag": notbag,
            "missing file": tmp_path / "missing.mcap", "no messages": header_only,
            "no Imu topic": other, "garbage after magic": magic_garbage}


CASES = ["empty file", "random bytes", "not a bag", "missing file", "no messages",
         "no Imu topic", "garbage after magic"]


@pytest.mark.parametrize("case", CASES)
def test_open_record_raises_one_line_input_error(tmp_path, case):
    path = _bad_inputs(tmp_path)[case]
    with pytest.raises(ReadError) as err:
        open_record(path)
    msg = str(err.value)
    assert "\n" not in msg and path.name in msg


@pytest.mark.parametrize("case", CASES)
def test_replay_and_repair_exit_2_with_one_line(tmp_path, capsys, case):
    path = _bad_inputs(tmp_path)[case]
    before = sorted(os.listdir(tmp_path))
    assert main(["replay", str(path), "--speed", "max"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("imunoise: replay:"), err
    if case not in ("no messages", "no Imu topic"):  # those two are valid MCAP files
        assert main(["repair", str(path)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("imunoise: repair:"), err
        assert sorted(os.listdir(tmp_path)) == before  # nothing written half-way


@pytest.mark.parametrize("argv,needle", [
    (["record", "--device", "sim:adis16350", "--out", "x", "--duration", "ten"], "duration"),
    (["record", "--device", "sim:adis16350", "--out", "x", "--rate", "-5"], "rate"),
    (["record", "--device", "sim:adis16350"], "--out"),
    (["replay", "f.mcap", "--speed", "fast"], "speed"),
    (["repair", "a.mcap", "-o", "b.mcap", "--in-place"], "no such file"),
])
def test_bad_options_exit_2(tmp_path, capsys, monkeypatch, argv, needle):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0]


def test_nan_values_are_a_warned_recovery_not_an_error(tmp_path, capsys):
    blocks = make_blocks(2, 200)
    blocks[1].channels["gyro_x"][[3, 4]] = np.nan
    rec = record_blocks(tmp_path, blocks)
    assert main(["replay", rec.stats.files[0], "--speed", "max", "--json"]) == 0
    out = capsys.readouterr().out
    assert '"gyro_x"' in out or "gyro_x" in out
    r = open_record(rec.stats.files[0])
    assert r.channels["gyro_x"].n_samples == 398
    assert any("non-finite" in w for w in r.warnings)


def test_repair_writes_clean_copy_and_in_place(tmp_path, capsys):
    rec = record_blocks(tmp_path, make_blocks(6, 100))
    path = rec.stats.files[0]
    data = open(path, "rb").read()
    cut = tmp_path / "crashed.mcap"
    cut.write_bytes(data[:int(len(data) * 0.6)])
    assert main(["repair", str(cut)]) == 0
    assert "finished in place" in capsys.readouterr().err
    fixed = tmp_path / "crashed.repaired.mcap"
    r = open_record(fixed)
    assert r.warnings == [] and r.channels["gyro_x"].n_samples > 0
    assert main(["repair", str(cut), "--in-place"]) == 0
    assert open(cut, "rb").read() == open(fixed, "rb").read()
    assert main(["repair", str(cut)]) == 0
    assert "already complete" in capsys.readouterr().err


def test_schema_text_only_needed_by_name(tmp_path):
    """Topics are chosen by schema name: an empty schema text (rosbag2 without .msg files)
    still reads through the bulk reader."""
    path = tmp_path / "noschema.mcap"
    t = np.arange(100) / 10.0
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="x")
        sid = w.register_schema(m.IMU, "", b"")
        cid = w.register_channel("/imu", "cdr", sid)
        rec = m.encode_imu(t, np.ones((100, 3)), np.zeros((100, 3)))
        for i in range(100):
            w.add_message(cid, int(t[i] * 1e9), rec[i].tobytes(), 0, i)
        w.finish()
    assert open_record(path).channels["gyro_z"].n_samples == 100
