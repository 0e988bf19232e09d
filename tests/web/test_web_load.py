"""Load and faults on loopback while a simulated 1 kHz device records."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import httpx
import numpy as np

from imunoise.live.service import LiveService
from imunoise.web.app import create_app
from tests.live_helpers import free_port, running_server, wait_until

TESTS = Path(__file__).resolve().parent.parent
CLIENTS = 50
REQUESTS = 2000
PATHS = ["/health", "/coefficients", "/allan?channel=gyro_x", "/psd?channel=gyro_y",
         "/diagnosis?channel=gyro_x", "/model?channel=gyro_y"]


async def _client(port: int, paths: list[str], latencies: list[float],
                  statuses: list[int]) -> None:
    """One keep-alive HTTP/1.1 connection issuing ``paths`` in turn.

    A minimal asyncio client: httpx's async pool costs more CPU per request than the server
    under test, which would make the figure measure the client.
    """
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        for path in paths:
            t0 = time.perf_counter()
            writer.write(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode())
            await writer.drain()
            head = (await reader.readuntil(b"\r\n\r\n")).decode("latin-1").split("\r\n")
            length = next(int(h.split(":", 1)[1]) for h in head
                          if h.lower().startswith("content-length:"))
            body = await reader.readexactly(length)
            latencies.append(time.perf_counter() - t0)
            status = int(head[0].split()[1])
            if status == 200:
                json.loads(body)  # a complete JSON document
            statuses.append(status)
    finally:
        writer.close()


async def _hammer(port: int) -> tuple[list[float], list[int]]:
    latencies: list[float] = []
    statuses: list[int] = []
    per_client = REQUESTS // CLIENTS
    await asyncio.gather(*(
        _client(port, [PATHS[(k + i) % len(PATHS)] for i in range(per_client)], latencies,
                statuses) for k in range(CLIENTS)))
    return latencies, statuses


def test_load_50_clients_2000_requests_while_recording_1khz_drops_nothing() -> None:
    port = free_port()
    proc = subprocess.Popen([sys.executable, str(TESTS / "serve_synthetic.py"), str(port), "1000"],
                            stdout=subprocess.PIPE, text=True, cwd=TESTS.parent)
    try:
        assert proc.stdout.readline().strip() == "ready"
        base = f"http://127.0.0.1:{port}"
        assert wait_until(lambda: len(httpx.get(base + "/channels").json()["channels"]) == 2)
        time.sleep(1.0)  # a first fit
        t0 = time.perf_counter()
        latencies, statuses = asyncio.run(_hammer(port))
        wall = time.perf_counter() - t0
        health = httpx.get(base + "/health").json()
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30)
    final = json.loads(out.strip().splitlines()[-1])
    lat = np.array(latencies) * 1e3
    p50, p99 = np.percentile(lat, [50, 99])
    print(f"\nload: {len(lat)} requests from {CLIENTS} clients in {wall:.1f} s "
          f"({len(lat) / wall:.0f} req/s); latency p50 {p50:.1f} ms, p99 {p99:.1f} ms, "
          f"max {lat.max():.1f} ms; 1 kHz source: {final['source_samples']} samples, "
          f"worst lateness {final['max_late_s'] * 1e3:.1f} ms")
    assert len(statuses) == REQUESTS and set(statuses) == {200}
    assert health["samples"]["dropped"] == 0 and health["samples"]["not_analysed"] == 0
    # Zero samples dropped: everything the device produced reached the recorder and analyzer.
    assert final["sink_closed"]
    assert final["sink_samples"] == final["source_samples"] == final["received"]
    assert final["analysed"] == final["received"] and final["not_analysed"] == 0
    assert final["source_samples"] >= 1000 * wall
    # The acquisition thread never fell behind by more than the recorder's 1 s flush window.
    assert final["max_late_s"] < 1.0


def test_unplug_and_replug_of_a_simulated_adis_shows_in_health_and_recording_goes_on(
        tmp_path: Path) -> None:
    """The real driver, pyserial, Bus Pirate emulator and MCAP recorder behind the service."""
    from mcap.reader import make_reader

    from imunoise.daq.devices import open_device
    from imunoise.daq.recorder import McapRecorder
    from imunoise.live.recorder_sink import RecorderSink

    acq = open_device("sim:adis16350", rate_hz=102.4, seed=3, timeout_s=0.1)
    acq.open()
    rec = McapRecorder(tmp_path, "sim:adis16350", config=acq.config, fsync=False)
    svc = LiveService(acq, sinks=[RecorderSink(rec, acq)], device={"spec": "sim:adis16350"},
                      current_file=lambda: rec.stats.file or None).start()
    states: list[str] = []

    def health(c: httpx.Client) -> dict:
        h = c.get("/health").json()
        states.append(h["device"]["state"])
        return h

    try:
        with running_server(create_app(svc)) as base, httpx.Client(base_url=base) as c:
            assert wait_until(lambda: health(c)["samples"]["received"] > 100)
            h = health(c)
            assert h["device"]["state"] == "running" and h["device"]["stats"]["reconnects"] == 0
            assert h["recording"]["file"].startswith(str(tmp_path))
            acq.simulator.emulator.unplug()
            assert wait_until(lambda: health(c)["device"]["state"] == "reconnecting"), states
            before = health(c)["samples"]["received"]
            acq.simulator.emulator.replug()
            assert wait_until(lambda: health(c)["device"]["state"] == "running"
                               and health(c)["samples"]["received"] > before + 100), states
            h = health(c)
            assert h["device"]["stats"]["reconnects"] == 1
            assert h["gaps"] >= 1 and h["samples"]["dropped"] > 0
            assert h["device"]["stats"]["last_error"] != ""
            assert wait_until(lambda: c.get("/coefficients").json()["channels"]["gyro_x"]
                               ["segments"] >= 2)
    finally:
        svc.stop()
    # The file holds data from before and after the outage, and the state changes as events.
    with open(rec.stats.files[0], "rb") as f:
        reader = make_reader(f)
        topics = [ch.topic for _, ch, _ in reader.iter_messages()]
    assert topics.count("/adis16350/imu") == acq.stats.samples
    assert topics.count("/diagnostics") >= 2  # running -> reconnecting -> running
