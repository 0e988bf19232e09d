"""Discrete-time noise models: hand-derived values, exact Allan variances, the simulator."""

from decimal import Decimal, getcontext

import allantools
import numpy as np
import pytest

from imunoise.analysis.discrete import (
    discretize,
    markov_avar,
    random_walk_avar,
    simulate,
)

DEG = np.pi / 180.0


def _markov_avar_decimal(m: int, x: float) -> float:
    """AR(1) Allan variance (sigma = 1) summed over lags in 50-digit arithmetic."""
    getcontext().prec = 50
    a = (-Decimal(x)).exp()
    total = Decimal(m)
    for k in range(1, 2 * m):
        weight = (2 * (m - k) if k < m else 0) - (k if k <= m else 2 * m - k)
        total += weight * a**k
    return float(total / Decimal(m * m))


def test_petkov_seed_values():
    # Petkov & Slavov (2010): ADIS16350 gyro at 100 Hz, T = 120 s, a_d = 0.999917.
    fs = 100.0
    n_si = 5.75e-2 * DEG  # deg/sqrt(s) -> rad/s/sqrt(Hz)
    k_si = 9e-4 * DEG  # deg/s^1.5 -> rad/s/sqrt(s)
    sigma = 1.55e-2 * DEG
    dm = discretize([("white", {"N": n_si}), ("gauss_markov", {"sigma": sigma, "T": 120.0}),
                     ("random_walk", {"K": k_si})], fs, "rad/s")
    (st,) = dm.markov
    assert st.a_d == pytest.approx(0.999917, abs=5e-7)
    assert st.a_d == pytest.approx(np.exp(-0.01 / 120.0), rel=1e-15)
    # 1 - a_d^2 = 1 - exp(-2/12000) = 1.666528e-4 -> sqrt = 1.290941e-2
    assert st.driving_sigma == pytest.approx(sigma * 1.290941e-2, rel=1e-6)
    # white: sigma_d = N sqrt(fs) = 5.75e-2 deg/s * 10 = 0.575 deg/s
    assert dm.white_sigma == pytest.approx(0.575 * DEG, rel=1e-12)
    # random walk step K sqrt(dt) = 9e-4 * 0.1 = 9e-5 deg/s
    assert dm.random_walk_step == pytest.approx(9e-5 * DEG, rel=1e-12)
    d = dm.to_dict()
    assert d["markov"][0]["a_d"] == st.a_d and d["dt_s"] == 0.01


@pytest.mark.parametrize("T_s", [0.02, 1.0, 120.0, 1e4, 1e7])
def test_markov_avar_matches_direct_sum(T_s):
    fs = 100.0
    m = np.array([1, 2, 7, 64, 300])
    got = markov_avar(m / fs, fs, 1.0, T_s)
    want = np.array([_markov_avar_decimal(int(k), 1.0 / (fs * T_s)) for k in m])
    np.testing.assert_allclose(got, want, rtol=1e-8)


def test_random_walk_and_markov_limits():
    fs = 50.0
    K = 3e-5
    # m = 1: half the step variance; long tau: the continuous K^2 tau / 3.
    assert random_walk_avar(np.array([1 / fs]), fs, K)[0] == pytest.approx(K**2 / fs / 2)
    assert random_walk_avar(np.array([1e3]), fs, K)[0] == pytest.approx(K**2 * 1e3 / 3, rel=1e-9)
    # Markov: tau << T behaves like a random walk of K^2 = 2 sigma^2 / T; tau >> T like white
    # noise of N^2 = 2 sigma^2 T.
    sigma, T = 2e-4, 500.0
    tau = np.array([0.5])
    assert markov_avar(tau, fs, sigma, T)[0] == pytest.approx(
        random_walk_avar(tau, fs, np.sqrt(2 * sigma**2 / T))[0], rel=2e-3)
    tau = np.array([5e5])
    assert markov_avar(tau, fs, sigma, T)[0] == pytest.approx(2 * sigma**2 * T / tau[0], rel=3e-3)


