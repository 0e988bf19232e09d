"""Batch Allan API: tau grids, segments, precision on offsets, options and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.allan import adev, allan, default_max_m, mdev, oadev, ohdev, tau_grid


def _white(n: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal(n)


def test_tau_grids():
    np.testing.assert_array_equal(tau_grid(1000, "octave"), [1, 2, 4, 8, 16, 32, 64, 128])
    np.testing.assert_array_equal(
        tau_grid(556989, "decade"),
        [1, 2, 4, 10, 20, 40, 100, 200, 400, 1000, 2000, 4000, 10000, 20000, 40000, 100000],
    )
    np.testing.assert_array_equal(tau_grid(100, "all"), np.arange(1, 26))
    g = tau_grid(10**6, 100)
    assert g[0] == 1 and g[-1] == 250_000 and 80 <= g.size <= 100
    assert np.all(np.diff(g) > 0) and g.dtype == np.int64
    assert default_max_m(19983, "oadev") == 4995 and default_max_m(19983, "adev") == 3996
    with pytest.raises(ValueError, match="unknown tau grid"):
        tau_grid(100, "weekly")


def test_white_noise_levels_and_term_counts():
    y = _white(100_000, 1)
    for fn in (oadev, adev, mdev, ohdev):
        c = fn(y, 50.0, m=np.array([1, 10, 100]))
        # white rate noise of unit variance: ADEV = OHDEV = 1/sqrt(m) (MDEV lower)
        ratio = c.dev * np.sqrt(c.m)
        if fn is mdev:
            assert np.all(ratio[1:] < 0.9)
        else:
            np.testing.assert_allclose(ratio, 1.0, rtol=0.05)
        assert np.all(c.ci_low < c.dev) and np.all(c.dev < c.ci_high)
    c = oadev(y, 50.0, m=np.array([1, 10]))
    np.testing.assert_array_equal(c.n_terms, [100_000 + 1 - 2, 100_000 + 1 - 20])
    np.testing.assert_allclose(c.tau_s, [0.02, 0.2])


def test_segments_pool_sums_and_never_bridge_a_gap():
    y = _white(30_000, 2)
    y[10_000:] += 50.0  # a step at the gap would dominate any term spanning it
    starts = [0, 10_000, 10_003, 25_000]
    c = oadev(y, 1.0, m=np.array([1, 4, 3000]), segment_starts=starts)
    pieces = [y[:10_000], y[10_000:10_003], y[10_003:25_000], y[25_000:]]
    sums = np.zeros(3)
    counts = np.zeros(3, dtype=np.int64)
    for p in pieces:
        part = oadev(p, 1.0, m=np.array([1, 4, 3000]), ci=None)
        for j, m in enumerate([1, 4, 3000]):
            k = np.flatnonzero(part.m == m)
            if k.size:
                sums[j] += part.avar[k[0]] * part.n_terms[k[0]]
                counts[j] += part.n_terms[k[0]]
    np.testing.assert_array_equal(c.n_terms, counts)
    np.testing.assert_allclose(c.avar, sums / counts, rtol=1e-12)
    assert c.dev[0] < 2.0  # the 50 rad/s step was not differenced
    # edf adds over independent segments
    single = oadev(y[10_003:25_000], 1.0, m=np.array([1]), alpha=0)
    assert c.edf[0] > single.edf[0]


@pytest.mark.parametrize("kind", ["oadev", "adev", "mdev", "ohdev"])
def test_a_large_rate_offset_does_not_cost_precision(kind):
    y = _white(400_000, 3) * 1e-3
    a = allan(y, 100.0, kind, m="octave", ci=None)
    b = allan(y + 1e3, 100.0, kind, m="octave", ci=None)
    np.testing.assert_allclose(b.dev, a.dev, rtol=1e-9)


def test_options_ci_none_alpha_and_threads():
    y = _white(50_000, 4)
    full = oadev(y, 10.0)
    bare = oadev(y, 10.0, ci=None)
    np.testing.assert_array_equal(bare.dev, full.dev)
    assert np.all(np.isnan(bare.ci_low)) and np.isnan(bare.ci)
    two = oadev(y, 10.0, workers=2)
    np.testing.assert_array_equal(two.dev, full.dev)
    fixed = oadev(y, 10.0, alpha=-1)
    assert np.all(fixed.alpha == -1)
    wide = oadev(y, 10.0, ci=0.95)
    assert np.all(wide.ci_high > full.ci_high) and np.all(wide.ci_low < full.ci_low)
    assert set(full.to_dict()) >= {"tau_s", "dev", "ci_low", "ci_high", "edf", "alpha"}


def test_bad_input_is_refused_with_a_clear_message():
    y = _white(1000)
    y[5] = np.inf
    with pytest.raises(ValueError, match="non-finite value at index 5"):
        oadev(y, 1.0)
    with pytest.raises(ValueError, match="1-D"):
        oadev(np.zeros((10, 2)), 1.0)
    with pytest.raises(ValueError, match="sampling rate"):
        oadev(_white(100), -1.0)
    with pytest.raises(ValueError, match="unknown deviation kind"):
        allan(_white(100), 1.0, "tdev")
    with pytest.raises(ValueError, match="averaging factors"):
        oadev(_white(100), 1.0, m=[0, 1])
    with pytest.raises(ValueError, match="segment_starts"):
        oadev(_white(100), 1.0, segment_starts=[0, 50, 20])
    empty = oadev(np.zeros(0), 1.0)
    assert empty.m.size == 0
    tiny = oadev(_white(2), 1.0, m=[1, 5])
    np.testing.assert_array_equal(tiny.m, [1])  # 3 phase points: one term at m = 1
    assert tiny.n_terms[0] == 1 and np.isfinite(tiny.ci_high[0])


def test_public_estimators_have_static_signatures_with_formula_and_reference():
    import inspect

    for fn in (oadev, adev, mdev, ohdev):
        params = list(inspect.signature(fn).parameters)
        assert params[:4] == ["rate", "fs_hz", "m", "segment_starts"], fn.__name__
        assert "NIST SP 1065" in fn.__doc__ and "sigma^2" in fn.__doc__, fn.__name__
        assert fn.__code__.co_filename.endswith("allan.py") and fn.__name__ in (
            "oadev", "adev", "mdev", "ohdev")
