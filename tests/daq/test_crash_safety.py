"""kill -9 and full-disk behaviour of the recorder, with real processes and file systems."""

import errno
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader

from imunoise.daq.readers import open_record
from imunoise.daq.recorder import McapRecorder, SyncedFile
from tests.mcap_helpers import make_blocks

ROOT = Path(__file__).resolve().parents[2]

# Live-paced recorder: 1 kHz in 20 ms blocks; prints the samples handed over after each block.
RECORDER_SCRIPT = """
import sys, time
import numpy as np
from imunoise.core.blocks import SampleBlock
from imunoise.daq.recorder import McapRecorder
fs, n = 1000.0, 20
rec = McapRecorder(sys.argv[1], "adis16350", rotate_s=None)
rng = np.random.default_rng(0)
k = 0
t0 = time.time()
while True:
    t = t0 + (k + np.arange(n)) / fs
    ch = {c: rng.normal(size=n) for c in ("gyro_x", "gyro_y", "gyro_z",
                                          "accel_x", "accel_y", "accel_z")}
    rec.write(SampleBlock("/adis16350/imu", t, ch, fs))
    k += n
    print(k, flush=True)
    delay = t0 + k / fs - time.time()
    if delay > 0:
        time.sleep(delay)
"""


def _kill_after(tmp_path: Path, seconds: float) -> tuple[int, Path]:
    script = tmp_path / "rec.py"
    script.write_text(RECORDER_SCRIPT)
    out = tmp_path / "out"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, str(script), str(out)], stdout=subprocess.PIPE,
                            text=True, env=env)
    handed = 0
    start = None
    try:
        for line in proc.stdout:
            handed = int(line)
            start = start or time.monotonic()
            if time.monotonic() - start >= seconds:
                proc.send_signal(signal.SIGKILL)  # right after this block was handed over
                break
    finally:
        proc.kill()
        proc.wait()
    (path,) = sorted(out.glob("*.mcap"))
    return handed, path


def test_kill_9_loses_at_most_the_last_second(tmp_path):
    handed, path = _kill_after(tmp_path, 2.6)
    record = open_record(path)
    got = record.channels["gyro_x"].n_samples
    lost_s = (handed - got) / 1000.0
    print(f"kill -9 after {handed} samples: {got} on disk, lost {lost_s:.3f} s")
    assert handed >= 2000
    assert 0 <= lost_s <= 1.0
    assert any("without a summary" in w or "truncated" in w for w in record.warnings)
    # what survives is exactly what was written: the first samples of the seeded stream
    rng = np.random.default_rng(0)
    first = rng.normal(size=20)
    assert np.array_equal(record.channels["gyro_x"].values[:20], first)


class _FullDisk(SyncedFile):
    """A file on a disk that holds only ``limit`` bytes (os.write fails with ENOSPC)."""

    limit = 200_000

    def write(self, data):
        if self.pos + len(data) > self.limit:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return super().write(data)


def _readable_everywhere(path: Path) -> int:
    """Message count, checked with our reader, mcap's indexed reader and rosbags."""
    n = open_record(path).channels["gyro_x"].n_samples
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        stats = reader.get_summary().statistics
        assert sum(1 for _ in reader.iter_messages()) == stats.message_count
    with AnyReader([path]) as ar:
        imu = [c for c in ar.connections if c.msgtype == "sensor_msgs/msg/Imu"]
        assert sum(c.msgcount for c in imu) == n
    return n


def test_full_disk_stops_with_message_and_leaves_indexed_file(tmp_path):
    rec = McapRecorder(tmp_path, "adis16350", threaded=False, fsync=False, rotate_s=None,
                       file_opener=_FullDisk)
    blocks = make_blocks(40, 500, fs=500.0)
    written = 0
    for b in blocks:
        rec.write(b)
        if rec.error:
            break
        written += len(b)
    assert rec.error and rec.error.startswith("disk full while writing")
    assert "complete and indexed" in rec.error
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    n = _readable_everywhere(path)
    assert 0 < n <= written
    assert not (tmp_path / ".imunoise-reserve").exists()


def _mount_tmpfs(where: Path, size: str) -> bool:
    if os.geteuid() != 0:
        return False
    where.mkdir()
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(where)],
                         capture_output=True)
    return res.returncode == 0


def test_full_tmpfs_disk_with_threaded_recorder(tmp_path):
    disk = tmp_path / "disk"
    if not _mount_tmpfs(disk, "1m"):
        pytest.skip("mounting a 1 MiB tmpfs needs root; the ENOSPC case is covered by "
                    "test_full_disk_stops_with_message_and_leaves_indexed_file")
    try:
        rec = McapRecorder(disk, "adis16350", rotate_s=None, reserve_bytes=128 << 10)
        for b in make_blocks(60, 1000, fs=1000.0, seed=3):
            rec.write(b)
            rec.flush()
            if rec.error:
                break
        assert rec.error is not None and rec.error.startswith("disk full"), rec.error
        rec.close()
        (path,) = disk.glob("*.mcap")
        n = _readable_everywhere(path)
        assert n >= 1000
        assert rec.stats.samples - n <= 1000  # at most the block that did not fit
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def test_no_room_for_the_reserve_is_refused_up_front(tmp_path):
    disk = tmp_path / "tiny"
    if not _mount_tmpfs(disk, "256k"):
        pytest.skip("mounting a tmpfs needs root")
    try:
        with pytest.raises(OSError, match="cannot write to .*tiny"):
            McapRecorder(disk, "adis16350")
        assert list(disk.iterdir()) == []
    finally:
        subprocess.run(["umount", str(disk)], check=False)
