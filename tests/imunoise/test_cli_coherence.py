"""``analyze`` and ``diagnose`` across channels, end to end through the real CLI: the
``coherence`` key, the suggestions' verdict, ``--subtract-common``."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from tests.analysis.bench_records import NAMES, bench_record

TRUE_N_ACCEL_Y = 1.5e-3


def _run(*args):
    return subprocess.run([sys.executable, "-m", "imunoise", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


@pytest.fixture(scope="module")
def bench_csv(tmp_path_factory):
    x, truth = bench_record(61, n=1 << 16)
    assert truth["N"][4] == TRUE_N_ACCEL_Y
    t = 10.0 + np.arange(len(x)) / 100.0
    path = tmp_path_factory.mktemp("coherence") / "bench.csv"
    np.savetxt(path, np.column_stack([t, x]), delimiter=",", fmt="%.10g", comments="",
               header="t," + ",".join(NAMES))
    return path


def _finite(obj) -> bool:
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, dict):
        return all(_finite(v) for v in obj.values())
    if isinstance(obj, list):
        return all(_finite(v) for v in obj)
    return True


def test_analyze_json_has_the_coherence_of_every_pair(bench_csv):
    proc = _run("analyze", bench_csv, "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    co = doc["coherence"]
    assert _finite(co)
    assert co["channels"] == NAMES and len(co["pairs"]) == 15
    assert np.shape(co["msc"]) == (15, len(co["f_hz"]))
    assert np.shape(co["ci"]["low"]) == np.shape(co["msc"])
    assert len(co["threshold"]) == len(co["f_hz"])
    found = {(c["channel"], round(c["f_hz"], 1)): c for c in co["classification"]}
    rock = found[("accel_y", 1.5)]
    assert rock["origin"] == "common" and rock["common_with"] == ["gyro_x"]
    assert "rotation" in rock["why"]
    assert found[("accel_z", 3.3)]["origin"] == "own"
    assert "own" not in doc["channels"]["accel_y"]
    assert co["shared_shapes"] == []  # a shared motion and own lines: no common filter


def test_analyze_subtract_common_reports_the_own_noise_beside_the_raw(bench_csv):
    proc = _run("analyze", bench_csv, "--json", "--subtract-common", "--channel", "accel_x",
                "--channel", "accel_y", "--channel", "accel_z", "--channel", "gyro_x")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    ch = doc["channels"]["accel_y"]
    own = ch["own"]
    assert _finite(own)
    assert own["subtraction"]["references"] == ["accel_x", "accel_z", "gyro_x"]
    err = own["subtraction"]["error"]
    assert 0 < err["removed_share"] < 0.5 and 0 <= err["leak_share"] < err["removed_share"]
    lo, hi = own["white_level"]["ci"]
    assert lo <= TRUE_N_ACCEL_Y <= hi
    # the raw Allan deviation at 1 s carries the lines; the own one does not
    raw = dict(zip(ch["allan"]["tau_s"], ch["allan"]["adev"], strict=True))
    mine = dict(zip(own["allan"]["tau_s"], own["allan"]["adev"], strict=True))
    assert raw[1.28] > 1.3 * mine[1.28]
    assert own["error"]["chi2_per_dof"] < ch["error"]["chi2_per_dof"]


def test_analyze_text_ends_with_the_coherence(bench_csv):
    proc = _run("analyze", bench_csv, "--channel", "accel_y", "--channel", "gyro_x",
                "--subtract-common")
    assert proc.returncode == 0, proc.stderr
    assert "accel_y own noise" in proc.stdout
    assert "own white level at tau = 1 s" in proc.stdout
    assert "coherence between channels" in proc.stdout
    assert "accel_y sinusoid at 1.5 Hz: common" in proc.stdout


def test_diagnose_says_common_or_own(bench_csv):
    proc = _run("diagnose", bench_csv, "--channel", "accel_z", "--model", "white", "--json")
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    own = [c for c in doc["coherence"]["classification"] if round(c["f_hz"], 1) == 3.3]
    assert own and own[0]["origin"] == "own"
    line = [s for s in doc["suggestions"] if s["term"] == "sinusoid"]
    assert line and "Own to accel_z" in line[0]["why"] and line[0]["origin"] == "own"


def test_diagnose_names_a_filter_every_channel_passes_through(tmp_path):
    # independent noise in each channel through one steep lowpass, as a decimating logger
    # leaves it: one spectral shape and no coherence
    from scipy import signal

    rng = np.random.default_rng(71)
    n = 1 << 16
    w = rng.standard_normal((n, 4)) * np.array([1e-3, 2e-3, 5e-2, 3e-2])
    x = signal.sosfilt(signal.butter(6, 5.0, fs=100.0, output="sos"), w, axis=0) \
        + 0.03 * w[::-1]
    names = ["gyro_x", "gyro_y", "accel_x", "accel_y"]
    path = tmp_path / "decimated.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / 100.0, x]), delimiter=",",
               fmt="%.10g", comments="", header="t," + ",".join(names))
    proc = _run("diagnose", path, "--channel", "accel_x", "--model", "white")
    assert proc.returncode == 0, proc.stderr
    assert "the channel's spectral shape (against the other channels)" in proc.stdout
    assert "share one spectral shape and no signal" in proc.stdout
    proc = _run("diagnose", path, "--channel", "accel_x", "--model", "white", "--json")
    doc = json.loads(proc.stdout)
    shapes = doc["coherence"]["shared_shapes"]
    assert len(shapes) == 1 and sorted(shapes[0]["channels"]) == sorted(names)
    shaping = [s for s in doc["suggestions"] if s["term"] in ("resonance", "gauss_markov",
                                                               "moving_average", "lowpass")]
    assert shaping and all("The channel's spectrum has the shape of gyro_x, gyro_y, accel_y "
                           "with no signal in common" in s["why"] for s in shaping)
    assert all("shared_shapes" not in s["why"] for s in doc["suggestions"]
               if s["term"] in ("sinusoid", "bias_step"))
    assert shapes[0]["span"] > 100.0 and shapes[0]["kinds"].count("gyro") == 2
    proc = _run("analyze", path)
    assert proc.returncode == 0, proc.stderr
    assert "spectral shape: gyro_x, gyro_y, accel_x, accel_y share one" in proc.stdout
    report = tmp_path / "report.html"
    proc = _run("analyze", path, "--report", report)
    assert proc.returncode == 0, proc.stderr
    html = report.read_text()
    assert "One spectral shape, no common signal: the chain's filter</h3>" in html
    assert "gyro_x, gyro_y, accel_x, accel_y share one spectral shape" in html


def test_subtract_common_on_a_streamed_file_is_a_usage_error(tmp_path):
    from tests.outputs_inputs import write_mcap

    path = write_mcap(tmp_path)
    proc = _run("analyze", path, "--stream", "always", "--subtract-common", "--json")
    assert proc.returncode == 2
    assert "--subtract-common" in proc.stderr and "Traceback" not in proc.stderr


def test_report_shows_the_coherence_matrix_pairs_and_own_noise(bench_csv):
    from imunoise.export.report_html import render_report
    from imunoise.pipeline import cross_channel
    from imunoise.pipeline.channel_analysis import analyze_record
    from imunoise.pipeline.documents import analysis_json
    from imunoise.pipeline.reading import read_record

    record = read_record(str(bench_csv), static="all")
    keys = ["gyro_x", "accel_x", "accel_y", "accel_z"]
    doc = analysis_json(str(bench_csv), record, analyze_record(record, keys))
    co, residuals = cross_channel.coherence_document(record, keys, subtract=True)
    doc["coherence"] = co
    cross_channel.add_own(doc, record, residuals)
    html = render_report(doc)
    assert 'id="coherence"' in html and 'href="#coherence"' in html
    assert html.count('class="matrix"') == 1
    # the coherent pairs drawn on log-frequency axes: gyro_x-accel_y and the accelerometers'
    assert "coherence gyro_x - accel_y" in html
    assert "coherence accel_x - accel_y" in html
    assert "environment or sensor" in html.lower()
    assert html.count("Own noise: the other channels") == 4
    assert "raw and own Allan deviation" in html


def test_three_sensors_on_one_bench_common_line_and_the_hat(tmp_path):
    """Three simulated sensors recorded into one MCAP (a topic each) under a shared bench
    vibration: the common resonance is named as seen by more than one sensor, a line of one
    sensor alone as its own, and the hat gives each one's own white level with an interval."""
    from imunoise.analysis.noise_stream import simulate
    from imunoise.core.blocks import SampleBlock
    from tests.mcap_helpers import record_blocks

    n, size, fs = 60000, 500, 100.0
    rng = np.random.default_rng(3)
    common = simulate([("white", {"N": 3e-3}), ("resonance", {"sigma": 0.02, "f0": 2.0,
                                                               "Q": 5.0})], n, fs, rng)
    own_n = [1e-3, 2e-3, 0.5e-3]
    sensors = []
    for v in own_n:  # a full IMU message per sample: the other axes own noise only
        ch = {c: simulate([("white", {"N": 1e-3})], n, fs, rng) for c in NAMES}
        ch["gyro_x"] = common + simulate([("white", {"N": v})], n, fs, rng)
        ch["accel_z"] -= 9.80665
        sensors.append(ch)
    # a line of sensor 2 alone, standing out of the shared broadband bench noise in the
    # coherence's 0.2 Hz bins (at 2e-3 it stands 1.14 times above that continuum, and its bin
    # is judged as it is: half common, "mixed")
    sensors[1]["gyro_x"] += 5e-3 * np.sin(2 * np.pi * 7.3 * np.arange(n) / fs)
    blocks = [SampleBlock(f"/imu{i + 1}/imu", 1.7e9 + np.arange(a, a + size) / fs,
                          {c: v[a:a + size] for c, v in ch.items()}, fs)
              for a in range(0, n, size) for i, ch in enumerate(sensors)]
    out = tmp_path / "bench"
    out.mkdir()
    record_blocks(out, blocks)
    (path,) = out.glob("*.mcap")
    keys = [f"/imu{i}/imu:gyro_x" for i in (1, 2, 3)]
    proc = _run("analyze", path, "--json", *[a for k in keys for a in ("--channel", k)])
    assert proc.returncode == 0, proc.stderr
    co = json.loads(proc.stdout)["coherence"]
    assert co["channels"] == keys
    lines = [c for c in co["classification"] if abs(c["f_hz"] - 2.0) < 0.3]
    assert lines and all(c["origin"] == "common" for c in lines)
    assert all("more than one sensor" in c["reading"] for c in lines)
    own = [c for c in co["classification"] if abs(c["f_hz"] - 7.3) < 0.05]
    assert [c["channel"] for c in own] == ["/imu2/imu:gyro_x"]
    assert own[0]["origin"] == "own" and own[0]["why"].startswith("Own to /imu2/imu:gyro_x")
    levels = co["sensors"]["gyro_x"]["white_level"]
    covered = [levels[k]["ci"][0] <= v <= levels[k]["ci"][1]
               for k, v in zip(keys, own_n, strict=True)]
    # 95 % intervals: at most one of three misses with probability 0.993
    assert sum(covered) >= 2, levels


