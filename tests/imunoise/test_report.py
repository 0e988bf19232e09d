"""HTML report: parsed, self-contained, rendered by headless Chromium; the SVG plotter."""

from __future__ import annotations

import shutil
import struct
import subprocess
import zlib
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from imunoise.analysis.discrete import discretize
from imunoise.export.report_html import render_report
from imunoise.export.svg_plot import Plot

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


class _Collector(HTMLParser):
    """Tags, attributes and text of a document, checking that every element is closed."""

    VOID = {"meta", "br", "img", "input", "link", "hr", "col", "area", "base", "source", "wbr"}
    SVG_EMPTY = {"rect", "line", "polyline", "polygon", "circle", "path"}

    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.stack: list[str] = []
        self.text: list[str] = []
        self.errors: list[str] = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag not in self.VOID:
            self.stack.append(tag)

    def handle_startendtag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_endtag(self, tag):
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"unexpected </{tag}> with open {self.stack[-3:]}")
            return
        self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def _channel_doc(name: str, units: str, fs: float = 100.0) -> dict:
    n_, b_, k_ = (3e-4, 4e-5, 2e-6) if units == "rad/s" else (2e-3, 1e-4, 3e-5)
    tau = 2.0 ** np.arange(0, 17) / fs
    avar = n_**2 / tau + 2 * np.log(2) / np.pi * b_**2 + k_**2 * tau / 3
    adev = np.sqrt(avar) * (1 + 0.03 * np.sin(np.arange(tau.size)))
    half = 1.96 / np.sqrt(np.maximum(2 * (1e6 / (tau * fs)) / 3, 1.0))
    f = np.logspace(-3, np.log10(fs / 2), 60)
    psd = 2 * n_**2 + 2 * b_**2 / (np.pi * f) + k_**2 / (2 * np.pi**2 * f**2)
    model = [
        {"term": "white", "params": {"N": n_}, "ci95": {"N": [0.99 * n_, 1.01 * n_]}},
        {"term": "bias_instability", "params": {"B": b_}, "ci95": {"B": [0.8 * b_, 1.2 * b_]}},
        {"term": "random_walk", "params": {"K": k_}, "ci95": {"K": [0.5 * k_, 1.5 * k_]}},
    ]
    dm = discretize(model, fs, units, tau_range_s=(tau[0], tau[-1]))
    return {
        "channel": name, "units": units, "fs_hz": fs, "n_samples": 1_000_000,
        "duration_s": 1e4, "model": model,
        "error": {"chi2_per_dof": 3.7, "max_abs_z": 4.2},
        "failures": [{"tau_s": [0.16, 0.64], "max_abs_z": 4.2,
                      "direction": "measured above model"}],
        "allan": {"tau_s": tau.tolist(), "adev": adev.tolist(),
                  "ci_low": (adev * np.exp(-half)).tolist(),
                  "ci_high": (adev * np.exp(half)).tolist(),
                  "model_adev": np.sqrt(avar).tolist(),
                  "z": np.clip(np.log(adev**2 / avar) / (2 * half / 1.96), -5, 5).tolist()},
        "psd": {"f_hz": f.tolist(), "psd": psd.tolist(), "ci_low": (psd * 0.8).tolist(),
                "ci_high": (psd * 1.25).tolist()},
        "model_psd": {"f_hz": f.tolist(), "psd": psd.tolist()},
        "terms_adev": {"white": (n_ / np.sqrt(tau)).tolist(),
                       "bias_instability": np.full(tau.size, 0.664 * b_).tolist(),
                       "random_walk": (k_ * np.sqrt(tau / 3)).tolist()},
        "discrete_model": dm.to_dict(),
        "discrete_check": {"tau_s": tau.tolist(), "adev": (np.sqrt(dm.avar(tau)) * 1.01).tolist(),
                           "inside": 16, "total": 17, "n_samples": 1_000_000,
                           "exact_inside": 15, "exact_total": 17},
        "suggestions": [{"term": "sinusoid", "params": {"A": 2e-4, "f": 2.7},
                         "chi2_per_dof_after": 1.05, "significant": True,
                         "why": "Allan deviation oscillates near tau = 0.16 s & the PSD has a "
                                "line at 2.7 Hz: add a sinusoid <vibration>"},
                        {"term": "rate_ramp", "params": {"R": 1e-10}, "chi2_per_dof_after": 3.6,
                         "chi2_per_dof_before": 3.7, "significant": False,
                         "why": "slow drift"}],
    }


