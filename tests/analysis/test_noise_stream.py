"""Each simulator reproduces its own Allan variance and PSD (mean over seeds).

Tolerance at each octave tau: 3.5 standard errors of the mean over the seeds, i.e. the
estimator's own spread, not a fixed percentage.
"""

import math

import numpy as np
import pytest
from scipy.signal import welch

from imunoise.analysis.noise_stream import (
    NoiseStream,
    flicker_avar,
    flicker_flat_band,
    flicker_psd,
    simulate,
)
from imunoise.analysis.terms import BIAS_INSTABILITY_FACTOR, get_term
from tests._avar_batch import oavar_rows

FS = 100.0
SEEDS = 300
N_SAMPLES = 4096
M = 2 ** np.arange(0, 11)  # tau = 0.01 .. 10.24 s, up to a quarter of the record

CASES = {
    "white": {"N": 3e-3},
    "quantization": {"Q": 2e-4},
    "bias_instability": {"B": 5e-3},
    "random_walk": {"K": 4e-3},
    "gauss_markov": {"sigma": 4e-3, "T": 0.5},
    "sinusoid": {"A": 2e-3, "f": 3.7},
}


def _runs(name, params, seeds=SEEDS, n=N_SAMPLES):
    return np.stack([NoiseStream([(name, params)], FS, seed).take(n) for seed in range(seeds)])


@pytest.mark.parametrize("name", list(CASES))
def test_simulator_reproduces_its_allan_formula(name):
    params = CASES[name]
    x = _runs(name, params)
    av = oavar_rows(x, M)
    mean = av.mean(axis=0)
    sem = av.std(axis=0, ddof=1) / math.sqrt(SEEDS)
    tau = M / FS
    if name == "bias_instability":
        expected = flicker_avar(tau, FS, **params)
    else:
        expected = get_term(name).avar(tau, FS, **params)
    z = (mean - expected) / sem
    assert np.all(np.abs(z) < 3.5), dict(zip(tau, np.round(z, 2), strict=True))


def test_ramp_and_temperature_are_exact():
    x = NoiseStream([("rate_ramp", {"R": 1e-4})], FS, 1).take(N_SAMPLES)
    np.testing.assert_allclose(oavar_rows(x, M)[0], get_term("rate_ramp").avar(M / FS, FS, R=1e-4),
                               rtol=1e-8)
    temp = 25 + np.cumsum(np.random.default_rng(3).standard_normal(N_SAMPLES)) * 0.01
    y = NoiseStream([("temperature", {"coef": 2e-3})], FS, 1).take(N_SAMPLES, temperature=temp)
    np.testing.assert_allclose(y, 2e-3 * (temp - temp[0]))
    tav = oavar_rows(temp, M)[0]
    np.testing.assert_allclose(oavar_rows(y, M)[0], get_term("temperature").avar(
        M / FS, FS, coef=2e-3, temp_avar=tav), rtol=1e-9)


def test_flicker_simulator_is_flat_in_its_documented_band():
    lo, hi = flicker_flat_band(FS)
    tau = np.unique(np.round(np.geomspace(lo * FS, hi * FS, 200))) / FS
    ratio = flicker_avar(tau, FS, 1.0) / BIAS_INSTABILITY_FACTOR
    assert ratio.min() > 0.965 and ratio.max() < 1.005
    f = np.geomspace(1e-4, 10.0, 300)
    ratio = flicker_psd(f, FS, 1.0) / get_term("bias_instability").psd(f, FS, B=1.0)
    assert ratio.min() > 0.95 and ratio.max() < 1.05


def test_blocks_equal_one_long_run_for_every_term():
    temp = np.linspace(20, 30, 10000)
    model = [(name, p) for name, p in CASES.items()] + [
        ("rate_ramp", {"R": 1e-5}), ("temperature", {"coef": 1e-3})]
    stream = NoiseStream(model, FS, seed=42)
    blocks = [stream.take(1000, temperature=temp[i * 1000:(i + 1) * 1000]) for i in range(10)]
    whole = NoiseStream(model, FS, seed=42).take(10000, temperature=temp)
    np.testing.assert_array_equal(np.concatenate(blocks), whole)
    # irregular block sizes too, and the batch helper
    stream = NoiseStream(model[:6], FS, seed=7)
    parts = [stream.take(k) for k in (1, 0, 999, 4000, 5000)]
    np.testing.assert_array_equal(np.concatenate(parts), simulate(model[:6], 10000, FS, 7))


def test_seeds_differ_and_bad_input_is_refused():
    a = NoiseStream([("white", {"N": 1e-3})], FS, 1).take(10)
    b = NoiseStream([("white", {"N": 1e-3})], FS, 2).take(10)
    assert not np.allclose(a, b)
    with pytest.raises(ValueError, match="temperature record"):
        NoiseStream([("temperature", {"coef": 1e-3})], FS, 1).take(10)
    with pytest.raises(ValueError, match="unknown term"):
        NoiseStream([("pink", {})], FS, 1)
    with pytest.raises(ValueError, match=r"sinusoid\.f"):
        NoiseStream([("sinusoid", {"A": 1.0, "f": 70.0})], FS, 1)


PSD_CASES = ["white", "quantization", "bias_instability", "random_walk", "gauss_markov"]


@pytest.mark.parametrize("name", PSD_CASES)
def test_simulated_psd_matches_formula(name):
    params = CASES[name]
    seeds, n, nper = 40, 16384, 1024
    x = _runs(name, params, seeds=seeds, n=n)
    f, p = welch(x, fs=FS, nperseg=nper, axis=1, detrend=False)
    # leave the lowest bins (the Hann window leaks steep spectra) and the Nyquist bin (welch
    # does not double it); average 16 neighbouring bins so that few, sharp comparisons remain
    sel = slice(16, 16 + 16 * 30)
    if name == "bias_instability":
        expected = flicker_psd(f[sel], FS, **params)
    else:
        expected = get_term(name).psd(f[sel], FS, **params)
    ratio = (p[:, sel] / expected).reshape(seeds, 30, 16).mean(axis=2)
    z = (ratio.mean(axis=0) - 1.0) / (ratio.std(axis=0, ddof=1) / math.sqrt(seeds))
    assert np.all(np.abs(z) < 3.5), z


def test_sinusoid_line_power():
    x = NoiseStream([("sinusoid", {"A": 2e-3, "f": 3.7})], FS, 0).take(100000)
    f, p = welch(x, fs=FS, nperseg=4096, detrend=False)
    df = f[1] - f[0]
    assert np.sum(p) * df == pytest.approx(0.5 * 2e-3**2, rel=1e-3)
    line = get_term("sinusoid").psd(f, FS, A=2e-3, f=3.7)
    assert np.sum(line) * df == pytest.approx(0.5 * 2e-3**2, rel=1e-12)
    assert f[np.argmax(line)] == pytest.approx(3.7, abs=df)
