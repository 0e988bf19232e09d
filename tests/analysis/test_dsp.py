"""The numpy signal primitives give scipy.signal's numbers, and the commands that fit and
diagnose start without importing scipy.signal or scipy.stats."""

import json
import subprocess
import sys

import numpy as np
import pytest
import scipy.signal

from imunoise.analysis import dsp


@pytest.mark.parametrize("n", [1, 2, 7, 64, 1000])
def test_hann_is_the_periodic_window(n):
    np.testing.assert_array_equal(dsp.hann(n), scipy.signal.get_window("hann", n))


def test_lowpass_and_its_response_match_firwin_and_freqz():
    taps = dsp.lowpass_fir(47, 0.3, beta=10.0)
    np.testing.assert_allclose(taps, scipy.signal.firwin(47, 0.3, window=("kaiser", 10.0)),
                               rtol=1e-14, atol=1e-17)
    w = np.linspace(0.0, np.pi, 301)
    _, h = scipy.signal.freqz(taps, worN=w)
    np.testing.assert_allclose(dsp.fir_response(taps, w), h, rtol=1e-12, atol=1e-15)


def test_linear_detrend_matches_scipy_along_either_axis():
    rng = np.random.default_rng(3)
    x = rng.standard_normal((5, 301)) + 4.0 + np.arange(301) * 0.01
    for axis in (0, 1):
        np.testing.assert_allclose(dsp.detrend_linear(x, axis=axis),
                                   scipy.signal.detrend(x, axis=axis, type="linear"),
                                   rtol=0.0, atol=1e-12)


@pytest.mark.parametrize("n, L, step", [(10_000, 256, 128), (4097, 512, 256), (999, 100, 50),
                                        (300_001, 1 << 15, 1 << 14), (5000, 255, 100)])
def test_welch_density_matches_scipy_welch(n, L, step):
    rng = np.random.default_rng(n)
    x = np.cumsum(rng.standard_normal(n)) * 1e-3 + 2.0
    w = dsp.hann(L)
    f, p = dsp.welch_density(x, 100.0, w, step)
    f_ref, p_ref = scipy.signal.welch(x, fs=100.0, window=w, nperseg=L, noverlap=L - step)
    np.testing.assert_allclose(f, f_ref, rtol=1e-15)
    np.testing.assert_allclose(p, p_ref, rtol=1e-10, atol=0.0)


def test_welch_density_refuses_a_record_shorter_than_a_segment():
    with pytest.raises(ValueError, match="fewer than one segment of 64"):
        dsp.welch_density(np.zeros(63), 100.0, 64)


PROBE = """
import runpy, sys
sys.argv = ["imunoise"] + sys.argv[1:]
try:
    runpy.run_module("imunoise", run_name="__main__")
except SystemExit as exc:
    assert not exc.code, exc.code
print(sorted(m for m in sys.modules if m.startswith(("scipy.stats", "scipy.signal"))),
      file=sys.stderr)
"""


@pytest.mark.parametrize("verb", ["fit", "diagnose", "analyze"])
def test_the_analysis_commands_start_without_scipy_stats_or_signal(tmp_path, verb):
    """Both cost half a second to import at every start (see imunoise.analysis.dsp)."""
    rng = np.random.default_rng(1)
    t = np.arange(20_000) / 100.0
    x = 1e-3 * rng.standard_normal(t.size) + 1e-5 * np.cumsum(rng.standard_normal(t.size))
    path = tmp_path / "rest.csv"
    np.savetxt(path, np.column_stack([t, x]), delimiter=",", header="t,gyro_x", comments="")
    model = [] if verb == "analyze" else ["--model", "white,random_walk"]
    p = subprocess.run([sys.executable, "-c", PROBE, verb, str(path), "--channel", "gyro_x",
                        *model, "--json"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    assert json.loads(p.stdout)
    assert p.stderr.strip().splitlines()[-1] == "[]"