def _doc() -> dict:
    return {
        "file": "night.mcap",
        "record": {"device": "adis16350", "fs_hz": 100.0, "duration_s": 10000.0,
                   "n_samples": 1_000_000, "segments": 2, "gaps": 1, "gap_time_s": 0.5,
                   "dropped": 50, "temperature_range_degC": [24.5, 31.25],
                   "warnings": ["file was truncated: read up to the last complete chunk"]},
        "channels": {"gyro_x": _channel_doc("gyro_x", "rad/s"),
                     "accel_z": _channel_doc("accel_z", "m/s^2")},
    }


def test_report_is_well_formed_and_self_contained():
    html = render_report(_doc())
    p = _Collector()
    p.feed(html)
    p.close()
    assert p.errors == [] and p.stack == []
    tags = [t for t, _ in p.tags]
    assert tags.count("svg") == 6  # Allan, z, PSD per channel
    assert "script" not in tags and "link" not in tags and "img" not in tags
    for _, attrs in p.tags:
        for key, value in attrs.items():
            if key in ("href", "src") and value:
                assert value.startswith("#"), (key, value)  # only in-page anchors
    assert "http://" not in html.replace('xmlns="http://www.w3.org/2000/svg"', "")
    assert "https://" not in html and "@import" not in html and "url(http" not in html


def test_report_content():
    html = render_report(_doc())
    p = _Collector()
    p.feed(html)
    text = " ".join(p.text)
    # record facts
    for needle in ("adis16350", "1000000", "10000 s (2.78 h)", "24.5 to 31.25 \u00b0C",
                   "samples dropped", "truncated"):
        assert needle in text, needle
    # coefficient in SI and conventional units, with 95 % intervals:
    # N = 3e-4 rad/s/sqrt(Hz) = 3e-4 * 180/pi * 60 deg/sqrt(h) = 1.031 deg/sqrt(h)
    assert "3.000\u00d710" in html and "rad/s/sqrt(Hz)" in text
    assert "1.031 deg/sqrt(h)" in text
    assert "1.031 deg/sqrt(h) [1.021, 1.042]" in text
    # B = 4e-5 rad/s = 8.251 deg/h; accel B = 1e-4 m/s^2 = 0.0102 mg
    assert "8.251 deg/h" in text and "0.0102 mg" in text
    # diagnosis: error before and after, escaped explanation
    assert "3.7 \u2192 1.05" in text and "The model misses these effects" in text
    assert "1 other candidate term(s) tried, not significant" in text and "slow drift" in text
    assert "&lt;vibration&gt;" in html and "<vibration>" not in html
    # failing range and discrete model
    assert "0.16 to 0.64 s" in text and "measured above model" in text
    assert "0.999" in text  # a_d of a Markov state shows its digits
    assert "16 of 17 averaging times" in text and "band at 15 of 17" in text
    assert "has no finite state model" in text
    # legends of the Allan plot
    for label in ("measured, 95 % band", "fitted model", "term: white",
                  "simulated discrete model"):
        assert label in html


def test_an_amplitude_whose_interval_reaches_zero_is_reported_as_not_resolved():
    doc = _doc()
    ch = doc["channels"]["gyro_x"]
    # a flicker level the record cannot resolve: the fit's number is no measurement
    ch["model"][1] = {"term": "bias_instability", "params": {"B": 1.7e-17},
                      "ci95": {"B": [0.0, 3.1e-5]}, "unresolved": ["B"]}
    ch["suggestions"][1]["unresolved"] = ["R"]
    html = render_report(doc)
    p = _Collector()
    p.feed(html)
    text = " ".join(p.text)
    assert "1.7\u00d710" not in html and "1.700\u00d710" not in html
    # the SI cell and the conventional one, each with its upper bound (3.1e-5 rad/s = 6.394 deg/h)
    assert text.count("not resolved") == 3
    assert "6.394 deg/h" in text
    # the accelerometer's resolved B is still shown as a number
    assert "0.0102 mg" in text


def test_report_handles_missing_parts():
    doc = {"file": "x.csv", "channels": {"gyro_x": {"units": "rad/s", "fs_hz": 10.0,
                                                     "model": [], "error": None,
                                                     "failures": [], "allan": {}, "psd": {}}}}
    html = render_report(doc)
    assert "No model was fitted" in html and "no data" in html
    p = _Collector()
    p.feed(html)
    assert p.errors == []



