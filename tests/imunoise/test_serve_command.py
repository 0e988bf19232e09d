"""`imunoise serve` end to end, as `make run` starts it: a real process, the simulated ADIS16350,
MCAP recording, HTTP on 127.0.0.1, and Ctrl-C."""

from __future__ import annotations

import contextlib
import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
from mcap.reader import make_reader

from tests.live_helpers import free_port, interrupt

ROOT = Path(__file__).resolve().parents[2]


def test_serve_answers_coefficients_within_a_minute_and_ctrl_c_closes_the_file(
        tmp_path: Path) -> None:
    port = free_port()
    out = tmp_path / "data"
    proc = subprocess.Popen(
        [sys.executable, "-m", "imunoise", "serve", "--device", "sim:adis16350", "--out",
         str(out), "--port", str(port), "--refit-interval", "1"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    base = f"http://127.0.0.1:{port}"
    t0 = time.monotonic()
    coefficients = None
    try:
        while time.monotonic() - t0 < 60 and proc.poll() is None:
            try:
                c = httpx.get(base + "/coefficients", timeout=5).json()
            except httpx.HTTPError:
                c = None
            if c and c["channels"] and all(ch["error"] for ch in c["channels"].values()):
                coefficients = c
                break
            time.sleep(0.5)
        assert coefficients is not None, "no fitted coefficients within a minute"
        for name, ch in coefficients["channels"].items():
            values = [v for t in ch["model"] for v in t["params"].values()]
            assert values and all(math.isfinite(v) for v in values), name
        assert set(coefficients["channels"]) == {"gyro_x", "gyro_y", "gyro_z",
                                                 "accel_x", "accel_y", "accel_z"}
        health = httpx.get(base + "/health", timeout=5).json()
        assert health["device"]["state"] == "running"
        written = health["recording"]["file"]
        assert written and Path(written).parent == out
        # A dashboard stays connected to the event stream while the user presses Ctrl-C.
        events_seen = threading.Event()

        def listen() -> None:
            with contextlib.suppress(httpx.HTTPError), httpx.stream(
                    "GET", base + "/events", timeout=30) as response:
                for line in response.iter_lines():
                    if line.startswith("event: update"):
                        events_seen.set()

        listener = threading.Thread(target=listen, daemon=True)
        listener.start()
        assert events_seen.wait(20), "no update event on /events"
    finally:
        t_stop = time.monotonic()
        err = interrupt(proc)
    assert proc.returncode == 0, err
    assert "Traceback" not in err and "graceful shutdown exceeded" not in err, err
    assert time.monotonic() - t_stop < 15, "Ctrl-C with an open event stream took too long"
    listener.join(5)
    assert not listener.is_alive(), "the event stream stayed open after the server stopped"
    assert "recorded" in err
    # Closed cleanly: the file has its summary (a crashed file would not).
    with open(written, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    assert not (out / ".imunoise-reserve").exists()


def test_recorder_sink_records_an_outage_that_ended_between_two_blocks(tmp_path: Path) -> None:
    """The device state is sampled when blocks arrive: an outage that began and ended between
    two blocks still lands in the file as reconnecting -> running, from the reconnect count."""
    from types import SimpleNamespace

    import numpy as np

    from imunoise.core.blocks import SampleBlock
    from imunoise.daq.recorder import McapRecorder
    from imunoise.live.recorder_sink import RecorderSink

    stats = SimpleNamespace(state="running", reconnects=0, last_error="")
    rec = McapRecorder(tmp_path, "test", rate_hz=100.0, fsync=False, threaded=False)
    sink = RecorderSink(rec, SimpleNamespace(stats=stats))

    def block(k: int) -> SampleBlock:
        t = (np.arange(100) + 100 * k) / 100.0
        return SampleBlock(stream="/test/imu", t=t, fs_hz=100.0,
                           channels={"gyro_x": np.zeros(100)})

    sink.write(block(0))
    stats.reconnects, stats.last_error = 1, "no answer"
    sink.write(block(2))  # one block lost; state already back to running
    sink.write(block(3))
    sink.close()
    with open(rec.stats.files[0], "rb") as f:
        texts = [m.data for _, ch, m in make_reader(f).iter_messages()
                 if ch.topic == "/diagnostics"]
    joined = b"".join(texts)
    assert b"device state: reconnecting (no answer)" in joined
    assert b"device state: running" in joined
    assert joined.count(b"device state:") == 2
