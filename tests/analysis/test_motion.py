"""Motion detection: still records (with bias instability, random walk and spikes) never move;
a shock moves its window; a robot that turns and drives is found where and as much as it
moved."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.motion import MotionWindows, detect_motion
from imunoise.analysis.noise_stream import simulate

FS = 100.0
GYRO_MODEL = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
              ("random_walk", {"K": 2e-5})]
ACCEL_MODEL = [("white", {"N": 2e-3}), ("bias_instability", {"B": 2e-4}),
               ("random_walk", {"K": 5e-5})]


def still_record(seconds: float, seed: int, gyro_model=GYRO_MODEL, accel_model=ACCEL_MODEL):
    n = int(seconds * FS)
    g = np.column_stack([simulate(gyro_model, n, FS, rng=10 * seed + i) for i in range(3)])
    a = np.column_stack([simulate(accel_model, n, FS, rng=10 * seed + 5 + i) for i in range(3)])
    return g, a + [0.0, 0.0, 9.80665]


@pytest.mark.parametrize("seed", range(4))
def test_a_still_half_hour_with_wandering_bias_never_moves(seed):
    """Bias instability and a rate random walk ten times a good MEMS gyro's, and a spike on
    every axis (a corrupt frame): no window moves (0 false alarms in 4 x 1800 windows)."""
    g, a = still_record(1800, seed)
    g[100_000] += 0.15  # one sample on six axes: an outlier, not motion
    a[100_000] += 2.0
    m = detect_motion(FS, g, a)
    assert not m.moved, m.describe()
    assert m.still_seconds() == pytest.approx(1800, abs=1)


def test_a_robot_that_turns_rests_tilted_and_drives_is_found():
    g, a = still_record(300, seed=9)
    t = np.arange(g.shape[0]) / FS
    turn = (t >= 60) & (t < 80)  # a smooth 90 deg turn about z in 20 s
    g[turn, 2] += np.pi / 2 / 20 * (1 - np.cos(2 * np.pi * (t[turn] - 60) / 20))
    tilt = t >= 80  # it stops on a 5 deg slope: gravity shifts into x
    a[tilt, 0] += 9.80665 * np.sin(np.radians(5))
    drive = (t >= 180) & (t < 220)  # driving: vibration and accelerations
    rng = np.random.default_rng(4)
    g[drive] += rng.normal(0, 0.05, (drive.sum(), 3))
    a[drive] += rng.normal(0, 0.8, (drive.sum(), 3))
    m = detect_motion(FS, g, a)
    moving = [(s.start / FS, s.stop / FS) for s in m.moving]
    assert len(moving) == 2, m.describe()
    (a0, b0), (a1, b1) = moving
    assert 57 <= a0 <= 61 and 79 <= b0 <= 83  # within a window (1 s) plus settling
    assert 177 <= a1 <= 181 and 219 <= b1 <= 223
    assert np.degrees(m.moving[0].peak_rate) == pytest.approx(9.0, rel=0.1)  # 2 x 4.5 deg/s
    # 60 s of motion, each stretch widened by its settling windows
    assert len(m.still) == 3 and m.still_seconds() == pytest.approx(300 - 60 - 4, abs=3)
    assert "moved in 2 stretch(es)" in m.describe()

    # fed in blocks of any size (a file read a batch at a time), the same stretches exactly
    for size in (1, 37, 100, 4096, g.shape[0]):
        acc = MotionWindows(FS, 3, 3)
        for i in range(0, g.shape[0], size):
            acc.update(list(g[i:i + size].T), list(a[i:i + size].T))
        assert acc.motion() == m, size


def _ring(n: int, start: int, amplitude: float) -> np.ndarray:
    """A blow's ringing: a 25 Hz decaying oscillation of 0.3 s from ``start``."""
    t = np.arange(30) / FS
    out = np.zeros(n)
    out[start:start + 30] = amplitude * np.exp(-t / 0.08) * np.sin(2 * np.pi * 25 * t)
    return out