def test_report_shows_every_part_of_the_error_and_the_halves_findings():
    """The error's parts side by side (Allan, PSD, hold-out, time domain) in each channel's
    section and the PSD part in the summary; a part not computed says why; the hold-out
    findings are listed."""
    doc = _doc()
    doc["channels"]["gyro_x"]["error"].update(
        psd={"deviance_per_bin": 2.52, "bins": 186, "outside_95": 0.15,
             "misses": [{"f_hz": [0.46, 0.47], "max_abs_z": 9.1, "direction":
                         "measured above model", "deviance_share": 0.31},
                        {"f_hz": [13.1, 13.1], "max_abs_z": 4.2, "direction":
                         "measured above model", "deviance_share": 0.01}]},
        holdout={"chi2_per_dof": 5.26, "parts": 2, "halves": [5.7, 4.8],
                 "changed": [{"param": "resonance.f0", "values": [10.2, 9.602], "z": 38.3,
                              "source": "psd"}],
                 "changes_free": {"chi2_per_dof": 5.37, "halves": [5.95, 4.78],
                                  "params": ["resonance.f0"]},
                 "joint_difference": {"params": ["white.N", "random_walk.K"], "chi2": 9.1,
                                      "dof": 2, "p": 0.011}},
        time_domain={"statistic": 4.11, "p": 0.005, "test": "bias step or warm-up"})
    doc["channels"]["accel_z"]["error"].update(
        psd={"deviance_per_bin": 1.1, "bins": 180, "outside_95": 0.05},
        holdout={"chi2_per_dof": None, "parts": 2,
                 "reason": "not computed by analyze: imunoise fit reports it"},
        time_domain={"statistic": None, "p": None,
                     "reason": "not computed by analyze: imunoise fit reports it"})
    html = render_report(doc)
    p = _Collector()
    p.feed(html)
    assert p.errors == []
    text = " ".join(" ".join(p.text).split())
    assert ("Allan \u03c7\u00b2/dof PSD deviance/bin hold-out \u03c7\u00b2/dof time domain "
            "3.7 2.52 (15 % of 186 bins outside 95 %) 5.26 (5.37 with the changes named "
            "fitted) max |z| 4.11 (p 0.005)") in text
    assert ("3.7 1.1 (5 % of 180 bins outside 95 %) not computed by analyze: imunoise fit "
            "reports it not computed by analyze: imunoise fit reports it") in text
    # the PSD's misses that make its part large, the small one counted
    assert ("Where the spectrum misses the model: measured above model at 0.46-0.47 Hz "
            "(max |z| 9.1, 31 % of the deviance); 1 smaller miss not shown "
            "Findings of the hold-out part:") in text
    assert ("Findings of the hold-out part: resonance.f0 changed between the first and "
            "second half: 10.2 -> 9.602 Hz (from each half's spectrum) (z = 38.3) the halves "
            "differ in white.N, random_walk.K taken together (chi2 9.1 over 2 parameters, "
            "p 0.011), none beyond its own level") in text
    assert "-&gt; 9.602 Hz" in html
    # the summary: Allan part then PSD part per channel
    assert "Allan \u03c7\u00b2/dof PSD deviance/bin model fits?" in text
    assert "3.7 2.52 " in text

def _png_rows(path: Path) -> tuple[int, int, np.ndarray]:
    """Width, height and the filtered scan lines (one row per image row) of a PNG."""
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, width, height = 8, b"", 0, 0
    while pos < len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        chunk = data[pos + 8:pos + 8 + length]
        if kind == b"IHDR":
            width, height = struct.unpack(">II", chunk[:8])
        elif kind == b"IDAT":
            idat += chunk
        pos += 12 + length
    rows = np.frombuffer(zlib.decompress(idat), dtype=np.uint8).reshape(height, -1)
    return width, height, rows


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install "
                    "chromium); the report's browser rendering cannot be checked")
def test_report_renders_in_headless_chromium(tmp_path):
    page = tmp_path / "report.html"
    page.write_text(render_report(_doc()))
    shot = tmp_path / "shot.png"
    r = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                        "--disable-background-networking", "--hide-scrollbars",
                        "--window-size=1200,2400", f"--screenshot={shot}", page.as_uri()],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    width, height, rows = _png_rows(shot)
    assert (width, height) == (1200, 2400)
    # A blank page filters to all-zero scan lines after the first; text, plot frames, curves
    # and bands leave many rows with content and many distinct rows.
    busy = np.count_nonzero(rows[1:, 1:], axis=1) > 20
    assert busy.mean() > 0.3, busy.mean()
    assert len({r.tobytes() for r in rows[1:][busy]}) > 500


