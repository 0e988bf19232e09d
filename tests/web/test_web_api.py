"""HTTP API against a real uvicorn server on 127.0.0.1 (httpx over the loopback)."""

from __future__ import annotations

import json
import math

import httpx
import pytest

from imunoise.analysis.fit import fit_allan
from imunoise.cli import main
from imunoise.live.service import LiveService
from imunoise.web.app import create_app
from tests.live_helpers import SINE_A, SINE_F, SyntheticImu, running_server

N_BLOCKS = 300  # of 1000 samples: 300,000 samples per channel at 100 Hz, 50 minutes


@pytest.fixture(scope="module")
def service():
    svc = LiveService(SyntheticImu(block=1000, n_blocks=N_BLOCKS), realtime=False).start()
    assert svc.wait(60)
    # joins the analysis thread after its final forced refit (slow on a loaded machine)
    svc.stop(timeout=180)
    return svc


@pytest.fixture(scope="module")
def url(service):
    with running_server(create_app(service)) as base:
        yield base


@pytest.fixture()
def client(url):
    with httpx.Client(base_url=url, timeout=10) as c:
        yield c


def _all_finite(xs) -> bool:
    return all(x is not None and math.isfinite(x) for x in xs)


def test_health_reports_device_counts_and_channels(client) -> None:
    h = client.get("/health").json()
    assert h["status"] == "ok"
    assert h["samples"] == {"received": N_BLOCKS * 1000, "analysed": N_BLOCKS * 1000,
                            "not_analysed": 0, "dropped": 0}
    assert h["channels"] == ["gyro_x", "gyro_y"]
    assert h["device"]["stats"]["samples"] == N_BLOCKS * 1000
    assert h["recording"]["file"] is None


def test_coefficients_have_units_intervals_and_record_length(client) -> None:
    c = client.get("/coefficients").json()
    assert c["samples_seen"] == 2 * N_BLOCKS * 1000
    assert c["record_length_s"] == pytest.approx(N_BLOCKS * 10)
    gy = c["channels"]["gyro_y"]
    assert [t["term"] for t in gy["model"]] == ["white", "bias_instability", "random_walk"]
    white = gy["model"][0]
    lo, hi = white["ci95"]["N"]
    assert lo <= 3e-3 <= hi
    assert white["units"]["N"] == "rad/s/sqrt(Hz)"
    assert white["conventional"]["N"]["units"] == "deg/sqrt(h)"
    assert math.isfinite(gy["error"]["chi2_per_dof"])
    # the PSD part beside the Allan's; the hold-out and time-domain parts say why they are absent
    assert gy["error"]["psd"]["bins"] > 10 and gy["error"]["psd"]["deviance_per_bin"] > 0
    assert gy["error"]["holdout"]["reason"] and gy["error"]["time_domain"]["reason"]


def test_allan_curve_with_band_model_terms_and_z(client) -> None:
    a = client.get("/allan", params={"channel": "gyro_y"}).json()
    n = len(a["tau_s"])
    assert n >= 12
    for key in ("adev", "ci_low", "ci_high", "model_adev", "z"):
        assert len(a[key]) == n and _all_finite(a[key]), key
    assert all(lo < v < hi for lo, v, hi in zip(a["ci_low"], a["adev"], a["ci_high"],
                                                 strict=True))
    assert set(a["terms"]) == {"white", "bias_instability", "random_walk"}
    # gyro_x carries a sinusoid the default model lacks: the z strip marks it.
    ax = client.get("/allan", params={"channel": "gyro_x"}).json()
    assert ax["failures"] and max(abs(z) for z in ax["z"]) > 3
    # the over-bounding model for a filter lies on or above the band and the model everywhere
    for curve in (a, ax):
        ob = curve["overbound"]
        assert len(ob["model_adev"]) == n and ob["N"] > 0 and ob["max_excess"] >= 0
        assert all(b >= max(hi, m) * (1 - 1e-6) for b, hi, m in
                   zip(ob["model_adev"], curve["ci_high"], curve["model_adev"], strict=True))


