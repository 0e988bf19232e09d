"""The antiresonance: a resonance through a pair of undamped zeros. Its Allan variance exact
against its autocovariance and its spectrum, a simulated record with its spectrum, the
spectrum's pin of the zeros, and the diagnosis offering it where a resonance's skirts miss."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.allan import oadev
from imunoise.analysis.dsp import welch_density
from imunoise.analysis.terms import get_term
from imunoise.analysis.terms.antiresonance import (
    antiresonance_variance,
    zero_gain,
    zero_taps,
)
from imunoise.analysis.terms.output_filter import avar_from_autocovariance
from imunoise.analysis.terms.resonance import pole_and_weight

FS = 100.0
P = {"sigma": 8e-3, "f0": 19.9, "Q": 17.0, "fa": 15.0}
"""The ADIS16405 run 1 gyro_z mode: 19.9 Hz, Q 17, its zeros near 15 Hz."""


@pytest.mark.parametrize(("f0", "q", "fa"), [(19.9, 17.0, 15.0), (19.9, 17.0, 26.0),
                                             (2.0, 3.0, 1.0), (0.5, 200.0, 0.45),
                                             (30.0, 0.6, 45.0)])
def test_allan_variance_equals_the_sum_over_its_autocovariance(f0: float, q: float,
                                                               fa: float) -> None:
    # y = b * x with x's autocorrelation 2 Re(c p^|k|): summed lag by lag until it has died
    p, c = pole_and_weight(FS, f0, q)
    b = zero_taps(FS, fa)
    lags = int(40.0 * q * FS / (np.pi * f0)) + 8  # p^lags below e^-40
    k = np.arange(-2, lags + 3)
    rho = 2.0 * np.real(c * p ** np.abs(k))
    r = sum(b[i] * b[j] * rho[2 + (j - i):2 + (j - i) + lags]
            for i in range(3) for j in range(3))
    m = np.array([1, 2, 3, 5, 8, 13, 50, 200, 1000, 5000], dtype=float)
    got = get_term("antiresonance").avar(m / FS, FS, sigma=1.0, f0=f0, Q=q, fa=fa)
    # digits go as the pole nears 1 and the zeros near 0 Hz (whose taps, scaled to gain 1
    # there, reach 1,250 and cancel): 1.8e-7 at f0 0.5 Hz, Q 200, fa 0.45 Hz; 1e-12 above 1 Hz
    np.testing.assert_allclose(got, avar_from_autocovariance(r, m), rtol=1e-6)
    assert antiresonance_variance(FS, f0, q, fa) == pytest.approx(r[0], rel=1e-6)


def test_allan_variance_equals_the_integral_of_its_spectrum() -> None:
    term = get_term("antiresonance")
    u = np.linspace(0.0, 0.5, 2_000_001)[1:]
    du = u[1] - u[0]
    s = term.psd(u * FS, FS, **P)
    var = antiresonance_variance(FS, P["f0"], P["Q"], P["fa"]) * P["sigma"] ** 2
    assert np.sum(s) * du * FS == pytest.approx(var, rel=1e-4)
    m = np.array([1, 2, 3, 5, 8, 13, 50, 200, 1000], dtype=float)
    numeric = [0.5 * FS * du * np.sum(s * 4 * np.sin(np.pi * u * k) ** 4
                                      / (k * k * np.sin(np.pi * u) ** 2)) for k in m]
    np.testing.assert_allclose(term.avar(m / FS, FS, **P), numeric, rtol=1e-4)


def test_the_zeros_null_the_spectrum_at_fa_and_pass_0_hz() -> None:
    f = np.array([0.0, 7.0, 15.0, 20.0])
    g = zero_gain(f, FS, 15.0)
    assert g[0] == pytest.approx(1.0, rel=1e-12) and g[2] < 1e-25
    assert zero_taps(FS, 15.0).sum() == pytest.approx(1.0)
    psd = get_term("antiresonance").psd(f, FS, **P)
    plain = get_term("resonance").psd(f, FS, sigma=P["sigma"], f0=P["f0"], Q=P["Q"])
    np.testing.assert_allclose(psd, plain * g, rtol=1e-12)


def test_a_simulated_record_has_the_term_s_spectrum_and_allan_variance() -> None:
    term = get_term("antiresonance")
    x = term.simulator(P, FS, np.random.default_rng(3)).take(1 << 20)
    var = antiresonance_variance(FS, P["f0"], P["Q"], P["fa"]) * P["sigma"] ** 2
    # the variance of 2^20 samples with a ring-down of 0.1 s: a standard error near 1 %
    assert x.var() == pytest.approx(var, rel=0.04)
    f, p = welch_density(x, FS, 1024)
    bands = [(f >= lo) & (f < lo + 2.0) for lo in np.arange(4.0, 46.0, 2.0)]
    ratio = np.array([p[b].mean() / term.psd(f[b], FS, **P).mean() for b in bands])
    # 2 Hz bands of about 2,000 segments' bins: a few per cent (the null's band is judged by
    # its level, the model's being near zero there)
    keep = np.array([not (lo <= P["fa"] < lo + 2.0) for lo in np.arange(4.0, 46.0, 2.0)])
    assert np.all(np.abs(ratio[keep] - 1.0) < 0.05)
    curve = oadev(x, FS, m="octave")
    tau, measured = np.asarray(curve.tau_s)[:7], np.asarray(curve.avar)[:7]
    assert np.all(np.abs(measured / term.avar(tau, FS, **P) - 1.0) < 0.05)


def test_the_psd_expectation_matches_the_mean_of_simulated_estimates() -> None:
    # as tests/analysis/test_psd_model.py judges every term: 8 records of 2^17 samples, the
    # mean estimate's z against the expectation below 4.5 everywhere and its mean square in
    # 0.7-1.4; the plain resonance of the same pole misses by far
    from imunoise.analysis.psd import log_psd
    from imunoise.analysis.psd_model import expected_log_psd

    n, r, white = 1 << 17, 8, 2e-4
    estimates = []
    for s in range(r):
        rng = np.random.default_rng(4000 + s)
        x = get_term("antiresonance").simulator(P, FS, rng).take(n)
        estimates.append(log_psd(x + white * np.sqrt(FS) * rng.standard_normal(n), FS))
    est, mean = estimates[0], np.mean([e.psd for e in estimates], axis=0)

    def z(model: list) -> np.ndarray:
        expected = expected_log_psd(model, est, FS)
        return (mean - expected) / (expected * np.sqrt(2.0 / (est.dof * r)))

    ok = z([("white", {"N": white}), ("antiresonance", P)])
    assert np.max(np.abs(ok)) < 4.5 and 0.7 < float(np.mean(ok ** 2)) < 1.4
    plain = z([("white", {"N": white}),
               ("resonance", {k: v for k, v in P.items() if k != "fa"})])
    assert np.max(np.abs(plain)) > 20.0


def _bench_record() -> np.ndarray:
    # 2.9 h at 100 Hz: white noise, a random walk and the mode with its zeros
    from imunoise.analysis.noise_stream import NoiseStream

    n = 1 << 20
    x = NoiseStream([("white", {"N": 3e-4}), ("random_walk", {"K": 1e-5})], FS,
                    seed=5).take(n)
    return x + get_term("antiresonance").simulator(P, FS, np.random.default_rng(6)).take(n)


def test_the_spectrum_pins_the_zeros() -> None:
    from imunoise.analysis.spectral_pins import PINNED, pin_resonances

    model = [("white", {"N": 3e-4}), ("random_walk", {"K": 1e-5}),
             ("antiresonance", {"sigma": 5e-3, "f0": 20.5, "Q": 10.0, "fa": 16.4})]
    held = {(i, k) for i in range(2) for k in PINNED}
    pin = pin_resonances(_bench_record(), FS, model, held)[0]
    assert pin.ci95["fa"][0] < P["fa"] < pin.ci95["fa"][1]
    assert pin.params["fa"] == pytest.approx(P["fa"], rel=0.02)
    # f0 to within two of its interval's half-widths (19.902 [19.901, 19.904] for 19.9 here)
    half = 0.5 * (pin.ci95["f0"][1] - pin.ci95["f0"][0])
    assert abs(pin.params["f0"] - P["f0"]) < 2.0 * half
    assert pin.deviance_per_dof < 1.3


def test_the_diagnosis_offers_it_where_a_resonance_s_skirts_miss() -> None:
    # given a plain resonance (fitted to 24 Hz, Q 3.9), the spectrum dips under the peak and
    # stands out over it (PSD part 2,050); the resonance replaced by an antiresonance whose
    # zeros the spectrum gives (15.0 Hz) brings the PSD part to 0.98, the Allan part from
    # 3,890 to 0.78
    from imunoise.analysis.diagnosis import diagnose

    d = diagnose(_bench_record(), FS, "white,random_walk,resonance", holdout=False)
    psd_before = d.error_parts["psd"]["deviance_per_bin"]
    swap = next(s for s in d.suggestions if s.label == "resonance by antiresonance")
    assert swap.action == "replace"
    assert swap.apply["model"].startswith("white,random_walk,antiresonance:f0=")
    assert swap.params["fa"] == pytest.approx(P["fa"], rel=0.03)
    assert psd_before > 3.0
    assert swap.error_after["psd"]["deviance_per_bin"] < 1.5
    assert swap.chi2_per_dof_after < 1.5
    assert swap.significant and d.suggestions[0] is swap


def test_a_background_level_at_its_bound_is_held_in_the_pin_s_intervals() -> None:
    # ADIS16405 run 5 gyro_z: the band's white level goes to its lower bound beside a Markov
    # term, its Jacobian column vanishes, and the pin's intervals come from the other columns
    from imunoise.analysis.spectral_pins import _pin_sd

    rng = np.random.default_rng(7)
    jac = rng.standard_normal((200, 6))
    jac[:, 4] = 0.0  # the background's white level, at its bound
    sd = _pin_sd(jac, 1.0, level_free=False, first_background=4)
    assert sd is not None and sd[4] == 0.0 and sd[5] == 0.0 and np.all(sd[:4] > 0.0)
    jac[:, 2] = 0.0  # a pinned parameter the band does not see: no pin
    assert _pin_sd(jac, 1.0, level_free=False, first_background=4) is None
