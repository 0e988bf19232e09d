"""Environment or sensor: common lines named common with their axes and physical reading, own
lines and resonances own; ADIS16405 run 1."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.coherence import cross_spectra
from imunoise.analysis.environment import (
    SpectralFeature,
    annotate,
    channel_device,
    channel_kind,
    classify,
    features_from_diagnosis,
    resonance_band,
)
from tests.analysis.bench_records import (
    LINE_DIR,
    LINE_F,
    NAMES,
    OWN_LINE_F,
    OWN_RES,
    ROCK_F,
    bench_record,
)


def _line(ch: str, f: float) -> SpectralFeature:
    return SpectralFeature(ch, "sinusoid", f, (f, f))


@pytest.fixture(scope="module")
def bench():
    x, _ = bench_record(11)
    return x, cross_spectra(x, 100.0, NAMES, nperseg=4096), dict(zip(NAMES, x.mean(0), strict=True))


def test_common_line_is_one_linear_motion_of_the_bench(bench):
    x, cs, means = bench
    origins = classify([_line(c, LINE_F) for c in ("accel_x", "accel_y", "accel_z")], cs,
                       means=means)
    for o in origins:
        assert o.origin == "common"
        assert set(o.common_with) == {"accel_x", "accel_y", "accel_z"} - {o.feature.channel}
        assert "linear vibration" in o.reading and "not a tilt" in o.reading
        u = np.array(o.motion["accel_direction"])
        d = LINE_DIR / np.linalg.norm(LINE_DIR)
        assert abs(abs(u @ d) - 1) < 1e-3
        angle = np.degrees(np.arccos(d[2]))
        assert o.motion["angle_to_gravity_deg"] == pytest.approx(angle, abs=1.0)
        assert o.motion["accel_amplitude"] == pytest.approx(0.01, rel=0.05)
        assert "Common, not" in o.why and "accel_" in o.why


def test_rocking_is_named_a_rotation_with_gyro_and_accelerometer(bench):
    x, cs, means = bench
    (o,) = classify([_line("accel_y", ROCK_F)], cs, means=means)
    assert o.origin == "common" and "gyro_x" in o.common_with
    assert "rotation" in o.reading
    assert o.motion["rotation_explains"] == pytest.approx(1.0, abs=0.1)
    assert abs(o.motion["rate_direction"][0]) > 0.99


def test_tilt_without_gyros_follows_the_gravity_projection(bench):
    x, _, means = bench
    acc = NAMES[3:]
    cs = cross_spectra(x[:, 3:], 100.0, acc, nperseg=4096)
    (o,) = classify([_line("accel_y", ROCK_F)], cs, means=means)
    # only accel_y sees the rocking: one axis, nothing to share -> own within this sensor
    assert o.origin == "own"
    # a tilt about an axis in the horizontal plane moves x and y together
    rng = np.random.default_rng(5)
    t = np.arange(len(x)) / 100.0
    theta = 4e-4 * np.sin(2 * np.pi * 0.9 * t + 1.0)
    y = x[:, 3:].copy()
    axis = np.array([0.6, 0.8, 0.0])  # tilt axis in the horizontal plane
    g = np.array([0.0, 0.0, -9.80665])
    y += theta[:, None] * np.cross(g, axis)[None, :] * -1.0
    y += 1e-4 * rng.normal(size=y.shape)
    cs = cross_spectra(y, 100.0, acc, nperseg=4096)
    (o,) = classify([_line("accel_x", 0.9)], cs, means=dict(zip(acc, y.mean(0), strict=True)))
    assert o.origin == "common" and o.common_with == ["accel_y"]
    assert "tilt" in o.reading
    assert o.motion["angle_to_gravity_deg"] > 85
    assert o.motion["accel_amplitude"] == pytest.approx(4e-4 * 9.80665, rel=0.1)


def test_own_resonance_and_own_line_are_own(bench):
    x, cs, means = bench
    feats = [SpectralFeature("accel_x", "resonance", OWN_RES["f0"],
                             resonance_band(OWN_RES["f0"], OWN_RES["Q"])),
             _line("accel_z", OWN_LINE_F)]
    for o in classify(feats, cs, means=means):
        assert o.origin == "own", o.why
        assert o.reading == ""
        assert all(p.ci_high < 0.5 for p in o.partners)
        assert o.why.startswith("Own to")


def test_independent_channels_show_no_common_feature():
    """Pure independent noise: at 40 frequencies no feature is called common (the test's
    threshold and the majority rule together)."""
    x, _ = bench_record(12, line=False, rock=False, own=False)
    cs = cross_spectra(x, 100.0, NAMES, nperseg=1024)
    freqs = np.geomspace(0.3, 40.0, 40)
    origins = classify([_line(c, f) for f in freqs for c in NAMES], cs)
    assert all(o.origin == "own" for o in origins)
    coherent = sum(any(p.coherent for p in o.partners) for o in origins)
    # alpha = 0.05 per feature (Sidak over the five partners): about 12 of 240 expected
    assert coherent <= 24


def test_features_from_suggestions_and_annotation():
    suggestions = {
        "accel_x": [{"term": "sinusoid", "params": {"A": 0.01, "f": LINE_F}, "significant": True,
                     "why": "A line."},
                    {"term": "resonance", "params": {"sigma": 0.01, "f0": 14.0, "Q": 4.0},
                     "significant": True, "why": "A resonance."},
                    {"term": "white", "params": {"N": 1.0}, "significant": True, "why": ""}]}
    feats = features_from_diagnosis("accel_x", suggestions["accel_x"])
    assert [(f.term, f.f_hz) for f in feats] == [("sinusoid", LINE_F), ("resonance", 14.0)]
    assert feats[1].band_hz == pytest.approx((14.0 - 1.75, 14.0 + 1.75))
    x, _ = bench_record(13)
    cs = cross_spectra(x, 100.0, NAMES, nperseg=4096)
    origins = classify(feats, cs, means=dict(zip(NAMES, x.mean(0), strict=True)))
    assert annotate(suggestions, origins) == 2
    assert suggestions["accel_x"][0]["why"].startswith("A line. Common, not accel_x's own")
    assert suggestions["accel_x"][0]["origin"] == "common"
    assert suggestions["accel_x"][1]["origin"] == "own"
    assert channel_kind("imu2/accel_y") == "accel" and channel_device("imu2/accel_y") == "imu2"
    assert channel_kind("temperature") == "temperature"


def _adis(shared_data, run: int) -> tuple[np.ndarray, dict]:
    d = np.load(shared_data / "adis16405" / f"run{run}.npz")
    x = np.column_stack([d["gyro_counts"] * float(d["gyro_scale_dps"]) * np.pi / 180,
                         d["accel_counts"] * float(d["accel_scale_g"]) * 9.80665])
    return x, dict(zip(NAMES, x.mean(0), strict=True))


def test_adis16405_run1_line_common_resonances_own(shared_data):
    from imunoise.analysis import evidence

    x, means = _adis(shared_data, 1)
    cs = cross_spectra(x, 100.0, NAMES, nperseg=8192)
    feats = []
    for k, ch in enumerate(NAMES[3:]):
        found = evidence.spectral_lines([x[:, 3 + k]], 100.0, units="m/s^2")
        feats += features_from_diagnosis(ch, {"findings": [found]})[:1]
        # the resonances the loop fits near 13.9 and 20.7 Hz, taken as Q = 2 bands
        feats += [SpectralFeature(ch, "resonance", f0, resonance_band(f0, 2.0))
                  for f0 in (13.9, 20.7)]
    feats.append(SpectralFeature("gyro_z", "resonance", 20.7, resonance_band(20.7, 2.0)))
    origins = classify(feats, cs, means=means)
    lines = [o for o in origins if o.feature.term == "sinusoid"]
    assert len(lines) == 3
    for o in lines:
        assert o.feature.f_hz == pytest.approx(0.564, abs=0.002)
        assert o.origin == "common"
        assert set(o.common_with) >= {"accel_x", "accel_y", "accel_z"} - {o.feature.channel}
    msc = {tuple(sorted((o.feature.channel, p.channel))): p.msc
           for o in lines for p in o.partners}
    assert msc[("accel_x", "accel_y")] == pytest.approx(0.963, abs=0.002)
    assert msc[("accel_x", "accel_z")] == pytest.approx(0.940, abs=0.002)
    assert msc[("accel_y", "accel_z")] == pytest.approx(0.908, abs=0.002)
    for o in origins:
        if o.feature.term == "resonance":
            assert o.origin == "own", o.why


def test_two_sensors_on_one_bench_common_line_is_environment_own_line_is_own():
    a, _ = bench_record(31, n=1 << 16)
    b, _ = bench_record(32, n=1 << 16, own=False)
    # the same bench line reaches both sensors (same phase: one bench)
    t = np.arange(1 << 16) / 100.0
    line = 0.01 * np.sin(2 * np.pi * 0.8 * t)
    a[:, 3] += line
    b[:, 3] += 0.7 * line
    names = [f"imu1/{c}" for c in NAMES[3:]] + [f"imu2/{c}" for c in NAMES[3:]]
    x = np.column_stack([a[:, 3:], b[:, 3:]])
    cs = cross_spectra(x, 100.0, names, nperseg=4096)
    common, own = classify([_line("imu1/accel_x", 0.8), _line("imu1/accel_z", 3.3)], cs)
    assert common.origin == "common" and "imu2/accel_x" in common.common_with
    assert "more than one sensor" in common.reading
    assert own.origin == "own"


def test_rocking_with_some_axes_only_is_still_a_rotation(bench):
    x, _, _ = bench
    names = ["gyro_x", "accel_x", "accel_y"]
    sub = x[:, [0, 3, 4]]
    cs = cross_spectra(sub, 100.0, names, nperseg=4096)
    (o,) = classify([_line("accel_y", ROCK_F)], cs,
                    means=dict(zip(names, sub.mean(0), strict=True)))
    assert o.origin == "common" and o.common_with == ["gyro_x"]
    assert "rotation" in o.reading
    # gravity assumed along -z when the z accelerometer is not among the channels
    assert o.motion["rotation_explains"] == pytest.approx(1.0, abs=0.1)
