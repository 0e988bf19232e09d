"""The simulated bench: one motion, seen by several simulated sensors through their own axes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from imunoise.analysis.noise_stream import stream_factory
from imunoise.core.units import G0
from imunoise.daq.clock import VirtualClock
from imunoise.daq.devices import open_device
from imunoise.daq.sim.bench import (
    BENCHES,
    Bench,
    BenchMotion,
    BenchPlacement,
    Motion,
    Mount,
    OwnLine,
    bench_named,
)

SWAY_HZ = 0.56
OWN_HZ = 7.7
TILT_AXIS = (math.cos(math.radians(30.0)), math.sin(math.radians(30.0)), 0.0)
TEST_BENCH = Bench(
    name="test",
    motions=(Motion("rotation", TILT_AXIS, line_hz=SWAY_HZ, amplitude=3e-3, label="sway"),
             Motion("translation", (0.0, 0.0, 1.0), band_hz=(2.0, 30.0), density=1e-3)),
    mounts=(Mount(rotation_deg=(0.3, -0.2, 0.0)),
            Mount(rotation_deg=(0.0, 0.0, 90.0), own_lines=(OwnLine("accel", 0, OWN_HZ, 0.03),))),
)


def test_the_motion_is_a_function_of_seed_and_time_alone():
    a = BenchMotion(BENCHES["lab"], seed=4)
    b = BenchMotion(BENCHES["lab"], seed=4)
    whole = a.grid(1000, 20000)
    # another instance, other calls, crossing block boundaries in another order
    part = b.grid(9000, 3000)
    for x, y in zip(whole, part, strict=True):  # equal up to the FFT convolution's rounding
        np.testing.assert_allclose(x[8000:11000], y, rtol=1e-12, atol=1e-12 * np.abs(x).max())
    other = BenchMotion(BENCHES["lab"], seed=5).grid(1000, 20000)
    assert not np.allclose(whole[2], other[2])


def test_a_rotation_band_rate_is_its_angle_derivative():
    bench = Bench("tilt", (Motion("rotation", (1.0, 0.0, 0.0), band_hz=(0.5, 20.0),
                                  density=1e-5),))
    theta, omega, accel = BenchMotion(bench, seed=1).grid(0, 40000)
    fs = bench.rate_hz
    d = (theta[2:, 0] - theta[:-2, 0]) * fs / 2
    np.testing.assert_allclose(omega[1:-1, 0], d, rtol=0, atol=1e-9 * np.abs(d).max())
    assert np.abs(accel).max() == 0
    # the band's level: density 1e-5 rad/sqrt(Hz) between 0.5 and 20 Hz
    f, p = signal.welch(theta[:, 0], fs=fs, nperseg=8192)
    inband = (f > 2) & (f < 15)
    assert np.median(p[inband]) / 2 == pytest.approx(1e-10, rel=0.15)


def test_unknown_bench_names_the_valid_ones():
    with pytest.raises(ValueError, match="lab"):
        bench_named("nope")


def _record(spec: str, position: int, seconds: float) -> dict[str, np.ndarray]:
    """Run a simulated device on the test bench (virtual clock from bench time 0, stamps on
    one wall epoch) and collect its channels by stream."""
    clock = VirtualClock(start=0.0, epoch0=1.0e9)
    acq = open_device(spec, clock=clock, seed=11 + position, noise=stream_factory,
                      bench=BenchPlacement(TEST_BENCH, position, seed=7, epoch=0.0))
    out: dict[str, list[np.ndarray]] = {}
    with acq:
        for block in acq.blocks(seconds):
            if not block.stream.endswith("/imu"):
                continue
            for ch, v in block.channels.items():
                out.setdefault(ch, []).append(v)
            out.setdefault(f"t{block.stream}", []).append(block.t)
        assert acq.stats.dropped == 0
    return {k: np.concatenate(v) for k, v in out.items()}


@pytest.fixture(scope="module")
def two_sensors():
    adis = _record("sim:adis16350", 0, 150.0)
    razor = _record("sim:razor", 1, 150.0)
    return adis, razor


def _line_bin(f: np.ndarray, p: np.ndarray, f_line: float) -> int:
    """The bin that holds a line: the largest PSD within one bin of its frequency."""
    near = np.flatnonzero(np.abs(f - f_line) <= f[1])
    return int(near[np.argmax(p[near])])


def _on_grid(rec: dict[str, np.ndarray], stream: str, ch: str, t: np.ndarray) -> np.ndarray:
    return np.interp(t, rec[f"t{stream}"], rec[ch])


def test_the_common_line_is_coherent_across_sensors_and_an_own_line_is_not(two_sensors):
    adis, razor = two_sensors
    t_a = adis["t/adis16350/imu"]
    t = t_a[(t_a > t_a[0] + 2) & (t_a < t_a[-1] - 2)]
    fs = 102.4
    nper = 1024  # 10 s segments: 0.1 Hz bins, about 27 averages with Welch's overlap
    f = None
    coh = {}
    for a_ch, r_stream, r_ch in (("accel_y", "/razor/adxl345/imu", "accel_x"),
                                 ("accel_x", "/razor/adxl345/imu", "accel_y"),
                                 ("gyro_x", "/razor/itg3200/imu", "gyro_y"),
                                 ("accel_z", "/razor/adxl345/imu", "accel_x")):
        f, c = signal.coherence(_on_grid(adis, "/adis16350/imu", a_ch, t),
                                _on_grid(razor, r_stream, r_ch, t), fs=fs, nperseg=nper)
        coh[(a_ch, r_ch)] = c
    _, p_a = signal.welch(_on_grid(adis, "/adis16350/imu", "accel_y", t), fs=fs, nperseg=nper)
    _, p_r = signal.welch(_on_grid(razor, "/razor/adxl345/imu", "accel_x", t), fs=fs,
                          nperseg=nper)
    sway = _line_bin(f, p_a, SWAY_HZ)
    own = _line_bin(f, p_r, OWN_HZ)
    # the razor sits turned by 90 degrees: its x is the bench's y, its y minus the bench's x
    # Expected coherence s1 s2 / ((1 + s1) (1 + s2)) from each side's line-to-noise ratio s
    # in the bin: about 0.97 on the bench's y (cos 30), 0.9 on its x (sin 30) for the
    # ADIS16350's accelerometer white noise
    assert coh[("accel_y", "accel_x")][sway] > 0.9
    assert coh[("accel_x", "accel_y")][sway] > 0.8
    assert coh[("gyro_x", "gyro_y")][sway] > 0.9
    # the razor's own 7.7 Hz line on its accel x: under independence the coherence of ~27
    # overlapping averages exceeds 0.4 with probability below 1e-3
    assert coh[("accel_z", "accel_x")][own] < 0.4
    assert coh[("accel_y", "accel_x")][own] < 0.4


def test_tilt_shows_gravity_projection_and_rotation_rate_together(two_sensors):
    adis, _ = two_sensors
    fs = 102.4
    x = {ch: adis[ch] for ch in ("gyro_x", "gyro_y", "accel_x", "accel_y")}
    nper = 2048
    f, p_gg = signal.welch(x["gyro_x"], fs=fs, nperseg=nper)
    sway = _line_bin(f, p_gg, SWAY_HZ)
    _, p_ag = signal.csd(x["gyro_x"], x["accel_y"], fs=fs, nperseg=nper)
    # accel_y = g * phi * u_x, gyro_x = dphi/dt * u_x: |H| = g / (2 pi f), 90 degrees apart
    h = p_ag[sway] / p_gg[sway]
    assert abs(h) == pytest.approx(G0 / (2 * np.pi * f[sway]), rel=0.05)
    assert abs(abs(np.angle(h)) - np.pi / 2) < 0.1
    # the gravity projection's ratio between the horizontal axes: -cos(30) / sin(30)
    _, p_xy = signal.csd(x["accel_x"], x["accel_y"], fs=fs, nperseg=nper)
    _, p_xx = signal.welch(x["accel_x"], fs=fs, nperseg=nper)
    ratio = p_xy[sway] / p_xx[sway]
    assert ratio.real == pytest.approx(-1 / math.tan(math.radians(30.0)), rel=0.08)
