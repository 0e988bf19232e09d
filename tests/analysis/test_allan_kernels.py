"""The compiled Allan kernels against the numpy path and against direct sums, and the switch."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from imunoise.analysis import allan_compiled, allan_kernels
from imunoise.analysis.allan import allan
from imunoise.analysis.streaming_allan import StreamingAllan

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def restore_switch():
    previous = allan_kernels.set_enabled(True)
    yield
    allan_kernels.set_enabled(previous)


@pytest.mark.parametrize("kind", ["oadev", "ohdev", "mdev", "noise_id"])
def test_compiled_kernels_are_in_use_here(kind):
    # numba is a runtime dependency: on this environment the compiled path must be the one run
    state = allan_kernels.status(kind)
    assert state["enabled"], state["error"]
    assert state["compile_s"] > 0.0
    assert not allan_kernels.enabled("adev")  # no kernel of its own


@pytest.mark.parametrize("n", [1, 2, 7, 8, 9, 17, 1023, 1024, 1025, 3001])
def test_kernels_equal_direct_sums_at_every_length(n):
    rng = np.random.default_rng(n)
    u = np.cumsum(rng.standard_normal(n + 40))
    for m in (1, 2, 3, 5, 13):
        k2 = u.size - 2 * m
        d2 = u[2 * m :] - 2 * u[m:-m] + u[: k2]
        assert allan_kernels.oadev_sum(u, m, 0, k2) == pytest.approx(float(d2 @ d2), rel=1e-13)
        # a sub-range, as the streaming estimator asks for
        a, b = 3, max(3, k2 - 4)
        ref = float(d2[a:b] @ d2[a:b])
        assert allan_kernels.oadev_sum(u, m, a, b) == pytest.approx(ref, rel=1e-13, abs=0.0)
        k3 = u.size - 3 * m
        d3 = u[3 * m :] - 3 * u[2 * m : 2 * m + k3] + 3 * u[m : m + k3] - u[:k3]
        assert allan_kernels.ohdev_sum(u, m, 0, k3) == pytest.approx(float(d3 @ d3), rel=1e-13)
        lo = rng.standard_normal(u.size) * 1e-17
        hi_d3 = u[3 * m :] - 3 * u[2 * m : 2 * m + k3] + 3 * u[m : m + k3] - u[:k3]
        lo_d3 = lo[3 * m :] - 3 * lo[2 * m : 2 * m + k3] + 3 * lo[m : m + k3] - lo[:k3]
        ref = float((hi_d3 + lo_d3) @ (hi_d3 + lo_d3))
        assert allan_kernels.mdev_sum(u, lo, m) == pytest.approx(ref, rel=1e-13)


def test_empty_range_sums_to_zero():
    u = np.arange(10.0)
    assert allan_kernels.oadev_sum(u, 2, 5, 5) == 0.0
    assert allan_kernels.ohdev_sum(u, 2, 4, 3) == 0.0
    assert allan_kernels.mdev_sum(u, u, 4) == 0.0


@pytest.mark.parametrize("kind", ["oadev", "adev", "mdev", "ohdev"])
def test_compiled_and_numpy_paths_agree(kind, restore_switch):
    # random walk plus white noise on a bias, two segments, clock-like tiny units (scaled
    # by a power of two inside) and ordinary ones
    rng = np.random.default_rng(7)
    n = 200_003
    y = 2e-2 + 1e-3 * rng.standard_normal(n) + 1e-6 * np.cumsum(rng.standard_normal(n))
    for scale in (1.0, 1e-9):
        args = dict(m="all", max_m=40, segment_starts=[0, 70_001], ci=None)
        allan_kernels.set_enabled(True)
        fast = allan(y * scale, 100.0, kind, **args)
        fast_long = allan(y * scale, 100.0, kind, m=30, ci=None)
        allan_kernels.set_enabled(False)
        slow = allan(y * scale, 100.0, kind, **args)
        slow_long = allan(y * scale, 100.0, kind, m=30, ci=None)
        np.testing.assert_array_equal(fast.n_terms, slow.n_terms)
        np.testing.assert_allclose(fast.dev, slow.dev, rtol=1e-12, atol=0)
        np.testing.assert_allclose(fast_long.dev, slow_long.dev, rtol=1e-12, atol=0)


def test_streaming_uses_either_path_alike(restore_switch):
    rng = np.random.default_rng(3)
    y = 1e-3 * rng.standard_normal(60_000) + 5e-3
    curves = []
    for flag in (True, False):
        allan_kernels.set_enabled(flag)
        sa = StreamingAllan(100.0, kinds=("oadev", "ohdev"), m0=64, history_points=4096)
        for a in range(0, y.size, 777):
            sa.update(y[a : a + 777])
        curves.append((sa.curve("oadev", ci=0.683), sa.curve("ohdev", ci=0.683)))
    for fast, slow in zip(*curves, strict=True):
        np.testing.assert_allclose(fast.dev, slow.dev, rtol=1e-12, atol=0)


def test_compile_failure_falls_back_to_numpy(monkeypatch, restore_switch):
    def broken(*_args):
        raise RuntimeError("no code generator")

    rng = np.random.default_rng(11)
    y = rng.standard_normal(5000)
    reference = allan(y, 10.0, "oadev", m="octave", ci=None)
    monkeypatch.setitem(allan_kernels._state, "compiled", {})
    monkeypatch.setitem(allan_kernels._state, "error", {})
    monkeypatch.setitem(allan_kernels._state, "compile_s", {})
    monkeypatch.setattr(allan_kernels, "oadev_sums", broken)
    state = allan_kernels.status("oadev")
    assert not state["enabled"]
    assert "RuntimeError: no code generator" in state["error"]
    fallback = allan(y, 10.0, "oadev", m="octave", ci=None)
    np.testing.assert_allclose(fallback.dev, reference.dev, rtol=1e-12, atol=0)


def test_environment_variable_selects_numpy():
    env = dict(os.environ, IMUNOISE_ALLAN_KERNEL="numpy")
    code = "from analysis import allan_kernels as k; print(k.status()['enabled'])"
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == "False"


def test_short_records_take_the_numpy_path_without_importing_numba():
    # the automatic switch: a command on a short record never pays for loading the kernels
    env = {k: v for k, v in os.environ.items() if k != "IMUNOISE_ALLAN_KERNEL"}
    code = (
        "import sys, numpy as np\n"
        "from imunoise.analysis.allan import allan\n"
        "from imunoise.analysis import allan_kernels as k\n"
        "y = np.random.default_rng(1).standard_normal(50_000)\n"
        "for kind in ('oadev', 'ohdev', 'mdev'):\n"
        "    allan(y, 100.0, kind)\n"
        "print(k._state['switch'], 'numba' in sys.modules, 'llvmlite' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == ["auto", "False", "False"]


def test_the_automatic_switch_goes_by_length(monkeypatch):
    monkeypatch.setitem(allan_kernels._state, "switch", "auto")
    monkeypatch.setattr(allan_kernels, "COMPILED_MIN_POINTS", 4096)
    assert not allan_kernels.enabled("oadev", 4095)
    assert allan_kernels.enabled("oadev", 4096)
    assert allan_kernels.enabled("noise_id")  # no length: the streaming estimator's calls
    allan_kernels.set_enabled(False)
    assert not allan_kernels.enabled("oadev", 10**8)
    allan_kernels.set_enabled(True)
    assert allan_kernels.enabled("mdev", 10)
    with pytest.raises(ValueError, match="True, False or 'auto'"):
        allan_kernels.set_enabled("sometimes")


def test_environment_variable_forces_the_kernels():
    env = dict(os.environ, IMUNOISE_ALLAN_KERNEL="numba")
    code = "from analysis import allan_kernels as k; "\
        "print(k._state['switch'], k.enabled('oadev', 5))"
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=True
    )
    assert out.stdout.split() == ["True", "True"]


def test_running_sum_split_carries_the_exact_prefix_sum():
    # hi + lo against exact rational sums: within about 2^-100 of the sum, far beyond float64
    from fractions import Fraction

    rng = np.random.default_rng(3)
    u = np.cumsum(rng.standard_normal(5000)) * 1e3 + 1e6
    offset = float(u.mean())
    hi, lo = allan_kernels.running_sum_split(u, offset)
    exact = Fraction(0)
    assert hi[0] == 0.0 and lo[0] == 0.0
    for k in range(u.size):
        exact += Fraction(float(u[k] - offset))  # each difference rounded, as numpy's
        if k % 499 == 0 or k == u.size - 1:
            got = Fraction(float(hi[k + 1])) + Fraction(float(lo[k + 1]))
            assert abs(got - exact) <= abs(exact) * Fraction(1, 2**95) + Fraction(1, 2**60)
            assert float(hi[k + 1]) == float(exact)  # hi is the sum rounded once


def test_mdev_of_a_random_walk_is_exact_where_long_double_was_not(restore_switch):
    # at m = 1 the third difference of the prefix sum is the second difference of the phase:
    # the double-double sums give it to 1e-15; the long double ones were 3e-11 off here
    import math

    from imunoise.analysis.allan import _running_sum_split, phase_from_rate

    rng = np.random.default_rng(7)
    w = rng.standard_normal(400_000)
    u = phase_from_rate(np.cumsum(w) * 1e-6 + w * 1e-4)
    u = np.ldexp(u, -int(np.floor(np.log2(np.abs(u).max()))))
    v = u - u.mean()
    d = (v[2:] - 2 * v[1:-1]) + v[:-2]
    exact = math.fsum(d * d)
    hi, lo = _running_sum_split(u)
    assert allan_kernels.mdev_sum(hi, lo, 1) == pytest.approx(exact, rel=1e-13)
    uu = np.concatenate(([0.0], np.cumsum(v, dtype=np.longdouble)))
    h2 = uu.astype(np.float64)
    long_double = allan_kernels.mdev_sum(h2, (uu - h2).astype(np.float64), 1)
    assert long_double == pytest.approx(exact, rel=1e-9)  # the bound of the change


@pytest.mark.parametrize("m", [1, 2, 3, 7, 64])
def test_diff_products_of_strided_views_equal_numpy(m):
    from imunoise.analysis.edf import _diff_products

    rng = np.random.default_rng(m)
    u = np.cumsum(rng.standard_normal(300_001))
    v = u[::m]
    zz, p, s1 = allan_kernels.diff_products(v)
    zz_ref, p_ref = _diff_products(v)
    assert zz == pytest.approx(zz_ref, rel=1e-13)
    assert p == pytest.approx(p_ref, rel=1e-12, abs=1e-12 * zz_ref)
    assert s1 == pytest.approx(float(np.sum(v[1:])), rel=1e-13)


def test_noise_identification_is_the_same_with_and_without_the_kernels(restore_switch):
    from imunoise.analysis.allan import oadev

    rng = np.random.default_rng(11)
    w = rng.standard_normal(600_001)
    for y in (w, np.diff(w), np.cumsum(w) * 1e-3 + w):  # white rate, white phase, random walk
        on = oadev(y, 100.0, m=60)
        allan_kernels.set_enabled(False)
        off = oadev(y, 100.0, m=60)
        allan_kernels.set_enabled(True)
        assert np.array_equal(on.alpha, off.alpha)
        assert np.array_equal(on.edf, off.edf)
        np.testing.assert_allclose(on.dev, off.dev, rtol=1e-13)


def test_sweeps_group_nearby_m_and_share_the_first_window_beyond_a_chunk():
    ms = np.unique(np.round(np.logspace(0, np.log10(2.5e6), 110)).astype(np.int64))
    stops = 10_000_000 - 2 * ms
    stops[5] = 0  # an m without terms is in no sweep
    found = allan_kernels.groups(ms, stops)
    flat = np.concatenate(found)
    assert sorted(flat.tolist()) == [j for j in range(ms.size) if j != 5]
    assert np.all(np.diff(ms[flat]) > 0)
    chunk = allan_compiled._CHUNK
    for g in found:
        assert 1 <= g.size <= allan_compiled.GROUP_MAX
        if ms[g[0]] <= chunk:
            assert ms[g[-1]] - ms[g[0]] <= chunk
    assert any(g.size > 1 and ms[g[0]] > chunk for g in found)


def test_sums_do_not_depend_on_the_grouping():
    u = np.cumsum(np.random.default_rng(4).standard_normal(300_000))
    ms = np.array([1, 3, 40, 900, 17_000, 20_000, 33_000, 70_000], dtype=np.int64)
    stops = u.size - 2 * ms
    together = allan_kernels.oadev_sums(u, ms, stops)
    alone = [allan_kernels.oadev_sums(u, ms[j:j + 1], stops[j:j + 1])[0] for j in range(ms.size)]
    assert together.tolist() == alone