def _advanced(x: np.ndarray, frac: float) -> np.ndarray:
    """``x`` (band-limited, periodic) read ``frac`` of a sample later: exact in the FFT."""
    k = np.arange(x.size // 2 + 1)
    return np.fft.irfft(np.fft.rfft(x) * np.exp(2j * np.pi * k * frac / x.size), x.size)


def test_three_sensors_sampled_at_their_own_instants_are_compared(tmp_path):
    """As recorded by ``serve``: each device samples at its own instants (0, 0.31 and 0.74 of
    a period apart) and the second lost 25 samples. The other devices are interpolated onto
    the first's sample times: the common resonance is named common, the second sensor's
    line its own, and the hat's own white levels cover the truth."""
    from imunoise.analysis.noise_stream import simulate
    from imunoise.core.blocks import SampleBlock
    from tests.mcap_helpers import record_blocks

    n, size, fs = 60000, 500, 100.0
    rng = np.random.default_rng(5)
    common = simulate([("white", {"N": 3e-3}), ("resonance", {"sigma": 0.02, "f0": 2.0,
                                                               "Q": 5.0})], n, fs, rng)
    own_n = [1e-3, 2e-3, 0.5e-3]
    offsets = [0.0, 0.31, 0.74]
    blocks = []
    for i, (v, frac) in enumerate(zip(own_n, offsets, strict=True)):
        ch = {c: simulate([("white", {"N": 1e-3})], n, fs, rng) for c in NAMES}
        ch["gyro_x"] = _advanced(common, frac) + simulate([("white", {"N": v})], n, fs, rng)
        ch["accel_z"] -= 9.80665
        if i == 1:
            ch["gyro_x"] += 5e-3 * np.sin(2 * np.pi * 7.3 * (np.arange(n) + frac) / fs)
        t = 1.7e9 + (np.arange(n) + frac) / fs
        keep = np.ones(n, bool)
        if i == 1:
            keep[30000:30025] = False
        for a in range(0, n, size):
            sl = np.flatnonzero(keep[a:a + size]) + a
            blocks.append(SampleBlock(f"/imu{i + 1}/imu", t[sl],
                                      {c: val[sl] for c, val in ch.items()}, fs))
    out = tmp_path / "bench"
    out.mkdir()
    record_blocks(out, blocks)
    (path,) = out.glob("*.mcap")
    keys = [f"/imu{i}/imu:gyro_x" for i in (1, 2, 3)]
    proc = _run("analyze", path, "--json", *[a for k in keys for a in ("--channel", k)])
    assert proc.returncode == 0, proc.stderr
    co = json.loads(proc.stdout)["coherence"]
    assert co["channels"] == keys
    assert co["aligned"]["reference"] == keys[0]
    assert co["aligned"]["interpolated"] == keys[1:]
    assert 0.99 < co["aligned"]["kept_share"] < 1.0
    lines = [c for c in co["classification"] if abs(c["f_hz"] - 2.0) < 0.3]
    assert lines and all(c["origin"] == "common" for c in lines)
    own = [c for c in co["classification"] if abs(c["f_hz"] - 7.3) < 0.05]
    assert [c["channel"] for c in own] == ["/imu2/imu:gyro_x"]
    assert own[0]["origin"] == "own"
    levels = co["sensors"]["gyro_x"]["white_level"]
    covered = [levels[k]["ci"][0] <= v <= levels[k]["ci"][1]
               for k, v in zip(keys, own_n, strict=True)]
    assert sum(covered) >= 2, levels
    # the own noise lies on the aligned samples: the second sensor's gap splits them
    proc = _run("analyze", path, "--json", "--subtract-common",
                *[a for k in keys for a in ("--channel", k)])
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    kept = round(co["aligned"]["kept_share"] * n)
    for k in keys:
        own = doc["channels"][k]["own"]
        assert own["n_samples"] == pytest.approx(kept, abs=1), (k, own["n_samples"], kept)
        assert own["n_segments"] == 2, (k, own["n_segments"])


def test_report_has_the_own_noise_diagnosis(bench_csv):
    from imunoise.export.report_html import render_report
    from imunoise.pipeline import cross_channel
    from imunoise.pipeline.channel_analysis import analyze_record
    from imunoise.pipeline.documents import analysis_json
    from imunoise.pipeline.reading import read_record

    record = read_record(str(bench_csv), static="all")
    keys = ["gyro_x", "accel_x", "accel_y", "accel_z"]
    doc = analysis_json(str(bench_csv), record, analyze_record(record, keys))
    co, residuals = cross_channel.coherence_document(record, keys, subtract=True,
                                                     only=["accel_y"])
    assert list(residuals) == ["accel_y"]
    doc["coherence"] = co
    cross_channel.add_own(doc, record, residuals, diagnose=True)
    own = doc["channels"]["accel_y"]["own"]
    # the bench line (0.56 Hz) and the rocking (1.5 Hz) are gone from the residual
    lines = [s["params"]["f"] for s in own["suggestions"]
             if s["term"] == "sinusoid" and s["significant"]]
    assert not any(abs(f - 0.56) < 0.05 or abs(f - 1.5) < 0.05 for f in lines), lines
    # the diagnosis is of the residual: its starting misfit is the own fit's, far below the raw
    raw_chi2 = doc["channels"]["accel_y"]["error"]["chi2_per_dof"]
    assert own["suggestions"][0]["chi2_per_dof_before"] == pytest.approx(
        own["error"]["chi2_per_dof"], rel=1e-6)
    assert own["error"]["chi2_per_dof"] < raw_chi2 / 10
    html = render_report(doc)
    assert html.count("Diagnosis of the own noise") == 1


def test_coherence_started_before_the_analysis_gives_the_same_document(bench_csv):
    # the commands start the channels' coherence in a background process while they fit;
    # the document is the one computed afterwards, and one started for other channels (a
    # channel dropped from the analysis) is not used
    from imunoise.pipeline import cross_channel
    from imunoise.pipeline.reading import read_record

    record = read_record(str(bench_csv))
    keys = list(record.channels)
    plain, _ = cross_channel.coherence_document(record, keys)
    pending = cross_channel.PendingCoherence(keys, cross_channel.coherence_inputs(record, keys))
    early, _ = cross_channel.coherence_document(record, keys, pending=pending)
    assert json.dumps(early) == json.dumps(plain)
    fewer = keys[:3]
    other, _ = cross_channel.coherence_document(record, fewer, pending=pending)
    assert len(other["pairs"]) == 3 and len(plain["pairs"]) == 15
    assert json.dumps(other) == json.dumps(cross_channel.coherence_document(record, fewer)[0])
