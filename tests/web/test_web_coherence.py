"""The coherence view of ``imunoise serve``: the ``/coherence`` endpoint and the dashboard's
coherence plot and matrix in real headless Debian Chromium (driven by Playwright as in
test_web_browser.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import httpx
import numpy as np
import pytest

from imunoise.core.blocks import SampleBlock
from imunoise.live.service import LiveService
from imunoise.web.app import create_app
from tests.analysis.bench_records import NAMES, bench_record
from tests.live_helpers import running_server
from tests.web.test_web_browser import ARGS, CHROMIUM, screenshot_on_failure

CHANNELS = ["gyro_x", "accel_x", "accel_y"]  # the rocking: gyro_x with accel_y at 1.5 Hz


def _blocks(n: int = 20000, size: int = 500):
    x, _ = bench_record(71, n=n)
    cols = {c: x[:, NAMES.index(c)] for c in CHANNELS}
    for a in range(0, n, size):
        yield SampleBlock("/bench/imu", np.arange(a, min(a + size, n)) / 100.0,
                          {c: v[a:a + size] for c, v in cols.items()}, 100.0)


@pytest.fixture(scope="module")
def url():
    svc = LiveService(_blocks(), realtime=False).start()
    assert svc.wait(120)
    svc.stop(timeout=120)
    with running_server(create_app(svc)) as base:
        yield base


def test_coherence_endpoint(url):
    doc = httpx.get(url + "/coherence", timeout=30).json()
    assert doc["ready"] and doc["stream"] == "/bench/imu"
    assert doc["channels"] == CHANNELS and len(doc["pairs"]) == 3
    k = doc["pairs"].index(["gyro_x", "accel_y"])
    j = int(np.argmin(np.abs(np.array(doc["f_hz"]) - 1.5)))
    assert doc["msc"][k][j] > doc["threshold_family"][j]
    assert doc["ci"]["low"][k][j] <= doc["msc"][k][j] <= doc["ci"]["high"][k][j]
    r = httpx.get(url + "/coherence", params={"stream": "/nope"}, timeout=30)
    assert r.status_code == 404 and "valid streams" in r.json()["detail"]
    assert "/coherence" in httpx.get(url + "/openapi.json", timeout=30).json()["paths"]


@pytest.mark.skipif(not Path(CHROMIUM).exists() and shutil.which("chromium") is None,
                    reason="Debian chromium is not installed (apt-get install -y chromium)")
def test_dashboard_draws_the_coherence_view(url, tmp_path):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM if Path(CHROMIUM).exists()
                                    else shutil.which("chromium"), args=ARGS)
        page = browser.new_page(viewport={"width": 1400, "height": 2200})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
        with screenshot_on_failure(page, tmp_path, "coherence"):
            page.goto(url + "/")
            page.wait_for_function("Number(document.body.dataset.renders || 0) >= 1",
                                   timeout=30000)
            page.wait_for_selector("#coherence-plot canvas", timeout=15000)
            plot = page.locator("#coherence-plot")
            assert int(plot.get_attribute("data-points") or 0) >= 20
            # three pairs and the threshold, on a log-frequency axis labelled by decades
            labels = page.evaluate("state.plots['coherence-plot'].series.map((s) => s.label)")
            assert "gyro_x–accel_y" in labels and "threshold" in labels
            ticks = page.evaluate("state.plots['coherence-plot'].axes[0]._values || []")
            assert any(t in ("1", "10") for t in ticks), ticks
            matrix = page.locator("#coherence-matrix")
            assert matrix.locator("tr").count() == 4  # header + three channels
            # gyro_x-accel_y (the rocking) and accel_x-accel_y (the bench line) are coherent
            assert int(matrix.get_attribute("data-coherent")) >= 2
            assert "segments of 1024 samples" in page.locator("#coherence-info").inner_text()
            assert errors == [], errors
        browser.close()


def _two_devices(n: int = 20000, size: int = 500):
    """The same bench seen by two devices that sample 0.37 of a period apart."""
    x, _ = bench_record(72, n=n)
    rng = np.random.default_rng(72)
    cols = {c: x[:, NAMES.index(c)] for c in CHANNELS}
    other = {c: v + 0.3 * np.std(v) * rng.standard_normal(n) for c, v in cols.items()}
    for a in range(0, n, size):
        stop = min(a + size, n)
        yield SampleBlock("/first/imu", np.arange(a, stop) / 100.0,
                          {c: v[a:stop] for c, v in cols.items()}, 100.0)
        yield SampleBlock("/second/imu", (np.arange(a, stop) + 0.37) / 100.0,
                          {c: v[a:stop] for c, v in other.items()}, 100.0)


@pytest.mark.skipif(not Path(CHROMIUM).exists() and shutil.which("chromium") is None,
                    reason="Debian chromium is not installed (apt-get install -y chromium)")
def test_dashboard_shows_the_coherence_across_devices(tmp_path):
    from playwright.sync_api import sync_playwright

    svc = LiveService(_two_devices(), realtime=False).start()
    assert svc.wait(120)
    svc.stop(timeout=120)
    with running_server(create_app(svc)) as base, sync_playwright() as p:
        doc = httpx.get(base + "/coherence", params={"stream": "devices"}, timeout=30).json()
        assert doc["ready"] and len(doc["channels"]) == 6, doc.get("reason")
        browser = p.chromium.launch(executable_path=CHROMIUM if Path(CHROMIUM).exists()
                                    else shutil.which("chromium"), args=ARGS)
        page = browser.new_page(viewport={"width": 1400, "height": 2200})
        with screenshot_on_failure(page, tmp_path, "coherence-devices"):
            page.goto(base + "/")
            page.wait_for_selector("#coherence-plot canvas", timeout=30000)
            assert page.locator("#coherence-info").inner_text().startswith("devices:")
            matrix = page.locator("#coherence-matrix")
            assert matrix.locator("tr").count() == 7  # header + three channels of each
            labels = page.evaluate("state.plots['coherence-plot'].series.map((s) => s.label)")
            assert "/first/imu:gyro_x–/second/imu:gyro_x" in labels
        browser.close()
