"""The recorder in a process of its own: every block handed to it reaches the file, a stalled
recorder loses nothing while the feed holds and marks what it could not hold as a gap, a
killed recorder is replaced and the new file says why. Real processes, real files read back by
the project's reader and by the ``mcap`` library."""

from __future__ import annotations

import os
import re
import signal
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from imunoise.daq import ros2_msgs
from imunoise.daq.readers.mcap import open_mcap, read_mcap
from imunoise.live.recorder_process import RecorderProcess
from tests.mcap_helpers import make_blocks

SIZE, FS = 20, 100.0


def _recorder(out: Path, **kw) -> RecorderProcess:
    return RecorderProcess({"out_dir": str(out), "device": "sim:adis16350", "rate_hz": FS,
                            "software": "imunoise-test"}, "normal", **kw).start()


def _texts(path: Path) -> list[bytes]:
    with open(path, "rb") as f:
        return [m.data for _s, ch, m in make_reader(f).iter_messages()
                if ch.topic == "/diagnostics"]


def _wait(pred, limit_s: float = 30.0) -> None:
    deadline = time.monotonic() + limit_s
    while not pred():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_blocks_and_events_reach_the_file_in_order(tmp_path):
    blocks = make_blocks(40, SIZE, fs=FS)
    rec = _recorder(tmp_path)
    rec.event(ros2_msgs.OK, "first note", {"event": "test"}, t=float(blocks[0].t[0]))
    for b in blocks:
        rec.write(b)
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    assert open_mcap(path).layout.complete
    got = read_mcap(path)
    want = np.concatenate([b.channels["gyro_x"] for b in blocks])
    np.testing.assert_array_equal(got.channels["gyro_x"].values, want)
    assert rec.stats.samples == len(want) and rec.stats.files == [str(path)]
    assert rec.stats.lost_samples == 0 and rec.error is None
    assert any(b"first note" in t for t in _texts(path))


def test_a_stalled_recorder_loses_nothing_the_feed_holds_and_marks_the_rest_as_a_gap(
        tmp_path):
    blocks = make_blocks(80, SIZE, fs=FS)
    big, small = tmp_path / "big", tmp_path / "small"
    for out, feed_bytes in ((big, 8 << 20), (small, 64 << 10)):
        rec = _recorder(out, feed_bytes=feed_bytes)
        os.kill(rec.pid, signal.SIGSTOP)  # a recorder that cannot write for a while
        try:
            for b in blocks[:70]:
                rec.write(b)
            assert rec.stats.backlog_bytes > 0  # /health shows the recorder lagging
        finally:
            os.kill(rec.pid, signal.SIGCONT)
        _wait(lambda r=rec: r.stats.backlog_bytes == 0)
        for b in blocks[70:]:
            rec.write(b)
        rec.close()
        (path,) = out.glob("*.mcap")
        got = read_mcap(path)
        lost = rec.stats.lost_samples
        facts = got.facts["timing"]["/adis16350/imu"]
        if out == big:
            assert lost == 0 and got.channels["gyro_x"].n_samples == 80 * SIZE
            assert facts["missing_samples"] == 0
        else:
            # 64 kB hold about 20 of these blocks (3.2 kB pickled): most of the 70 did not fit
            assert 30 * SIZE <= lost <= 60 * SIZE and lost % SIZE == 0
            assert got.channels["gyro_x"].n_samples == 80 * SIZE - lost
            assert facts["missing_samples"] == lost  # the file knows exactly what is missing
            # marked as gaps, summing to what was lost (the feed may have dropped in more
            # than one run, each marked where it happened)
            marked = [int(m.group(1)) for t in _texts(path)
                      for m in [re.search(rb"gap: (\d+) samples missing", t)] if m]
            assert marked and sum(marked) == lost, marked


def test_a_killed_recorder_is_replaced_and_the_new_file_says_why(tmp_path):
    blocks = make_blocks(60, SIZE, fs=FS)
    rec = _recorder(tmp_path)
    try:
        for b in blocks[:30]:
            rec.write(b)
        # everything written and flushed (a flush at most every second)
        _wait(lambda: rec.stats.samples == 30 * SIZE)
        time.sleep(1.5)
        first_pid = rec.pid
        os.kill(first_pid, signal.SIGKILL)
        _wait(lambda: not rec._proc.is_alive())
        assert rec.error is not None and "recorder process ended" in rec.error
        for b in blocks[30:]:  # handed over while no recorder runs: the feed keeps them
            rec.write(b)
        # it lived less than restart_pause.QUICK_DEATH_S: replaced after 1 s, not at once
        assert not rec.check() and rec.restarts == 0
        _wait(rec.check, limit_s=5.0)
        assert rec.pid != first_pid and rec.restarts == 1
        assert not rec.check()  # the new one is alive
    finally:
        rec.close()
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) == 2 and rec.stats.files == [str(f) for f in files]
    killed, new = (read_mcap(f) for f in files)
    assert killed.channels["gyro_x"].n_samples == 30 * SIZE  # flushed before the kill
    assert new.channels["gyro_x"].n_samples == 30 * SIZE  # nothing the feed held was lost
    assert rec.stats.samples == 60 * SIZE
    assert open_mcap(files[1]).layout.complete
    assert any(b"recording restarted" in t and b"signal 9" in t for t in _texts(files[1]))


def test_a_recorder_that_cannot_write_says_why(tmp_path):
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    with pytest.raises(OSError, match="File exists|Not a directory"):
        _recorder(blocked)


def test_what_a_dead_recorder_left_in_the_feed_is_written_at_close(tmp_path):
    blocks = make_blocks(20, SIZE, fs=FS)
    rec = _recorder(tmp_path)
    try:
        os.kill(rec.pid, signal.SIGKILL)
        _wait(lambda: not rec._proc.is_alive())
        for b in blocks:
            rec.write(b)
    finally:
        rec.close()  # no check() before: close replaces the dead recorder itself
    (path,) = tmp_path.glob("*.mcap")  # the killed one had no block: no file
    assert read_mcap(path).channels["gyro_x"].n_samples == 20 * SIZE
    assert rec.restarts == 1 and open_mcap(path).layout.complete