def test_a_shock_moves_its_window_and_a_burst_on_one_axis_does_not():
    """Half a g ringing on two accelerometer axes and the gyro's x for 0.3 s, 900.4 s into a
    still record: the shock's window and its two neighbours are cut, the rest is still. The
    same ringing on one axis only is an outlier burst, and nothing moves."""
    g, a = still_record(1800, seed=5)
    n, at = g.shape[0], 90_040
    one = a.copy()
    one[:, 2] += _ring(n, at, 5.0)
    assert not detect_motion(FS, g, one).moved
    a[:, 0] += _ring(n, at, 2.0)
    a[:, 2] += _ring(n, at, 5.0)
    g[:, 0] += _ring(n, at, 0.3)
    m = detect_motion(FS, g, a)
    assert [(s.start, s.stop, s.shock) for s in m.moving] == [(89_900, 90_200, True)]
    assert m.still_seconds() == pytest.approx(1797, abs=0.01)
    assert "(a shock)" in m.describe()
    for size in (1, 333, g.shape[0]):  # fed in blocks: the same stretches
        acc = MotionWindows(FS, 3, 3)
        for i in range(0, n, size):
            acc.update(list(g[i:i + size].T), list(a[i:i + size].T))
        assert acc.motion() == m, size


def test_a_record_that_never_rests_has_no_still_stretch():
    g, a = still_record(120, seed=2)
    rng = np.random.default_rng(1)
    g += rng.normal(0, 0.3, g.shape)
    a += rng.normal(0, 2.0, a.shape)
    m = detect_motion(FS, g, a)
    assert m.moved and m.still == ()


def test_real_still_recordings_do_not_move(shared_data):
    for run in range(1, 7):
        d = np.load(shared_data / "adis16405" / f"run{run}.npz")
        g = d["gyro_counts"] * float(d["gyro_scale_dps"]) * np.pi / 180
        a = d["accel_counts"] * float(d["accel_scale_g"]) * 9.80665
        m = detect_motion(100.0, g, a)
        if run != 4:
            assert not m.moved, run
            continue
        # run 4 holds a real shock, 4046 s in: its window and the two beside it move
        assert [(s.start, s.stop, s.shock) for s in m.moving] == [(404_500, 404_800, True)]
        assert m.describe().endswith("4045.0-4048.0 s (a shock)")
        # on one axis the same samples are an outlier burst, not a shock
        assert not detect_motion(100.0, accel=a[:, 2]).moved
    d = np.load(shared_data / "galaxy_s5" / "galaxy_s5_static_10hz.npz")
    assert not detect_motion(10.0, d["gyro"], d["accel"]).moved
    d = np.load(shared_data / "mtig_outliers" / "gyro_x.npz")  # a hundred 10-sigma outliers
    assert not detect_motion(100.0, d["gyro_x"][:, None]).moved


@pytest.mark.parametrize("w", [32, 100, 101])
def test_window_statistics_are_the_medians_numpy_defines(w):
    # the windows are sorted, not put through np.median: the same doubles, NaN included
    from imunoise.analysis.motion import SHOCK_SAMPLES, _spread_and_centre

    rng = np.random.default_rng(w)
    cols = [rng.normal(0.0, 1e-3, 50 * w + 7), np.round(rng.normal(0.0, 3.0, 50 * w + 7)),
            rng.standard_t(2, 50 * w + 7)]
    cols[2][[3, 5 * w + 1]] = np.nan  # two windows of one axis hold a NaN
    spread, centre, reach = _spread_and_centre(cols, w)
    win = np.stack([c[:50 * w].reshape(50, w) for c in cols], axis=1)
    with np.errstate(invalid="ignore"):
        med = np.median(win, axis=2)
        dev = np.abs(win - med[:, :, None])
        want_spread = 1.4826 * np.median(dev, axis=2).max(axis=1)
        want_reach = np.partition(dev, w - SHOCK_SAMPLES, axis=2)[:, :, w - SHOCK_SAMPLES]
    assert np.array_equal(centre, med, equal_nan=True)
    assert np.array_equal(spread, want_spread, equal_nan=True)
    assert np.array_equal(reach, want_reach, equal_nan=True)
    assert np.isnan(centre[0, 2]) and np.isnan(spread[5]) and not np.isnan(spread[1])