def test_quantization_and_sinusoid_exact_avar():
    fs = 100.0
    dm = discretize([("quantization", {"Q": 1e-5}), ("sinusoid", {"A": 1e-3, "f": 3.0})], fs)
    tau = np.array([0.01, 0.1, 1.0 / 6.0])
    avar = dm.avar(tau)
    quant = 3 * 1e-10 / tau**2
    sine = 1e-6 * np.sin(np.pi * 3.0 * tau) ** 4 / ((tau * fs) * np.sin(np.pi * 3.0 / fs)) ** 2
    np.testing.assert_allclose(avar, quant + sine, rtol=1e-12)
    # m = 1: two samples of a sine at phase step theta differ by 2 A sin(theta/2) cos(.), so
    # the Allan variance is A^2 sin^2(theta/2) plus the quantization part.
    assert sine[0] == pytest.approx(1e-6 * np.sin(np.pi * 3.0 / fs) ** 2, rel=1e-12)


@pytest.mark.parametrize("B,tau_range", [(5e-5, (0.01, 3000.0)), (1e-3, (0.1, 100.0))])
def test_bias_instability_approximation_within_tolerance(B, tau_range):
    fs = 100.0
    N, K = 3e-4, 2e-6
    dm = discretize([("white", {"N": N}), ("bias_instability", {"B": B}),
                     ("random_walk", {"K": K})], fs, tau_range_s=tau_range)
    fl = dm.flicker
    assert fl is not None and fl.max_rel_avar_error <= 0.02
    decades = np.log10(tau_range[1] / tau_range[0])
    assert 2 <= len(dm.markov) <= 3 * decades + 3
    assert all(s.term == "bias_instability" for s in dm.markov)
    tau = np.logspace(*np.log10(tau_range), 97)
    cont = N**2 / tau + 2 * np.log(2) / np.pi * B**2 + K**2 * tau / 3
    # The discrete random walk differs from K^2 tau/3 by K^2 dt/(6m): add it to the reference.
    cont += K**2 / fs / (6 * tau * fs)
    assert np.max(np.abs(dm.avar(tau) / cont - 1)) <= 0.02
    # A pure flicker model over five decades still needs only a few states per decade.
    pure = discretize([("bias_instability", {"B": B})], fs, tau_range_s=(0.01, 1000.0))
    assert pure.flicker.max_rel_avar_error <= 0.05
    assert len(pure.markov) <= 3 * 5 + 2


def test_unknown_term_and_bad_rate():
    with pytest.raises(ValueError, match="unknown term 'wobble'"):
        discretize([("wobble", {"X": 1.0})], 100.0)
    with pytest.raises(ValueError, match="sample rate"):
        discretize([("white", {"N": 1.0})], 0.0)


def test_contract_json_model_accepted():
    model = [{"term": "white", "params": {"N": 2e-4}, "ci95": {"N": [1e-4, 3e-4]}}]
    dm = discretize(model, 200.0)
    assert dm.white_sigma == pytest.approx(2e-4 * np.sqrt(200.0))


def test_simulator_reproduces_exact_avar():
    # The overlapping AVAR estimator is unbiased, so the mean over seeds of the estimates must
    # equal the discrete model's exact Allan variance; tolerance 3.5 standard errors of the mean.
    fs = 100.0
    model = [("white", {"N": 3e-4}), ("quantization", {"Q": 4e-6}),
             ("gauss_markov", {"sigma": 2e-4, "T": 0.5}), ("bias_instability", {"B": 6e-5}),
             ("random_walk", {"K": 5e-5}), ("sinusoid", {"A": 2e-4, "f": 7.0})]
    dm = discretize(model, fs, tau_range_s=(0.01, 20.0))
    n, seeds = 20_000, 24
    taus = 2.0 ** np.arange(0, 11) / fs
    est = []
    for seed in range(seeds):
        y = simulate(dm, n, seed)
        t, ad, _, _ = allantools.oadev(y, rate=fs, data_type="freq", taus=taus)
        np.testing.assert_allclose(t, taus)
        est.append(ad**2)
    est = np.array(est)
    mean = est.mean(axis=0)
    sem = est.std(axis=0, ddof=1) / np.sqrt(seeds)
    exact = dm.avar(taus)
    assert np.all(np.abs(mean - exact) <= 3.5 * sem), np.c_[taus, mean / exact, sem / exact]