def test_psd_shows_the_line_and_the_model(client) -> None:
    p = client.get("/psd", params={"channel": "gyro_x"}).json()
    assert p["units"] == "(rad/s)^2/Hz"
    peak = p["f_hz"][max(range(len(p["psd"])), key=p["psd"].__getitem__)]
    # Within one Welch bin (fs / nperseg = 100 / 256 Hz) of the line.
    assert peak == pytest.approx(SINE_F, abs=100 / 256)
    assert _all_finite(p["model_psd"]) and len(p["model_psd"]) == len(p["f_hz"])
    assert _all_finite(p["z"]) and len(p["z"]) == len(p["f_hz"])


def test_diagnosis_then_add_the_suggestion_and_error_falls(client) -> None:
    d = client.get("/diagnosis", params={"channel": "gyro_x"}).json()
    top = d["suggestions"][0]
    assert top["term"] == "sinusoid" and top["significant"]
    assert top["params"]["A"] == pytest.approx(SINE_A, rel=0.1)
    # gyro_y is white noise and random walk: the default model leaves nothing significant
    dy = client.get("/diagnosis", params={"channel": "gyro_y"}).json()
    assert dy["suggestions"] and not [s for s in dy["suggestions"] if s["significant"]]
    m0 = client.get("/model", params={"channel": "gyro_x"}).json()
    assert "sinusoid" in m0["valid_terms"] and "temperature" not in m0["valid_terms"]
    # /diagnosis and /model give the error with every part, as /coefficients does: the
    # missing line shows in the PSD part; the hold-out and time-domain parts say why absent
    c0 = client.get("/coefficients").json()["channels"]["gyro_x"]
    assert d["error"] == m0["error"] == c0["error"]
    assert d["error"]["psd"]["deviance_per_bin"] > 3.0 and d["error"]["psd"]["bins"] > 10
    assert "not computed by the live service" in d["error"]["holdout"]["reason"]
    assert "not computed by the live service" in d["error"]["time_domain"]["reason"]
    # the Add button posts the suggestion's apply.model: the full model, the line's
    # frequency held where the spectrum put it
    assert top["apply"]["args"] == []
    assert top["apply"]["model"].startswith("white,bias_instability,random_walk,sinusoid:f=")
    r = client.post("/model", json={"channel": "gyro_x", "model": top["apply"]["model"]})
    assert r.status_code == 200, r.text
    change = r.json()
    assert change["error_before"]["chi2_per_dof"] == pytest.approx(d["error"]["chi2_per_dof"])
    assert change["error_after"]["chi2_per_dof"] < change["error_before"]["chi2_per_dof"] / 10
    # the reply's errors carry the PSD part too, both against the same spectrum: the line
    # modelled, it falls
    assert change["error_before"] == d["error"]
    assert change["error_after"]["psd"]["deviance_per_bin"] < \
        change["error_before"]["psd"]["deviance_per_bin"] / 2
    c = client.get("/coefficients").json()["channels"]["gyro_x"]
    assert c["error"] == change["error_after"]
    sine = next(t for t in c["model"] if t["term"] == "sinusoid")
    assert sine["params"]["f"] == pytest.approx(SINE_F, rel=0.01)  # Allan fit, octave taus
    assert sine["params"]["A"] == pytest.approx(SINE_A, rel=0.05)
    m = client.get("/model", params={"channel": "gyro_x"}).json()
    assert m["model"][-1] == top["apply"]["model"].split(",")[-1] and m["model_revision"] == 1
    assert [h["revision"] for h in m["history"]][-2:] == [0, 1]
    r = client.post("/model", json={"channel": "gyro_x", "remove": "sinusoid"})
    assert r.status_code == 200
    assert r.json()["error_after"]["chi2_per_dof"] == pytest.approx(
        change["error_before"]["chi2_per_dof"], rel=1e-9)


def test_refit_on_request_gives_the_profile_intervals_of_imunoise_fit(service, client) -> None:
    r = client.post("/refit", json={"channel": "gyro_y", "intervals": "profile"})
    assert r.status_code == 200, r.text
    live = r.json()
    assert live["intervals"] == "profile" and live["fitted_samples"] == N_BLOCKS * 1000
    ref = fit_allan(service.analyzers.get("gyro_y").curve(),
                    "white,bias_instability,random_walk")
    for got, want in zip(live["model"], ref.terms, strict=True):
        assert got["term"] == want.term
        for k, v in want.params.items():
            assert got["params"][k] == pytest.approx(v, rel=1e-6)
    assert client.post("/refit", json={"channel": "gyro_y", "intervals": "exact"}
                       ).status_code == 422
    assert client.get("/health").json()["analysis"]["cpu_budget"] == 0.3


