"""Output filter terms (moving_average, bartlett, lowpass): their Allan variance against the
closed forms and against simulated filtered records, the fit recovering a filter, and the
diagnosis naming it."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.allan import oadev
from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.fit import fit_series
from imunoise.analysis.fit.layout import _unpack
from imunoise.analysis.fit.problem import _problem
from imunoise.analysis.fit.solve import _nested_starts
from imunoise.analysis.fit.starts import _cold_starts
from imunoise.analysis.noise_stream import NoiseStream
from imunoise.analysis.terms import TermError, get_term, model_avar, parse_model
from imunoise.analysis.terms.output_filter import avar_from_autocovariance

FS = 100.0
NOISE = [("white", {"N": 1e-3}), ("quantization", {"Q": 2e-5}), ("random_walk", {"K": 1e-4})]
FILTERS = [("moving_average", {"taps": 4.0}), ("bartlett", {"taps": 4.0}),
           ("lowpass", {"fc": 5.0})]


def _oavar(x: np.ndarray, m: np.ndarray) -> np.ndarray:
    c = np.concatenate(([0.0], np.cumsum(x)))
    out = []
    for k in m:
        d = (c[2 * k:] - 2.0 * c[k:-k] + c[:-2 * k]) / k
        out.append(0.5 * np.mean(d * d))
    return np.array(out)


def test_autocovariance_formula_reproduces_white_and_quantization() -> None:
    m = np.array([1, 2, 3, 5, 17, 400, 1e4 + 0.5])
    for name, p in [("white", {"N": 2e-3}), ("quantization", {"Q": 3e-5})]:
        term = get_term(name)
        got = avar_from_autocovariance(term.autocovariance(FS, p), m)
        np.testing.assert_allclose(got, term.avar(m / FS, FS, **p), rtol=1e-12)


def test_moving_average_of_white_noise_has_the_closed_form() -> None:
    # N^2/tau - N^2 (L^2-1)/(2 L fs tau^2) once tau >= L/fs; at m = 1, sigma^2/L^2
    n, taps = 1e-3, 8
    tau = np.array([8, 9, 20, 1000]) / FS
    got = model_avar([("white", {"N": n}), ("moving_average", {"taps": taps})], tau, FS)
    want = n**2 / tau - n**2 * (taps**2 - 1) / (2 * taps * FS * tau**2)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    one = model_avar([("white", {"N": n}), ("moving_average", {"taps": taps})], 1 / FS, FS)
    assert one[0] == pytest.approx(n**2 * FS / taps**2, rel=1e-12)


@pytest.mark.parametrize("filt", FILTERS, ids=[f[0] for f in FILTERS])
def test_numeric_route_agrees_with_the_time_domain(filt) -> None:
    # the grid integral used for random walk and flicker, checked on white noise where the
    # time-domain result is exact
    name, p = filt
    term, white = get_term(name), get_term("white")
    m = np.array([1, 2, 3, 4, 8, 16, 64, 1000], dtype=float)
    exact = model_avar([("white", {"N": 1.0}), (name, p)], m / FS, FS)
    numeric = white.avar(m / FS, FS, N=1.0) * term._ratio(white, {"N": 1.0}, m, FS, p)
    np.testing.assert_allclose(numeric, exact, rtol=2e-3)


def test_filtered_flicker_stays_positive_under_a_long_filter() -> None:
    # the flicker floor is asymptotic: at one sample the sampled 1/f spectrum holds more
    # than B^2 times the floor constant, and the difference of the filtered and unfiltered
    # integrals exceeded the floor itself (-2.0e-7 at tau = 0.1 s for these numbers)
    fs = 10.0
    tau = np.array([0.1, 0.2, 1.0, 10.0, 100.0])
    own = model_avar([("bias_instability", {"B": 1.6e-3})], tau, fs)
    got = model_avar([("bias_instability", {"B": 1.6e-3}), ("moving_average", {"taps": 20})],
                     tau, fs)
    assert np.all(got > 0.0)
    assert np.all(got <= own)
    # the filter's effect fades where tau spans many filter lengths
    assert got[-1] == pytest.approx(own[-1], rel=1e-3)
    assert got[0] < 0.05 * own[0]


@pytest.mark.parametrize("filt", FILTERS, ids=[f[0] for f in FILTERS])
def test_filtered_model_matches_a_simulated_filtered_record(filt) -> None:
    n = 1 << 20
    x = NoiseStream(NOISE + [filt], FS, seed=11).take(n)
    m = np.array([1, 2, 3, 4, 8, 16, 64])
    measured = _oavar(x, m)
    model = model_avar(NOISE + [filt], m / FS, FS)
    # the overlapping estimate's relative spread is below sqrt(4 m / n): 5 of them
    tol = 5.0 * np.sqrt(4.0 * m / n)
    assert np.all(np.abs(measured / model - 1.0) < tol), (measured / model - 1.0, tol)
    unfiltered = model_avar(NOISE, m / FS, FS)
    assert measured[0] < 0.5 * unfiltered[0]  # the filter really acted


def test_filter_parameters_are_checked() -> None:
    with pytest.raises(TermError, match="below fs/1000"):
        get_term("lowpass").validate({"fc": 0.01}, FS)
    with pytest.raises(TermError, match="taps = 0.5 outside"):
        get_term("moving_average").validate({"taps": 0.5}, FS)
    spec = parse_model("white,moving_average:taps=4")
    assert spec.names == ["white", "moving_average"] and spec.fixed == {1: {"taps": 4.0}}
    with pytest.raises(TermError, match="at most one output filter"):
        model_avar([("white", {"N": 1.0}), ("lowpass", {"fc": 5.0}),
                    ("bartlett", {"taps": 2.0})], np.array([1.0]), FS)


def test_fit_recovers_a_four_tap_moving_average() -> None:
    model = [("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5}),
             ("moving_average", {"taps": 4.0})]
    x = NoiseStream(model, FS, seed=3).take(1 << 20)
    with_filter, _ = fit_series(x, FS, "white,random_walk,moving_average")
    without, _ = fit_series(x, FS, "white,random_walk")
    taps = with_filter.terms[2]
    lo, hi = taps.ci95["taps"]
    assert lo <= 4.0 <= hi and hi - lo < 1.0, taps
    n_lo, n_hi = with_filter.terms[0].ci95["N"]
    assert n_lo <= 1e-3 <= n_hi
    assert with_filter.chi2_per_dof < 2.0 < 10.0 < without.chi2_per_dof


def test_a_filter_fitted_beside_the_terms_after_it_starts_from_its_taps_grid() -> None:
    """A 4-tap moving average under a 20 Hz resonance (its f0 and Q held, as the spectrum
    gives them) and a 30 s Markov term, fitted from no previous fit: the filter is not the
    model's last term, so it is solved together with those after it. From one guess of
    its taps the solve stopped at 3 taps with the resonance at zero (chi2/dof 55 against 1.3
    at the truth); started from the grid of taps, it finds the truth."""
    truth = [("white", {"N": 5e-4}), ("bias_instability", {"B": 1.4e-4}),
             ("random_walk", {"K": 1.4e-5}), ("moving_average", {"taps": 4.0}),
             ("resonance", {"sigma": 3e-3, "f0": 20.0, "Q": 15.0}),
             ("gauss_markov", {"sigma": 2e-4, "T": 30.0})]
    x = NoiseStream(truth, FS, seed=1).take(1_080_000)
    fit, _ = fit_series(x, FS, "white,bias_instability,random_walk,moving_average,"
                        "resonance:f0=20:Q=15,gauss_markov")
    assert fit.chi2_per_dof < 3.0, fit.chi2_per_dof
    for i, name, key, value in ((0, "white", "N", 5e-4), (3, "moving_average", "taps", 4.0),
                                (4, "resonance", "sigma", 3e-3)):
        lo, hi = fit.terms[i].ci95[key]
        assert fit.terms[i].term == name and lo <= value <= hi, fit.terms[i]


def test_an_appended_lowpass_starts_from_no_filter_and_near_the_true_cutoff() -> None:
    # the smaller model's solution with the pole at Nyquist (a pole at fs/1000 would stand
    # for "no filter" as amplitude 0 does for a noise term, and it filters everything), then
    # the cutoffs of the grid whose amplitude solve follows the curve best
    x = NoiseStream([("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5}),
                     ("lowpass", {"fc": 5.0})], FS, seed=8).take(1 << 19)
    curve = oadev(x, FS, m="octave")
    spec = parse_model("white,random_walk,lowpass")
    prob = _problem(curve, spec, None, 0.10, 200)
    memo: dict = {}
    starts, exact = _nested_starts(prob, curve, spec, None, memo, _cold_starts(prob, None)[0])
    fcs = [_unpack(prob.layout, theta)[2]["fc"] for theta in starts]
    assert len(fcs) == 3 and fcs[0] == pytest.approx(0.5 * FS, rel=1e-6)
    # four grid points per octave: the best is within a quarter octave of the truth
    assert abs(np.log2(fcs[1] / 5.0)) <= 0.25, fcs
    # so the unsolved start is the smaller model's fit, not a far worse one
    (_, smaller), = [v for k, v in memo.items() if k[1] == "white,random_walk"]
    assert exact is not None and exact.chi2 < 1.2 * smaller.chi2, (exact.chi2, smaller.chi2)
    fitted, _ = fit_series(x, FS, spec)
    lo, hi = fitted.terms[2].ci95["fc"]
    assert lo <= 5.0 <= hi, fitted.terms[2]


def test_diagnosis_names_the_filter_of_a_filtered_record() -> None:
    x = NoiseStream([("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-4}),
                     ("random_walk", {"K": 1e-5}), ("moving_average", {"taps": 4.0})],
                    FS, seed=5).take(200_000)
    d = diagnose(x, FS, "white,bias_instability,random_walk")
    top = d.suggestions[0]
    assert top.significant and get_term(top.term).kind == "filter", top
    assert top.chi2_per_dof_after < 2.0 < d.fit.chi2_per_dof
    assert top.apply["model"] == f"white,bias_instability,random_walk,{top.term}"
    refit, _ = fit_series(x, FS, top.apply["model"], intervals="jacobian")
    assert refit.chi2_per_dof == pytest.approx(top.chi2_per_dof_after, rel=1e-6)


def test_no_filter_is_offered_for_an_unfiltered_record() -> None:
    x = NoiseStream([("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-4}),
                     ("random_walk", {"K": 1e-5})], FS, seed=6).take(200_000)
    d = diagnose(x, FS, "white,bias_instability,random_walk")
    assert not [s for s in d.suggestions if get_term(s.term).kind == "filter" and s.significant]


def test_a_filter_the_device_states_is_offered_with_its_parameters_held() -> None:
    x = NoiseStream([("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5}),
                     ("moving_average", {"taps": 4.0})], FS, seed=8).take(200_000)
    d = diagnose(x, FS, "white,random_walk", sensor_filter=("moving_average", {"taps": 4.0}))
    filters = [s for s in d.suggestions if get_term(s.term).kind == "filter"]
    assert [s.term for s in filters] == ["moving_average"]  # the stated one only
    (s,) = filters
    assert s.significant and s.params == {"taps": 4.0}
    assert s.apply["model"] == "white,random_walk,moving_average:taps=4"
    assert "device configuration states this filter" in s.why


@pytest.mark.parametrize("taps", [1.07, 2.5, 10.3, 64.3, 100.5, 333.25, 1023.999])
def test_fractional_moving_average_response_equals_the_sum_over_its_taps(taps) -> None:
    # a non-integer filter's response is taken in closed form; against the sum over the taps
    # in long double it holds to 1e-12 of its peak value (1) and 1e-9 where it is above 1e-6
    from imunoise.analysis.terms.output_filter import OutputFilter

    term = get_term("moving_average")
    u = np.concatenate((np.geomspace(1e-8, 0.5, 700), np.linspace(0.0, 0.5, 301)))
    got = term.response(u * FS, FS, {"taps": taps})
    g = term.impulse_response(FS, {"taps": taps}).astype(np.longdouble)
    k = np.arange(g.size, dtype=np.longdouble)
    w = 2.0 * np.pi * u.astype(np.longdouble)
    want = ((np.cos(np.outer(w, k)) @ g) ** 2 + (np.sin(np.outer(w, k)) @ g) ** 2
            ).astype(np.float64)
    np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-12)
    big = want > 1e-6
    np.testing.assert_allclose(got[big], want[big], rtol=1e-9)
    # and the float64 sum it replaces agrees with both to the same bound
    generic = OutputFilter.response(term, u * FS, FS, {"taps": taps})
    np.testing.assert_allclose(got[big], generic[big], rtol=1e-9)


@pytest.mark.parametrize("name", ["white", "quantization"])
def test_a_short_memory_terms_filtered_part_scales_with_its_amplitude_squared(name):
    # the part is computed once at unit amplitude and scaled: a fit moving only the
    # amplitude reuses it, and it must equal the part computed at that amplitude
    term, filt = get_term(name), get_term("bartlett")
    tau = np.array([0.01, 0.02, 0.05, 0.1, 1.0, 10.0])
    amp = term.amplitude
    _, (one,) = filt.filtered_parts([(term, {amp: 1.0})], tau, FS, {"taps": 2.3})
    _, (three,) = filt.filtered_parts([(term, {amp: 3.0})], tau, FS, {"taps": 2.3})
    np.testing.assert_allclose(three, 9.0 * one, rtol=1e-14)
    r_in = term.autocovariance(FS, {amp: 3.0})
    direct = avar_from_autocovariance(filt.filtered_autocovariance(r_in, FS, {"taps": 2.3}),
                                      tau * FS)
    np.testing.assert_allclose(three, direct, rtol=1e-13)
