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

ROOT = Path(__file__).resolve().parent.parent


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
