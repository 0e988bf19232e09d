"""StreamingAllan: equal to the batch estimator where exact, close where strided, bounded."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.allan import allan
from imunoise.analysis.streaming_allan import StreamingAllan, default_streaming_grid
from tests.shared_paths import SHARED_DATA

RUN1 = SHARED_DATA / "adis16405/run1.npz"


def _signal(n: int, seed: int) -> np.ndarray:
    """White rate noise plus a rate random walk and a large constant bias (rad/s)."""
    rng = np.random.default_rng(seed)
    return 0.3 + 0.01 * rng.standard_normal(n) + 1e-4 * np.cumsum(rng.standard_normal(n))


def _feed(sa: StreamingAllan, y: np.ndarray, starts, rng, max_block: int) -> None:
    bounds = [*list(starts[1:]), y.size]
    pos = 0
    for b in bounds:
        while pos < b:
            k = min(b - pos, int(rng.integers(1, max_block)))
            sa.update(y[pos : pos + k])
            pos += k
        if b < y.size:
            sa.new_segment()


@pytest.mark.parametrize("kind", ["oadev", "ohdev"])
def test_exact_part_equals_batch_with_gaps_and_odd_blocks(kind):
    y = _signal(300_000, 1)
    starts = np.array([0, 100_000, 100_050, 200_000])  # one segment only 50 samples long
    sa = StreamingAllan(100.0, kinds=(kind,), m0=512, history_points=4096)
    _feed(sa, y, starts, np.random.default_rng(2), 5000)
    assert sa.n_samples == y.size
    c = sa.curve(kind)
    ref = allan(y, 100.0, kind, m=c.m, segment_starts=starts)
    exact = c.m <= 512
    assert exact.sum() >= 20 and (~exact).sum() >= 10
    np.testing.assert_allclose(c.dev[exact], ref.dev[exact], rtol=1e-9)
    np.testing.assert_array_equal(c.n_terms[exact], ref.n_terms[exact])
    assert c.exact_upto_m == 512
    # strided part: well inside the batch interval (here the stride is 32)
    half = (ref.ci_high - ref.ci_low) / 2
    assert np.all(np.abs(c.dev[~exact] - ref.dev[~exact]) <= half[~exact] / 5)


def test_curve_at_any_moment_is_the_batch_curve_of_the_prefix():
    y = _signal(50_000, 3)
    sa = StreamingAllan(200.0, m0=1024)
    for stop in (7, 1000, 20_001, 50_000):
        sa.update(y[sa.n_samples : stop])
        c = sa.curve()
        ref = allan(y[:stop], 200.0, "oadev", m=c.m)
        np.testing.assert_allclose(c.dev, ref.dev, rtol=1e-9)
        np.testing.assert_allclose(c.tau_s, c.m / 200.0)


def test_update_copies_the_callers_buffer():
    y = _signal(10_000, 4)
    sa = StreamingAllan(100.0, m0=256)
    buf = np.empty(100)
    for a in range(0, y.size, 100):
        buf[:] = y[a : a + 100]
        sa.update(buf)
    buf[:] = np.nan
    ref = allan(y, 100.0, "oadev", m=sa.curve().m)
    np.testing.assert_allclose(sa.curve().dev, ref.dev, rtol=1e-9)


@pytest.fixture(scope="module")
def adis_gyro():
    if not RUN1.is_file():
        pytest.skip(f"reference data {RUN1} not present")
    with np.load(RUN1) as d:
        return np.deg2rad(d["gyro_counts"][:, 1] * float(d["gyro_scale_dps"])), float(d["fs_hz"])


@pytest.mark.parametrize("history_points", [1 << 18, 1 << 12])
def test_strided_part_within_a_fifth_of_the_interval_on_adis16405(adis_gyro, history_points):
    y, fs = adis_gyro
    sa = StreamingAllan(fs, m0=4096, history_points=history_points)
    for a in range(0, y.size, 250_000):
        sa.update(y[a : a + 250_000])
    c = sa.curve()
    ref = allan(y, fs, "oadev", m=c.m)
    strided = c.m > 4096
    assert strided.sum() >= 20
    half = (ref.ci_high - ref.ci_low) / 2
    ratio = np.abs(c.dev - ref.dev) / half
    assert np.all(ratio[strided] <= 0.2), ratio[strided].max()
    np.testing.assert_allclose(c.dev[~strided], ref.dev[~strided], rtol=1e-9)
    # 1e6 samples in 2^12 values of history: stride 256; all grid m stay multiples of it
    if history_points == 1 << 12:
        assert sa._stride == 256
    np.testing.assert_array_equal(c.m, ref.m)


def test_hundred_million_samples_in_bounded_state():
    sa = StreamingAllan(1000.0, m0=4096, m_grid=1 << np.arange(27))
    rng = np.random.default_rng(5)
    block = 1 << 21
    sizes = []
    n_total = 100_000_000
    fed = 0
    while fed < n_total:
        k = min(block, n_total - fed)
        sa.update(rng.standard_normal(k))
        fed += k
        sizes.append(sa.state_nbytes)
    assert sa.n_samples == n_total
    # the bound depends on the configuration only, not on the record length
    assert sa.state_bound_nbytes < 8 * 1024 * 1024
    assert max(sizes) <= sa.state_bound_nbytes
    c = sa.curve(ci=0.999)
    # unit white noise: ADEV(tau) = 1/sqrt(m) inside its 99.9 % interval at every tau
    expected = 1.0 / np.sqrt(c.m)
    assert np.all(c.ci_low <= expected) and np.all(expected <= c.ci_high)
    assert c.m.max() == 1 << 24  # n // 4 limits the grid as in the batch estimator
    assert np.all(c.alpha == 0)


def test_bad_blocks_are_refused_and_change_nothing():
    sa = StreamingAllan(100.0, m0=64)
    y = _signal(5000, 6)
    sa.update(y)
    before = sa.curve().dev.copy()
    bad = y[:100].copy()
    bad[17] = np.nan
    with pytest.raises(ValueError, match="non-finite value at index 17"):
        sa.update(bad)
    with pytest.raises(ValueError, match="1-D"):
        sa.update(np.zeros((3, 2)))
    assert sa.n_samples == 5000
    np.testing.assert_array_equal(sa.curve().dev, before)
    sa.update(np.array([], dtype=np.float64))
    assert sa.n_samples == 5000


def test_configuration_errors():
    with pytest.raises(ValueError, match="streaming supports"):
        StreamingAllan(100.0, kinds=("mdev",))
    with pytest.raises(ValueError, match="sampling rate"):
        StreamingAllan(0.0)
    sa = StreamingAllan(100.0)
    with pytest.raises(ValueError, match="not accumulated"):
        sa.curve("ohdev")
    empty = sa.curve()
    assert empty.m.size == 0


def test_default_grid_values_are_multiples_of_large_powers_of_two():
    g = default_streaming_grid(1 << 30)
    assert np.all(np.diff(g) > 0)
    big = g[g > 7]
    # lowest set bit of each value is at least a quarter of it
    low_bit = big & -big
    assert np.all(low_bit * 8 > big)
    assert np.all(np.diff(np.log2(big)) < 0.33)


def test_streaming_noise_id_matches_batch_on_random_walk():
    rng = np.random.default_rng(7)
    y = np.cumsum(rng.standard_normal(400_000))  # rate random walk: alpha = -2
    sa = StreamingAllan(10.0, m0=1024, history_points=1 << 14)
    sa.update(y)
    c = sa.curve()
    ref = allan(y, 10.0, "oadev", m=c.m)
    assert np.mean(c.alpha == ref.alpha) >= 0.9
    assert np.all(c.alpha[: c.m.size // 2] == -2)


def test_streaming_b1_noise_id_at_the_longest_taus_equals_batch():
    """Taus with fewer than 30 averages: both sides use the B1 ratio on the same m-averages
    (the streaming ones from the strided history), so they name the same noise type."""
    rng = np.random.default_rng(11)
    n = 300_000
    y = 0.02 * np.cumsum(rng.standard_normal(n)) / np.sqrt(n) + rng.standard_normal(n)
    sa = StreamingAllan(10.0, m0=256, history_points=1 << 14)
    for block in np.array_split(y, 7):
        sa.update(block)
    c = sa.curve()
    ref = allan(y, 10.0, "oadev", m=c.m)
    few = (n // c.m) < 30
    assert few.sum() >= 3
    assert len(set(ref.alpha[few].tolist())) > 1  # identified per tau, not carried over
    np.testing.assert_array_equal(c.alpha[few], ref.alpha[few])


def test_segments_of_different_strides_pool_as_the_batch_estimator():
    # A long segment (strided history, stride 2) beside shorter exact ones: each segment's
    # strided mean counts with the full estimate's number of terms, and noise identification
    # reads the longest segment, so deviations, term counts, alphas and edf all equal the
    # batch estimator's (the strided terms of white + random-walk data differ from the full
    # set by far less than 1e-3 at m >= 8192).
    rng = np.random.default_rng(1)
    lengths = [100, 800, 510_400, 86_200]
    segs = [rng.normal(0, 8, n) + np.cumsum(rng.normal(0, 0.02, n)) + 5 * i
            for i, n in enumerate(lengths)]
    ref = allan(np.concatenate(segs), 100.0, "oadev", m="octave",
                segment_starts=np.cumsum([0] + lengths[:-1]))
    sa = StreamingAllan(100.0, m_grid=1 << np.arange(41))
    for i, seg in enumerate(segs):
        if i:
            sa.new_segment()
        for a in range(0, seg.size, 3000):
            sa.update(seg[a:a + 3000])
    c = sa.curve()
    assert sa._longest_closed is not None and sa._longest_closed.stride == 2
    np.testing.assert_array_equal(c.m, ref.m)
    np.testing.assert_array_equal(c.n_terms, ref.n_terms)
    np.testing.assert_allclose(c.dev[c.m <= 4096], ref.dev[ref.m <= 4096], rtol=1e-9)
    np.testing.assert_allclose(c.dev, ref.dev, rtol=1e-3)
    np.testing.assert_array_equal(c.alpha, ref.alpha)
    np.testing.assert_allclose(c.edf, ref.edf, rtol=1e-12)
