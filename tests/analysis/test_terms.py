import math

import numpy as np
import pytest

from imunoise.analysis import terms
from imunoise.analysis.terms import TERM_NAMES, TermError, get_term, parse_terms, validate_params

CONTRACT = {
    "white": ("N",), "quantization": ("Q",), "bias_instability": ("B",), "random_walk": ("K",),
    "rate_ramp": ("R",), "gauss_markov": ("sigma", "T"), "sinusoid": ("A", "f"),
    "temperature": ("coef",),
}
GYRO_UNITS = {"N": "rad/s/sqrt(Hz)", "Q": "rad", "B": "rad/s", "K": "rad/s/sqrt(s)",
              "R": "rad/s^2", "sigma": "rad/s", "T": "s", "A": "rad/s", "f": "Hz",
              "coef": "rad/s/degC"}


def test_registry_matches_contract_vocabulary_and_units():
    # the contract's vocabulary comes first, in its order; terms added since follow it
    assert TERM_NAMES[:len(CONTRACT)] == tuple(CONTRACT)
    assert set(TERM_NAMES[len(CONTRACT):]) == {"resonance", "wandering_resonance",
                                                "antiresonance", "moving_average", "bartlett",
                                                "lowpass", "chain_filter"}
    for name, params in CONTRACT.items():
        term = get_term(name)
        assert term.param_names == params
        for p in term.params:
            assert terms.param_unit(p, "rad/s") == GYRO_UNITS[p.name]
        assert len(term.explanation) > 120 and term.effect


def test_accelerometer_units_replace_rad_by_m_per_s():
    t = get_term("white").params[0]
    assert terms.param_unit(t, "m/s^2") == "m/s^2/sqrt(Hz)"
    assert terms.param_unit(get_term("quantization").params[0], "m/s^2") == "m/s"
    assert terms.param_unit(get_term("rate_ramp").params[0], "m/s^2") == "m/s^3"


def test_unknown_terms_and_out_of_range_params_are_named():
    with pytest.raises(TermError, match="flicker.*valid terms: white"):
        parse_terms("white,flicker")
    with pytest.raises(TermError, match=r"gauss_markov\.T = -1"):
        validate_params("gauss_markov", {"sigma": 1e-3, "T": -1.0})
    with pytest.raises(TermError, match=r"sinusoid\.f = 60 outside"):
        validate_params("sinusoid", {"A": 1e-3, "f": 60.0}, fs_hz=100.0)
    with pytest.raises(TermError, match="unknown parameter.*X"):
        validate_params("white", {"N": 1e-3, "X": 2.0})
    with pytest.raises(TermError, match="missing"):
        validate_params("white", {})
    validate_params("temperature", {"coef": -1e-3})


def _brute_avar(r, m):
    """AVAR of a stationary sampled process with autocovariance r(j), j = 0..2m."""
    j = np.arange(1, 2 * m + 1)
    c = np.where(j <= m, 2 * m - 3 * j, j - 2 * m)
    return (2 * m * r(0) + 2 * np.sum(c * r(j))) / (2 * m * m)


def test_gauss_markov_discrete_form_is_exact():
    fs, sigma, T = 100.0, 2e-3, 0.7
    a = math.exp(-1 / (fs * T))
    ms = np.array([1, 2, 3, 7, 64, 513, 4096])
    exact = get_term("gauss_markov").avar(ms / fs, fs, sigma=sigma, T=T)
    brute = [_brute_avar(lambda j: sigma**2 * a ** np.abs(j), m) for m in ms]
    np.testing.assert_allclose(exact, brute, rtol=1e-10)
    # very long correlation time: no cancellation; tends to sigma^2 m b (2m^2+1)/(3m^2) . . .
    b = 1e-8
    shape = terms.ar1_avar_shape(np.array([1.0, 10.0]), b)
    np.testing.assert_allclose(shape, [b, b * 201 / 30], rtol=1e-5)
    for x in (1e-7, 1e-6, 1e-5, 1e-3):  # both sides of the switch to the expansion
        m = 50.0
        ref = _brute_avar(lambda j, bb=x / m: np.exp(-bb * np.abs(j)), 50)
        assert terms.ar1_avar_shape(np.array([m]), x / m)[0] == pytest.approx(ref, rel=1e-5)


def test_sinusoid_discrete_form_is_exact_and_tends_to_continuous():
    fs, A, f = 100.0, 0.3, 7.3
    ms = np.array([1, 2, 5, 17, 100])
    exact = get_term("sinusoid").avar(ms / fs, fs, A=A, f=f)
    brute = [_brute_avar(lambda j: 0.5 * A * A * np.cos(2 * np.pi * f * j / fs), m) for m in ms]
    np.testing.assert_allclose(exact, brute, rtol=1e-9)
    tau = 1000 / fs
    cont = A * A * np.sin(np.pi * f * tau) ** 4 / (np.pi * f * tau) ** 2
    assert get_term("sinusoid").avar(tau, 1e6, A=A, f=f)[0] == pytest.approx(cont, rel=1e-6)


def test_classical_signatures():
    tau = np.array([0.01, 1.0, 100.0])
    assert np.allclose(get_term("white").avar(tau, 100, N=2.0), 4.0 / tau)
    assert np.allclose(get_term("quantization").avar(tau, 100, Q=2.0), 12.0 / tau**2)
    assert np.allclose(get_term("bias_instability").avar(tau, 100, B=1.0),
                       2 * math.log(2) / math.pi)
    assert np.allclose(get_term("random_walk").avar(tau, 100, K=3.0), 3.0 * tau)
    assert np.allclose(get_term("rate_ramp").avar(tau, 100, R=2.0), 2.0 * tau**2)
    # Gauss-Markov peak near tau = 1.9 T
    t = np.geomspace(0.1, 1000, 4001)
    gm = get_term("gauss_markov").avar(t, 1000.0, sigma=1.0, T=10.0)
    assert t[np.argmax(gm)] == pytest.approx(18.9, rel=0.02)
    # sinusoid peak near tau = 0.37/f
    s = get_term("sinusoid").avar(t, 1000.0, A=1.0, f=0.2)
    assert t[np.argmax(s)] == pytest.approx(0.371 / 0.2, rel=0.02)


def test_psd_white_is_consistent_with_allan():
    # the Allan variance of any spectrum is 2 int_0^fs/2 G(f) |H_m(f)|^2/(...) ; for white noise
    # the one-sided level 2 N^2 integrates to the sample variance N^2 fs
    fs, N = 50.0, 3e-3
    f = np.linspace(0, fs / 2, 100001)
    g = get_term("white").psd(f, fs, N=N)
    assert np.trapezoid(g, f) == pytest.approx(N * N * fs, rel=1e-9)
    q = get_term("quantization").psd(f, fs, Q=1e-4)
    assert np.trapezoid(q, f) == pytest.approx(2 * (1e-4) ** 2 * fs**2, rel=1e-6)
    gm = get_term("gauss_markov").psd(f, fs, sigma=0.2, T=0.05)
    assert np.trapezoid(gm, f) == pytest.approx(0.04, rel=1e-4)
