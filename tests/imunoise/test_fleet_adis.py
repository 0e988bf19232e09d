"""Six nights of one real ADIS16405 as a fleet: pooled white noise with its interval, the
agreement test, and the fleet report in headless Chromium."""

from __future__ import annotations

import itertools
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from imunoise.analysis.fleet_stats import Z95, log_se
from imunoise.cli import main
from imunoise.core.blocks import SampleBlock
from imunoise.core.units import DEG, G0
from imunoise.daq.recorder import McapRecorder
from imunoise.fleet.catalog import read_catalog

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
UNIT = "ADIS16405-A"
DATASHEET_N_DPS = 0.05
"""deg/s/sqrt(Hz): the data sheet's typical gyro noise density (shared/data/README.md)."""


def _write_night(out: Path, run: int, npz: Path) -> None:
    d = np.load(npz)
    fs = float(d["fs_hz"])
    gyro = d["gyro_counts"] * float(d["gyro_scale_dps"]) * DEG
    acc = d["accel_counts"] * float(d["accel_scale_g"]) * G0
    start = 1.6e9 + run * 86400.0
    clock = itertools.count(start)
    rec = McapRecorder(out, f"adis16405_run{run}", config={"unit_id": UNIT,
                                                           "sensor_model": "adis16405"},
                       rate_hz=fs, rotate_s=None, fsync=False, threaded=False,
                       reserve_bytes=0, clock=lambda: float(next(clock)))
    block = 20000
    for k in range(0, gyro.shape[0], block):
        t = start + (k + np.arange(min(block, gyro.shape[0] - k))) / fs
        ch = {f"gyro_{a}": gyro[k:k + block, i].copy() for i, a in enumerate("xyz")}
        ch |= {f"accel_{a}": acc[k:k + block, i].copy() for i, a in enumerate("xyz")}
        rec.write(SampleBlock("/adis/imu", t, ch, fs))
    rec.close()


@pytest.fixture(scope="module")
def catalog(shared_data, tmp_path_factory) -> Path:
    nights = tmp_path_factory.mktemp("adis_nights")
    for run in range(1, 7):
        _write_night(nights, run, shared_data / "adis16405" / f"run{run}.npz")
    cat = tmp_path_factory.mktemp("adis_catalog")
    assert main(["fleet", str(nights), "--catalog", str(cat), "--workers", "2",
                 "--no-diagnose"]) == 0
    return cat


@pytest.fixture(scope="module")
def fleet_doc(catalog, tmp_path_factory) -> tuple[dict, Path]:
    out = tmp_path_factory.mktemp("adis_report") / "fleet.html"
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["fleet-report", str(catalog), "-o", str(out), "--json"]) == 0
    return json.loads(buf.getvalue()), out


@pytest.mark.slow
def test_six_nights_pooled_white_noise(catalog, fleet_doc):
    doc, _ = fleet_doc
    rows = [r for r in read_catalog(catalog).to_pylist() if r["status"] == "ok"]
    assert len(rows) == 36 and {r["unit"] for r in rows} == {UNIT}
    for axis in ("gyro_x", "gyro_y", "gyro_z"):
        (unit,) = [u for u in doc["units"] if u["channel"] == axis]
        n = unit["coefficients"]["N"]
        nights = np.array([h["value"] for h in n["history"]])
        lo = np.array([h["ci95"][0] for h in n["history"]])
        hi = np.array([h["ci95"][1] for h in n["history"]])
        assert nights.size == 6 and np.all(lo > 0)
        pooled = n["pooled"]
        # the unit's gyro white noise: near the data sheet's typical 0.05 deg/s/sqrt(Hz)
        assert 0.7 * DATASHEET_N_DPS < pooled["value"] / DEG < 1.0 * DATASHEET_N_DPS
        assert nights.min() < pooled["value"] < nights.max()
        assert pooled["ci95"][0] < np.median(nights) < pooled["ci95"][1]
        # Cochran's Q recomputed from the catalogue's own rows
        x, se = np.log(nights), log_se(lo, hi)
        w = 1 / se**2
        q = float(np.sum(w * (x - np.sum(w * x) / np.sum(w)) ** 2))
        assert pooled["cochran_q"] == pytest.approx(q, rel=1e-9)
        assert pooled["p_value"] == pytest.approx(stats.chi2.sf(q, 5), rel=1e-6, abs=1e-300)
        # the nights differ by more than the default model's intervals allow: said plainly,
        # and the pooled interval is widened to the night-to-night spread
        assert pooled["agree"] is False
        assert pooled["ci95"][1] - pooled["ci95"][0] > np.max(hi - lo)
        assert Z95 * pooled["between_runs_log_sd"] > 0.02


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install "
                    "chromium); the fleet report's rendering cannot be checked")
@pytest.mark.slow
def test_fleet_report_renders_in_headless_chromium(fleet_doc):
    from playwright.sync_api import sync_playwright

    _, page_path = fleet_doc
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=["--headless",
                                                                    "--no-sandbox"])
        page = browser.new_page(viewport={"width": 1200, "height": 1600})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(page_path.as_uri())
        text = page.inner_text("body")
        n_svg = page.locator("svg").count()
        circles = page.locator("svg circle").count()
        first = page.locator("svg").first.bounding_box()
        browser.close()
    assert not errors
    assert "6 recording(s): 6 analysed" in text and UNIT in text
    assert n_svg >= 6 * 3  # six channels x three coefficients, at least
    assert circles >= 6 * 3
    assert first is not None and first["width"] >= 300 and first["height"] >= 200
