"""Steps several channels take together (imunoise.analysis.common_steps): none found in
stationary noise, shared ones found at their time and size, each channel corrected only where
its own contrast shows the step."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from imunoise.analysis.common_steps import GATE_Z, LEVEL, find_common_steps
from imunoise.analysis.noise_stream import simulate

FS = 50.0
N = int(2 * 3600 * FS)
NAMES = ["accel_x", "accel_y", "accel_z"]
# an accelerometer at rest: white noise, flicker and random walk (m/s^2)
MODEL = [("white", {"N": 4.7e-3}), ("bias_instability", {"B": 2.7e-3}),
         ("random_walk", {"K": 2.9e-4})]
ADIS = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "adis16405"


def _noise(seed: int) -> np.ndarray:
    return np.column_stack([simulate(MODEL, N, FS, rng=3 * seed + c) for c in range(3)])


@pytest.mark.parametrize("seed", range(8))
def test_stationary_noise_has_no_steps(seed):
    # the family-wise false-alarm rate is 1e-3 per record: eight seeds find none
    found = find_common_steps(_noise(seed), FS, NAMES)
    assert found.steps == []
    # 7111 boundaries of one-second blocks: 30 s before each, 60 s after (the lasting step's
    # second window); Bonferroni at 1e-3
    assert found.boundaries == 7200 - 30 - 60 + 1
    assert found.threshold == pytest.approx(stats.chi2.isf(1e-3 / 7111, 3), rel=1e-9)


def test_a_wander_the_channels_share_is_not_a_step():
    # a random walk common to the three axes correlates their contrasts; the test allows for
    # the correlation instead of summing three standard scores that move together
    x = _noise(11)
    common = simulate([("random_walk", {"K": 1.5e-3})], N, FS, rng=99)
    found = find_common_steps(x + common[:, None], FS, NAMES)
    assert found.steps == []


def test_shared_steps_are_found_with_their_sizes():
    x = _noise(21)
    t = np.arange(N) / FS
    truth = [(1200.0, {"accel_x": 0.02, "accel_y": -0.015, "accel_z": 0.0}),
             (4100.5, {"accel_x": -0.02, "accel_y": 0.0, "accel_z": 0.025})]
    for t0, sizes in truth:
        x += (t >= t0)[:, None] * np.array([sizes[c] for c in NAMES])
    found = find_common_steps(x, FS, NAMES)
    assert [round(s.t_s) for s in found.steps] == [1200, 4100]
    for step, (t0, sizes) in zip(found.steps, truth, strict=True):
        assert abs(step.t_s - t0) <= 1.0  # one-second blocks
        for c in NAMES:
            sd = abs(step.sizes[c] / step.z[c])  # the contrast's own spread
            assert abs(step.sizes[c] - sizes[c]) < 4.0 * sd, (c, step.sizes[c], sizes[c])
            # each channel corrected only where its own contrast shows the step
            assert step.removed_from(c) == (sizes[c] != 0.0)
        assert step.log10_p < math.log10(LEVEL)  # family-wise, below the detection level
    # the corrected channel keeps no step: its contrast at the steps is within the noise
    fixed = found.corrected(x[:, 0], "accel_x")
    again = find_common_steps(np.column_stack([fixed, x[:, 1:]]), FS, NAMES)
    for s in again.steps:
        assert abs(s.z["accel_x"]) < GATE_Z
    # accel_y loses its first step only: the second left it as it was
    first = found.steps[0]
    change = found.corrected(x[:, 1], "accel_y") - x[:, 1]
    assert np.all(change[:first.index] == 0.0)
    assert np.allclose(change[first.index:], -first.sizes["accel_y"])


def test_a_transient_that_settles_back_is_left_in_the_record():
    # a knock that moves the level and lets it settle back within 10 s: found, and taken out of
    # no channel, since nothing of it lasts
    x = _noise(61)
    t = np.arange(N) / FS
    after = np.clip(t - 2500.0, 0.0, None)
    x += ((t >= 2500.0) * np.exp(-after / 10.0))[:, None] * np.array([0.3, -0.2, 0.25])
    step, = find_common_steps(x, FS, NAMES).steps
    assert round(step.t_s) == 2500 and all(abs(step.jump_z[c]) > 5.0 for c in NAMES)
    assert not any(step.removed_from(c) for c in NAMES)
    assert np.array_equal(find_common_steps(x, FS, NAMES).corrected(x[:, 0], "accel_x"), x[:, 0])


def test_records_without_room_for_the_test_have_no_steps():
    x = _noise(31)
    assert find_common_steps(x[: int(100 * FS)], FS, NAMES).steps == []  # 100 s: too short
    assert find_common_steps(x[:, :1], FS, NAMES[:1]).steps == []  # one channel alone
    bad = x.copy()
    bad[5, 1] = np.nan
    assert find_common_steps(bad, FS, NAMES).steps == []
    flat = x.copy()
    flat[:, 2] = 1.0  # a constant channel has no scale to standardise by
    assert find_common_steps(flat, FS, NAMES).steps == []


def test_segments_are_searched_apart():
    # a gap between two segments is no step, even where the level differs across it
    x = _noise(41)
    x[N // 2:] += 0.05
    starts = np.array([0, N // 2])
    assert find_common_steps(x, FS, NAMES, segment_starts=starts).steps == []
    assert [round(s.t_s) for s in find_common_steps(x, FS, NAMES).steps] == [N // 2 / FS]


@pytest.mark.skipif(not (ADIS / "run1.npz").exists(),
                    reason="../shared/data (ADIS16405 recordings) is not beside this checkout")
def test_adis16405_run1_bench_steps():
    d = np.load(ADIS / "run1.npz")
    a = d["accel_counts"] * float(d["accel_scale_g"]) * 9.80665
    found = find_common_steps(a, float(d["fs_hz"]), NAMES)
    by_time = {round(s.t_s): s for s in found.steps}
    # the knock at 2149 s: all three axes jump at once, 8-10 standard scores each, and settle
    # back part of the way: the lasting step is taken out of accel_z alone
    step = by_time[2149]
    assert [round(step.jump_z[c], 1) for c in NAMES] == [8.1, 8.3, 10.3]
    assert [c for c in NAMES if step.removed_from(c)] == ["accel_z"]
    assert 0.0 < step.sizes["accel_z"] < 0.0251  # the jump itself was 0.0251 m/s^2
    assert len(found.steps) == 8
    assert math.isclose(found.threshold, 35.4, abs_tol=0.1)


def test_a_huge_step_keeps_a_finite_p_value():
    # far beyond the chi-square's floating-point tail: the leading terms of the tail
    x = _noise(51)
    x[N // 3:] += np.array([2.0, -1.5, 1.0])
    step, = find_common_steps(x, FS, NAMES).steps
    assert step.statistic > 1e4
    assert math.isfinite(step.log10_p) and step.log10_p < -1000