def test_svg_plot_axes_and_gaps():
    p = Plot("t", "tau (s)", "adev (rad/s)")
    x = np.array([0.01, 0.1, 1.0, 10.0, 100.0])
    p.line(x, [1e-3, np.nan, 1e-4, 3e-5, 1e-5], "measured")
    p.band(x, [9e-4, 1e-4, 9e-5, 2e-5, 0.0], [1.1e-3, 1e-3, 1.1e-4, 4e-5, 2e-5], "band")
    svg = p.svg()
    # decade labels 10^-2 ... 10^2 (as superscripts), and the NaN splits the polyline
    for e in ("\u22122", "\u22121"):
        assert f'font-size="9">{e}</tspan>' in svg
    assert ">1<" in svg and ">10<" in svg
    assert svg.count("<polyline") == 1  # the first point is alone: no segment
    assert svg.count("<polygon") == 1  # the zero lower bound cannot be drawn on a log axis
    empty = Plot("e", "x", "y").svg()
    assert "no data" in empty
    lin = Plot("z", "tau (s)", "z", y_log=False)
    lin.markers([1.0, 10.0], [-3.0, 2.0]).hline(0.0)
    svg = lin.svg()
    assert ">\u22122<" in svg and ">0<" in svg and ">2<" in svg


def test_negligible_term_does_not_stretch_the_axis():
    tau = np.array([0.01, 0.1, 1.0, 10.0])
    p = Plot("t", "tau (s)", "adev (rad/s)")
    p.line(tau, [1e-3, 3e-4, 1e-4, 3e-5], "measured")
    p.line(tau, [1e-20, 1e-19, 1e-18, 1e-17], "term: random_walk", autoscale=False)
    svg = p.svg()
    assert 'font-size="9">\u22123</tspan>' in svg
    assert 'font-size="9">\u221219</tspan>' not in svg


# --- end to end: analyze --report on CSV and MCAP recordings ---------------------------------

@pytest.fixture(scope="module")
def recordings(tmp_path_factory):
    from tests.outputs_inputs import write_csv, write_mcap

    d = tmp_path_factory.mktemp("rec")
    return {"csv": write_csv(d / "still.csv"), "mcap": write_mcap(d / "mcap")}


@pytest.mark.parametrize("kind", ["csv", "mcap"])
def test_analyze_report_end_to_end(recordings, kind, tmp_path, capsys):
    import json

    from imunoise.cli import main
    from tests.outputs_inputs import FS

    out = tmp_path / "night.html"
    assert main(["analyze", str(recordings[kind]), "--json", "--report", str(out)]) == 0
    doc = json.loads(capsys.readouterr().out)
    html = out.read_text()
    assert list(tmp_path.iterdir()) == [out]  # no temporary left behind
    chans = doc["channels"]
    assert sorted(chans) == sorted(f"{s}_{a}" for s in ("gyro", "accel") for a in "xyz")
    inside = total = 0
    for name, ch in chans.items():
        # the JSON carries the discrete model and nothing that only the report needs
        assert not {"terms_adev", "model_psd", "discrete_check"} & set(ch)
        dm = ch["discrete_model"]
        n_fit = next(t["params"]["N"] for t in ch["model"] if t["term"] == "white")
        fs = ch["fs_hz"]
        assert fs == pytest.approx(FS, rel=1e-8)
        assert dm["white_sigma"] == pytest.approx(n_fit * np.sqrt(fs), rel=1e-12)
        k_fit = next(t["params"]["K"] for t in ch["model"] if t["term"] == "random_walk")
        assert dm["random_walk_step"] == pytest.approx(k_fit / np.sqrt(fs), rel=1e-12)
        approx = dm["bias_instability_approximation"]
        if approx is not None and approx["states_per_decade"] > 0:
            assert approx["max_rel_avar_error"] <= 0.02
            assert approx["tau_range_s"][0] == pytest.approx(1 / fs)
            assert 2 <= len(dm["markov"]) <= 20
        elif approx is not None:  # B fitted as (nearly) zero on a short record: no states
            assert approx["max_rel_avar_error"] < 1e-4 and dm["markov"] == []
        assert f'id="ch-{name}"' in html
    p = _Collector()
    p.feed(html)
    assert p.errors == []
    # three plots per channel, and the coherence section's pairs that pass the family-wise
    # zero-coherence test (by chance here: the six axes are independent)
    pair_plots = html.count('<div class="plot"><svg')
    assert pair_plots <= 6 and 'id="coherence"' in html
    assert [t for t, _ in p.tags].count("svg") == 3 * 6 + pair_plots
    text = " ".join(p.text)
    # the simulated discrete model against the measurement, per channel, stated in the report
    import re

    checks = re.findall(r"agrees with the measurement at (\d+) of (\d+) averaging times", text)
    assert len(checks) == 6
    for a, b in checks:
        inside += int(a)
        total += int(b)
    # A correct model agrees at about 95 % of taus (two independent estimates compared on
    # their combined interval); neighbouring taus are correlated, so allow a wide margin.
    assert total >= 6 * 8 and inside >= 0.8 * total, (inside, total)
    # the diagnosis of the default model for every channel, with chi2/dof before and after
    assert html.count("<h3>Diagnosis</h3>") == 6
    assert len(re.findall(r"\d \u2192 \d", text)) >= 6
    assert "no diagnosis" not in text
    assert re.search(r"samples\s*40000\b", text)
    assert re.search(rf"gaps\s*{1 if kind == 'mcap' else 0}\b", text)
    if kind == "mcap":
        assert "sim:adis16350" in text
        from tests.outputs_inputs import GAP_LEN

        assert f"{GAP_LEN} sample(s) missing in 1 gap(s)" in text  # the reader warns
    # temperature 30 +- 2 degC over the record
    assert "28 to 32 \u00b0C (spread 4 \u00b0C)" in text


