"""``imunoise analyze --stream``: a recording analysed in two bounded-memory passes gives the
numbers of the loaded analysis (real recorder files, the real CLI in a subprocess)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from imunoise.core.blocks import SampleBlock
from imunoise.pipeline import streamed_analysis
from tests.mcap_helpers import ACCEL_LSB, GYRO_LSB, record_blocks

FS = 100.0


def _blocks(n_blocks: int = 2400, nan_at: int | None = None) -> list[SampleBlock]:
    """40 min of quantized white noise plus a random walk at 100 Hz in 1 s blocks; 137 samples
    lost before block 1500; the sensor turns at 0.3 rad/s and tilts for a minute from 600 s."""
    rng = np.random.default_rng(7)
    walk = np.zeros(6)
    blocks, k = [], 0
    names = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
    for b in range(n_blocks):
        gap = 137 if b == 1500 else 0
        k += gap
        t = 1.7e9 + (k + np.arange(100)) / FS
        ch, raw = {}, {}
        for i, name in enumerate(names):
            lsb = GYRO_LSB if i < 3 else ACCEL_LSB
            drift = walk[i] + np.cumsum(rng.normal(0, 0.005, 100))
            walk[i] = drift[-1]
            counts = np.rint(rng.normal(0, 8, 100) + drift).astype(np.int64)
            if 600 <= b < 660:
                counts += int(0.3 / GYRO_LSB) if name == "gyro_z" else 0
                counts += int(1.0 / ACCEL_LSB) if name == "accel_x" else 0
            raw[name] = counts
            ch[name] = counts * lsb
        if nan_at is not None and b == nan_at:
            ch["gyro_x"] = ch["gyro_x"].copy()
            ch["gyro_x"][40] = np.nan
        ch["temp"] = np.full(100, 25.0 + 1e-4 * b)
        blocks.append(SampleBlock("/sim/imu", t, ch, FS, raw=raw, gap_before=gap))
        k += 100
    return blocks


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    out = tmp_path_factory.mktemp("streamed")
    record_blocks(out, _blocks())
    (path,) = out.glob("*.mcap")
    return path


def _analyze(path, *args) -> dict:
    p = subprocess.run([sys.executable, "-m", "imunoise", "analyze", str(path), "--json", *args],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


def test_streamed_equals_loaded(recording):
    loaded = _analyze(recording, "--stream", "never")
    streamed = _analyze(recording, "--stream", "always")
    assert streamed["motion"] == loaded["motion"]
    assert loaded["motion"]["imu"]["moved"] and "still stretch" in loaded["motion"]["imu"]["used"]
    assert streamed["warnings"] == loaded["warnings"]
    tl, ts = loaded["timing"]["/sim/imu"], streamed["timing"]["/sim/imu"]
    assert (ts["fs_hz"], ts["segments"], ts["missing_samples"], ts["backward_steps"]) == \
        (tl["fs_hz"], tl["segments"], tl["missing_samples"], tl["backward_steps"]) == \
        (100.0, 2, 137, 0)
    assert set(streamed["channels"]) == set(loaded["channels"]) and len(loaded["channels"]) == 6
    for key, a in loaded["channels"].items():
        b = streamed["channels"][key]
        for field in ("n_samples", "n_segments", "fs_hz", "duration_s", "units"):
            assert b[field] == a[field], (key, field)
        assert a["n_segments"] == 3  # before the turn, after it, after the gap
        al, bl = a["allan"], b["allan"]
        np.testing.assert_array_equal(bl["tau_s"], al["tau_s"])
        # 2.4e5 samples fit the strided history at stride 1: exact at every tau
        np.testing.assert_allclose(bl["adev"], al["adev"], rtol=1e-9)
        assert bl["alpha"] == al["alpha"]
        np.testing.assert_allclose(bl["edf"], al["edf"], rtol=1e-9)
        np.testing.assert_allclose(bl["ci_low"], al["ci_low"], rtol=1e-9)
        # the in-memory PSD is the same streaming estimator
        np.testing.assert_allclose(b["psd"]["psd"], a["psd"]["psd"], rtol=1e-12)
        np.testing.assert_array_equal(b["psd"]["f_hz"], a["psd"]["f_hz"])
        # curves equal to 1e-13 give fits equal to the optimizer's own stopping tolerance
        # (about 1e-5 relative; the coefficients' 95 % intervals are a few % wide)
        for ta, tb in zip(a["model"], b["model"], strict=True):
            assert ta["term"] == tb["term"]
            assert tb["unresolved"] == ta["unresolved"], key
            for p, v in ta["params"].items():
                if p in ta["unresolved"]:
                    # not a measurement (its interval reaches zero): the optimizer leaves it
                    # anywhere near zero (gyro_y's B, loaded and streamed, on one machine: 6.5e-16
                    # and 4.1e-12 rad/s); what is reported, the upper end, agrees
                    assert tb["ci95"][p][1] == pytest.approx(ta["ci95"][p][1], rel=0.03)
                    continue
                assert tb["params"][p] == pytest.approx(v, rel=1e-4), (key, p)
        assert b["error"]["chi2_per_dof"] == pytest.approx(a["error"]["chi2_per_dof"], rel=1e-4)


def test_non_finite_samples_become_gaps(tmp_path):
    record_blocks(tmp_path, _blocks(600, nan_at=300))
    (path,) = tmp_path.glob("*.mcap")
    doc = _analyze(path, "--stream", "always", "--channel", "gyro_x", "--static", "all")
    ch = doc["channels"]["gyro_x"]
    assert ch["n_samples"] == 600 * 100 - 1
    assert ch["n_segments"] == 2
    assert "gyro_x: 1 non-finite samples dropped (treated as gaps)" in doc["warnings"]


def test_report_of_a_streamed_record_says_why_it_has_no_diagnosis(recording, tmp_path):
    out = tmp_path / "r.html"
    p = subprocess.run([sys.executable, "-m", "imunoise", "analyze", str(recording),
                        "--stream", "always", "--channel", "gyro_x", "--report", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    html = out.read_text()
    assert "no diagnosis: the record was analysed without holding its samples" in html
    assert "gyro_x" in html


def test_which_files_stream(recording, tmp_path, monkeypatch):
    def streams(path, mode):
        return streamed_analysis.stream_source(str(path), mode) is not None

    # 2.4e5 samples x 6 channels x 8 bytes = 11.5 MB: loaded unless asked
    src = streamed_analysis.stream_source(str(recording), "always")
    assert streamed_analysis.imu_sample_bytes(src) == 240_000 * 6 * 8
    assert not streams(recording, "auto")
    assert streams(recording, "always")
    assert not streams(recording, "never")
    monkeypatch.setattr(streamed_analysis, "STREAM_ABOVE_BYTES", 10_000_000)
    assert streams(recording, "auto")
    csv = tmp_path / "x.csv"
    csv.write_text("t,gyro_x\n0,1\n0.01,2\n")
    assert not streams(csv, "always")  # CSV is always loaded
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"not an mcap")
    assert not streams(broken, "always")  # the loader says why


def test_temperature_channel_of_a_streamed_record(recording):
    # the temperature (small) is held and analysed as when the file is loaded
    loaded = _analyze(recording, "--stream", "never", "--channel", "temp")
    streamed = _analyze(recording, "--stream", "always", "--channel", "temp")
    assert streamed["channels"] == loaded["channels"]
    assert streamed["channels"]["temp"]["n_samples"] == 240_000


def test_streamed_and_loaded_warn_alike_of_held_samples(tmp_path):
    """gyro_y read twice a sample for 100 s, and held for 0.35 s across a block boundary."""
    blocks = _blocks(n_blocks=400)
    for b in blocks[100:200]:
        v = b.channels["gyro_y"].copy()
        v[1::2] = v[0::2]
        b.channels["gyro_y"] = v
    for b, part in ((blocks[250], slice(80, 100)), (blocks[251], slice(0, 15))):
        v = b.channels["gyro_y"].copy()
        v[part] = blocks[250].channels["gyro_y"][79]
        b.channels["gyro_y"] = v
    record_blocks(tmp_path, blocks)
    (path,) = tmp_path.glob("*.mcap")
    loaded = _analyze(path, "--stream", "never")["channels"]
    streamed = _analyze(path, "--stream", "always")["channels"]
    y = np.concatenate([b.channels["gyro_y"] for b in blocks])
    count = int(np.count_nonzero(np.diff(y) == 0))  # 5,035 held, the rest by chance
    assert 5_035 < count < 5_035 + 0.05 * y.size
    expected = (f"{count} samples ({100 * count / y.size:.2g} %) repeat the sample before them "
                "exactly, in runs of up to 0.35 s: held values, not measurements (diagnose's "
                "held_samples evidence says more)")
    assert expected in loaded["gyro_y"]["warnings"]
    assert streamed["gyro_y"]["warnings"] == loaded["gyro_y"]["warnings"]
    assert not any("held" in w for w in streamed["gyro_x"].get("warnings") or [])