@pytest.mark.parametrize(("method", "path", "body", "status", "message"), [
    ("get", "/allan?channel=gyro_q", None, 404, "valid channels: gyro_x, gyro_y"),
    ("get", "/psd?channel=../../etc/passwd", None, 404, "valid channels"),
    ("post", "/model", {"channel": "gyro_x", "add": "flicker"}, 400,
     "valid terms: white, quantization, bias_instability"),
    ("post", "/model", {"channel": "accel_z", "add": "white"}, 404, "valid channels"),
    ("post", "/model", {"channel": "gyro_x", "add": "white"}, 400, "already in the model"),
    ("post", "/model", {"channel": "gyro_x", "remove": "sinusoid"}, 400, "not in the model"),
    ("post", "/model", {"channel": "gyro_x", "add": "white", "remove": "white"}, 422,
     "exactly one of"),
    ("post", "/model", {"channel": "gyro_x", "path": "/etc/passwd"}, 422, "path"),
    ("post", "/model", {"channel": "gyro_x", "model": "white,flicker"}, 400,
     "valid terms: white, quantization"),
    ("post", "/model", {"channel": "gyro_x", "model": "white,temperature"}, 400,
     "temperature"),
    ("post", "/model", {"channel": "gyro_x", "model": "white", "add": "white"}, 422,
     "exactly one of"),
])
def test_bad_requests_get_4xx_with_a_reason(client, method, path, body, status, message) -> None:
    r = client.request(method.upper(), path, json=body)
    assert r.status_code == status, r.text
    assert message in r.text


def test_no_file_is_served_outside_the_static_folder(client) -> None:
    for path in ("/static/../app.py", "/static/%2e%2e/app.py", "/static/..%2fapp.py"):
        r = client.get(path)
        assert r.status_code == 404, path
    assert client.get("/static/vendor/uplot/LICENSE").status_code == 200


def test_foreign_host_header_is_refused_on_loopback(client) -> None:
    # A page on another site that rebinds its name to 127.0.0.1 sends its own Host header.
    assert client.get("/coefficients", headers={"Host": "evil.example"}).status_code == 400
    assert client.get("/coefficients", headers={"Host": "localhost:8000"}).status_code == 200


def test_openapi_documents_every_endpoint(client) -> None:
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    for p in ("/coefficients", "/allan", "/psd", "/diagnosis", "/model", "/health", "/events"):
        assert p in paths
    assert "post" in paths["/model"]


def test_event_stream_pushes_updates(client) -> None:
    with client.stream("GET", "/events") as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        lines = []
        for line in r.iter_lines():
            lines.append(line)
            if line.startswith("data:"):
                break
    assert "event: update" in lines
    payload = json.loads(lines[-1][5:])
    assert payload["channels"] == ["gyro_x", "gyro_y"]
    assert payload["samples"]["received"] == N_BLOCKS * 1000


def test_token_guards_changes_but_not_reads(service) -> None:
    with running_server(create_app(service, token="s3cret")) as base, \
            httpx.Client(base_url=base, timeout=10) as c:
        body = {"channel": "gyro_y", "add": "quantization"}
        assert c.get("/coefficients").status_code == 200
        r = c.post("/model", json=body)
        assert r.status_code == 401 and "token" in r.json()["detail"]
        assert c.post("/model", json=body,
                      headers={"Authorization": "Bearer wrong"}).status_code == 401
        r = c.post("/model", json=body, headers={"Authorization": "Bearer s3cret"})
        assert r.status_code == 200
        r = c.post("/model", json={"channel": "gyro_y", "remove": "quantization"},
                   headers={"X-Imunoise-Token": "s3cret"})
        assert r.status_code == 200


@pytest.mark.parametrize(("argv", "message"), [
    (["serve", "--host", "0.0.0.0"], "give --token T or set IMUNOISE_TOKEN"),
    (["serve", "--model", "white,flicker"], "valid terms"),
    (["serve", "--device", "adis99"], "unknown device 'adis99'"),
    (["serve", "--replay", "/nonexistent/night.mcap"], "no such file"),
    (["serve", "--port", "70000"], "bad port"),
])
def test_serve_usage_errors_are_one_line_exit_2(argv, message, capsys, monkeypatch) -> None:
    monkeypatch.delenv("IMUNOISE_TOKEN", raising=False)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err
