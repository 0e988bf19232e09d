"""``/fleet`` on the real HTTP server: the page, the JSON, and 404 without a catalogue."""

from __future__ import annotations

from datetime import UTC, datetime

import httpx
import pytest

from imunoise.fleet.catalog import write_part
from imunoise.live.service import LiveService
from imunoise.web.app import create_app
from tests.live_helpers import SyntheticImu, running_server


def _rows() -> list[dict]:
    rows = []
    for k, factor in enumerate((1.0, 1.04, 0.96, 1.02, 0.98, 3.0)):
        n = 3e-4 * factor
        rows.append({"file": f"/d/u{k}.mcap", "file_hash": f"h{k}", "status": "ok",
                     "unit": f"U{k}", "sensor_model": "sim-imu", "channel": "gyro_x",
                     "kind": "gyro", "start_time": datetime(2026, 1, 1 + k, tzinfo=UTC),
                     "N": n, "N_lo95": 0.98 * n, "N_hi95": 1.02 * n, "N_resolved": True,
                     "B_resolved": False, "K_resolved": False})
    rows.append({"file": "/d/bad.mcap", "status": "failed", "error": "not an MCAP file"})
    return rows


@pytest.fixture(scope="module")
def service():
    svc = LiveService(SyntheticImu(block=100, n_blocks=20), realtime=False).start()
    assert svc.wait(60)
    svc.stop()
    return svc


def test_fleet_page_and_json(service, tmp_path):
    write_part(tmp_path, _rows())
    with running_server(create_app(service, catalog=str(tmp_path))) as base:
        page = httpx.get(f"{base}/fleet", timeout=30)
        assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
        assert "U5" in page.text and "<svg" in page.text and "not an MCAP file" in page.text
        for kwargs in ({"params": {"format": "json"}},
                       {"headers": {"Accept": "application/json"}}):
            doc = httpx.get(f"{base}/fleet", timeout=30, **kwargs).json()
            assert doc["files"] == 7 and doc["files_failed"] == 1
            assert [(o["unit"], o["coefficient"]) for o in doc["outliers"]] == [("U5", "N")]
        # a new part is seen on the next request
        write_part(tmp_path, [dict(_rows()[0], file="/d/late.mcap", file_hash="h9", unit="U9")])
        doc = httpx.get(f"{base}/fleet", params={"format": "json"}, timeout=30).json()
        assert doc["files"] == 8


def test_fleet_without_catalogue_is_404(service, tmp_path):
    with running_server(create_app(service)) as base:
        r = httpx.get(f"{base}/fleet", timeout=30)
        assert r.status_code == 404 and "--catalog" in r.json()["detail"]
    with running_server(create_app(service, catalog=str(tmp_path / "none"))) as base:
        assert httpx.get(f"{base}/fleet", timeout=30).status_code == 404


def test_fleet_without_the_fleet_extra_says_what_to_install(service, tmp_path, monkeypatch):
    """Without pyarrow (the ``fleet`` extra) the view is a 501 naming the pip line, not a
    traceback."""
    write_part(tmp_path, _rows())
    monkeypatch.setitem(__import__("sys").modules, "pyarrow", None)  # import pyarrow fails
    with running_server(create_app(service, catalog=str(tmp_path))) as base:
        r = httpx.get(f"{base}/fleet", params={"format": "json"}, timeout=30)
    assert r.status_code == 501
    assert "pip install 'imunoise[fleet]'" in r.json()["detail"]