def test_analyze_report_bad_output_path_is_one_line_exit_2(recordings, tmp_path, capsys):
    from imunoise.cli import main

    missing = tmp_path / "no" / "such" / "r.html"
    assert main(["analyze", str(recordings["csv"]), "--report", str(missing)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "does not exist" in err[0]
    assert main(["analyze", str(recordings["csv"]), "--report", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a folder" in err[0]
    assert list(tmp_path.iterdir()) == []


def test_report_names_a_missing_effect(tmp_path):
    # A gyro with a 2.7 Hz vibration line that the default model lacks: the report's diagnosis
    # must list the sinusoid as significant, with the misfit falling when it is added.
    import re

    from imunoise.analysis.noise_stream import NoiseStream
    from imunoise.cli import main

    fs, n = 100.0, 40_000
    t = np.arange(n) / fs
    model = [("white", {"N": 3e-4}), ("random_walk", {"K": 2e-5})]
    rate = NoiseStream(model, fs, seed=21).take(n) + 2e-3 * np.sin(2 * np.pi * 2.7 * t)
    src = tmp_path / "vib.csv"
    np.savetxt(src, np.column_stack([t, rate]), delimiter=",", header="t,gyro_x",
               comments="", fmt="%.10g")
    out = tmp_path / "vib.html"
    assert main(["analyze", str(src), "--report", str(out)]) == 0
    html = out.read_text()
    p = _Collector()
    p.feed(html)
    text = " ".join(p.text)
    assert "The model misses these effects" in text
    first = text[text.index("The model misses these effects"):]
    m = re.search(r"sinusoid\s+f = ([\d.]+), A = ([\d.]+)\s+([\d.]+) \u2192 ([\d.]+)\s+yes",
                  first)
    assert m, first[:400]
    assert float(m.group(1)) == pytest.approx(2.7, abs=0.05)
    assert float(m.group(2)) == pytest.approx(2e-3, rel=0.1)  # amplitude in rad/s
    assert float(m.group(4)) < float(m.group(3))


def test_a_significant_removal_is_reported_as_a_term_to_drop():
    doc = _doc()
    for other in doc["channels"].values():
        other.pop("suggestions", None)
    ch = doc["channels"]["gyro_x"]
    ch["suggestions"] = [{"term": "gauss_markov", "action": "remove", "label": "gauss_markov",
                          "params": {"sigma": 5e-5, "T": 183.0},
                          "ci95": {"sigma": [0.0, 1.9e-3], "T": [0.04, 2.6e5]},
                          "unresolved": ["sigma"], "chi2_per_dof_before": 1.48,
                          "chi2_per_dof_after": 1.36, "significant": True, "p_value": 0.52,
                          "why": "The record does not resolve gauss_markov.",
                          "apply": {"model": "white,bias_instability,random_walk",
                                    "args": []}}]
    p = _Collector()
    p.feed(render_report(doc))
    text = " ".join(p.text)
    assert "the record does not resolve these terms" in text
    assert "remove gauss_markov" in text
    assert "misses these effects" not in text