def test_simulator_is_seeded_and_handles_edges():
    dm = discretize([("white", {"N": 1e-3}), ("temperature", {"coef": 2e-3})], 10.0)
    a = simulate(dm, 500, 7)
    assert np.array_equal(a, simulate(dm, 500, 7))
    assert simulate(dm, 0, 1).shape == (0,)
    temp = np.linspace(20.0, 30.0, 500)
    b = simulate(dm, 500, 7, temperature=temp)
    np.testing.assert_allclose(b - a, 2e-3 * (temp - temp.mean()), atol=1e-15)
    with pytest.raises(ValueError, match="temperature must have 500 samples"):
        simulate(dm, 500, 7, temperature=temp[:10])


def _agreement(curve, sim_dev: np.ndarray) -> np.ndarray:
    """Where a second, independent estimate agrees with the measured curve: log-ratio within
    sqrt(2) times the measured 95 % half-width (the combined interval of two estimates)."""
    r = np.log(sim_dev / curve.dev)
    return (r >= -np.sqrt(2) * np.log(curve.dev / curve.ci_low)) & (
        r <= np.sqrt(2) * np.log(curve.ci_high / curve.dev))


def test_discrete_model_allan_curve_inside_measured_band():
    # "Measured": flicker + white + random walk made by the project's noise generator (not
    # this module's simulator). The discrete model of the same continuous parameters, with
    # bias instability as a few Markov states, must give an Allan curve inside the measured
    # 95 % band: exactly (its own Allan variance) and as a simulation.
    from imunoise.analysis.allan import oadev
    from imunoise.analysis.noise_stream import NoiseStream

    fs, n = 100.0, 200_000
    model = [("white", {"N": 3e-4}), ("bias_instability", {"B": 1e-4}),
             ("random_walk", {"K": 1e-6})]
    inside, agree, lost_in, single_in, total = 0, 0, 0, 0, 0
    for seed in range(5):
        curve = oadev(NoiseStream(model, fs, seed=seed).take(n), fs, m="octave", ci=0.95)
        lo, hi = curve.ci_low, curve.ci_high
        dm = discretize(model, fs, "rad/s", tau_range_s=(curve.tau_s[0], curve.tau_s[-1]))
        exact = np.sqrt(dm.avar(curve.tau_s))
        inside += int(((exact >= lo) & (exact <= hi)).sum())
        sim = oadev(simulate(dm, n, 100 + seed), fs, m=curve.m, alpha=0)
        agree += int(_agreement(curve, sim.dev).sum())
        total += curve.tau_s.size
        # Controls: without the bias-instability states, or with only the strongest one.
        crippled = np.sqrt(discretize(model[:1] + model[2:], fs).avar(curve.tau_s))
        lost_in += int(((crippled >= lo) & (crippled <= hi)).sum())
        dm.markov = [max(dm.markov, key=lambda st: st.sigma)]
        single = np.sqrt(dm.avar(curve.tau_s))
        single_in += int(((single >= lo) & (single <= hi)).sum())
    # Per tau either check holds with about 95 % probability on a correct model; neighbouring
    # taus are correlated, so over 5 records x 16 taus allow down to 85 %. The controls fall
    # far below (the flicker plateau is what they miss).
    assert inside >= 0.85 * total and agree >= 0.85 * total, (inside, agree, total)
    assert lost_in <= 0.6 * total and single_in <= 0.75 * total, (lost_in, single_in, total)


def test_negligible_bias_instability_gets_no_states():
    # A fit that drives B to ~0 must not produce Markov states of 1e-19 rad/s.
    dm = discretize([("white", {"N": 3e-4}), ("bias_instability", {"B": 1e-18}),
                     ("random_walk", {"K": 2e-5})], 100.0, tau_range_s=(0.01, 40.0))
    assert dm.markov == []
    assert dm.flicker.states_per_decade == 0.0 and dm.flicker.max_rel_avar_error < 1e-20
