"""The PSD, hold-out and time-domain parts of a model's error (analysis.model_error)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from imunoise.analysis.fit import TermFit, fit_series
from imunoise.analysis.model_error import (
    HalfFit,
    HoldoutHalves,
    _changed,
    _pairs,
    error_parts,
    fit_half,
    holdout_findings,
    holdout_halves,
    holdout_part,
    parts_line,
    right_model_limit,
    time_domain_part,
)
from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.psd_model import psd_misses, psd_z

FS = 100.0
N = 1 << 19
MODEL = [("white", {"N": 1e-3}), ("gauss_markov", {"sigma": 1e-3, "T": 0.5}),
         ("random_walk", {"K": 1e-5})]
SPEC = "white,gauss_markov,random_walk"


def _half(setup: HoldoutHalves | dict, k: int) -> HalfFit:
    assert isinstance(setup, HoldoutHalves)
    done = fit_half(setup.shared(), k)
    assert isinstance(done, HalfFit), done
    return done


@pytest.fixture(scope="module")
def stationary():
    x = simulate(MODEL, N, FS, rng=11)
    return x, fit_series(x, FS, SPEC)[0]


def test_a_correct_model_has_every_part_near_one(stationary):
    x, fit = stationary
    block, parts = error_parts(x, FS, SPEC, fit)
    assert set(block) == {"f_hz", "psd", "dof", "ci_low", "ci_high", "model_psd", "z"}
    assert len(block["model_psd"]) == parts["psd"]["bins"] > 150
    assert 0.7 < parts["psd"]["deviance_per_bin"] < 1.4
    assert parts["psd"]["outside_95"] < 0.12 and parts["psd"]["misses"] == []
    ho = parts["holdout"]
    assert ho["parts"] == 2 and 0.3 < ho["chi2_per_dof"] < 2.0 and ho["changed"] == []
    assert "joint_difference" not in ho and ho["misses"] == []
    td = parts["time_domain"]
    assert td["p"] > 0.01 and td["statistic"] > 0


def test_a_model_missing_a_term_fails_the_psd_and_holdout_parts(stationary):
    x, _ = stationary
    fit = fit_series(x, FS, "white,random_walk")[0]
    _, parts = error_parts(x, FS, "white,random_walk", fit)
    assert parts["psd"]["deviance_per_bin"] > 5.0
    # the missing 0.5 s Markov term: the spectrum stands above the model from well below
    # its corner (0.32 Hz) to just beyond it, and that one miss makes most of the part
    misses = parts["psd"]["misses"]
    top = max(misses, key=lambda m: m["deviance_share"])
    assert top["direction"] == "measured above model"
    assert top["f_hz"][0] < 0.1 and 0.32 < top["f_hz"][1] < 1.0
    assert top["deviance_share"] > 0.5
    assert all(m["direction"] == "measured above model" for m in misses)
    lines = parts_line(fit.chi2_per_dof, parts).splitlines()
    assert lines[1].startswith("  psd: measured above model at ")


def test_psd_misses_extend_over_the_bins_beside_a_flagged_one():
    # 200 bins of 1000 degrees of freedom (a score of about sqrt(500) (r - 1)): a broad
    # excess at bins 50-59 with bin 55 only a little above the model, one bin far below at
    # 150, and a lone bin above by a score of 2.5, under the family level
    f = np.arange(200.0) + 1.0
    dof = np.full(200, 1000.0)
    model = np.ones(200)
    psd = np.ones(200)
    psd[50:60] = 1.3
    psd[55] = 1.1
    psd[150] = 0.7
    psd[100] = 1.115
    misses = psd_misses(f, psd, dof, model)
    assert [(m["f_hz"], m["direction"]) for m in misses] == [
        ([51.0, 60.0], "measured above model"), ([151.0, 151.0], "measured below model")]
    assert misses[0]["max_abs_z"] == pytest.approx(psd_z(psd[50:51], dof[:1], model[:1])[0])
    r = psd / model
    dev = dof * (r - 1.0 - np.log(r))
    assert misses[1]["deviance_share"] == pytest.approx(dev[150] / dev.sum())


@pytest.fixture(scope="module")
def moving_peak() -> np.ndarray:
    """A 30-Q resonance at 20.7 Hz for the first half of the record and 19.9 Hz for the
    second, over white noise."""
    halves = [simulate([("white", {"N": 1e-3}),
                        ("resonance", {"sigma": 3e-3, "f0": f0, "Q": 30.0})], N // 2, FS, rng=seed)
              for f0, seed in ((20.7, 3), (19.9, 4))]
    return np.concatenate(halves)


def test_a_resonance_that_moves_between_the_halves_is_named(moving_peak):
    x = moving_peak
    spec = "white,resonance"
    fit = fit_series(x, FS, spec)[0]
    ho = holdout_part(x, FS, spec, fit)
    names = [c["param"] for c in ho["changed"]]
    assert "resonance.f0" in names, ho
    moved = next(c for c in ho["changed"] if c["param"] == "resonance.f0")
    # each half's spectrum pins its peak: within 0.1 Hz of where it was simulated
    assert moved["source"] == "psd"
    assert moved["values"] == pytest.approx([20.7, 19.9], abs=0.1)
    assert "20.7" in parts_line(1.0, {"holdout": ho}) and " Hz (from each half's spectrum)" \
        in parts_line(1.0, {"holdout": ho})


def test_a_resonance_whose_power_falls_is_named_from_each_halfs_spectrum():
    # the peak's power, 3e-3 then 2.4e-3 at one f0 and Q, is read from each half's
    # spectrum, where the peak's area lies apart from the floor beside it; each half's
    # interval is about +-2 % (test_spectral_pins), so the values come within 5 %
    halves = [simulate([("white", {"N": 1e-3}),
                        ("resonance", {"sigma": sigma, "f0": 20.0, "Q": 30.0})], N // 2, FS,
                       rng=seed) for sigma, seed in ((3e-3, 5), (2.4e-3, 6))]
    x = np.concatenate(halves)
    fit = fit_series(x, FS, "white,resonance")[0]
    ho = holdout_part(x, FS, "white,resonance", fit)
    fell = next(c for c in ho["changed"] if c["param"] == "resonance.sigma")
    assert fell["source"] == "psd"
    assert fell["values"] == pytest.approx([3e-3, 2.4e-3], rel=0.05)
    assert not any(c["param"] in ("resonance.f0", "resonance.Q") for c in ho["changed"]), ho


def test_a_resonance_that_stays_put_is_not_named():
    # family level 5 % per record over every parameter compared; 6 seeds: one false naming
    # has probability about 0.26, two about 0.03
    model = [("white", {"N": 1e-3}), ("resonance", {"sigma": 3e-3, "f0": 20.0, "Q": 30.0})]
    named = 0
    for seed in range(6):
        x = simulate(model, N // 2, FS, rng=20 + seed)
        fit = fit_series(x, FS, "white,resonance")[0]
        named += bool(holdout_part(x, FS, "white,resonance", fit)["changed"])
    assert named <= 1


def test_repeats_are_paired_by_their_shape_not_their_order():
    def fit_of(*terms):
        return SimpleNamespace(terms=[TermFit(n, p, {}) for n, p in terms])

    a = fit_of(("white", {"N": 1.0}), ("resonance", {"sigma": 1.0, "f0": 20.7, "Q": 15.0}),
               ("resonance", {"sigma": 1.0, "f0": 9.0, "Q": 0.6}))
    b = fit_of(("white", {"N": 1.0}), ("resonance", {"sigma": 1.0, "f0": 10.0, "Q": 0.5}),
               ("resonance", {"sigma": 1.0, "f0": 19.9, "Q": 22.0}))
    assert _pairs(a, b) == [0, 2, 1]


def test_a_bias_step_shows_in_the_time_domain_part(stationary):
    x, fit = stationary
    y = x.copy()
    y[N // 3:] += 3e-3
    td = time_domain_part(y, FS, fit.params)
    assert td["p"] < 0.01 and td["kind"] == "bias_step"


def test_parts_that_cannot_be_computed_say_why():
    td = time_domain_part(np.zeros(100), FS, MODEL)
    assert td["statistic"] is None and td["reason"]


def test_a_drift_present_in_one_half_only_is_named():
    # a random walk through the first half, none in the second: the second half's K interval
    # reaches zero, so the two are compared on the linear scale
    walk = [("white", {"N": 1e-3}), ("random_walk", {"K": 3e-5})]
    x = np.concatenate((simulate(walk, N // 2, FS, rng=7),
                        simulate(walk[:1], N // 2, FS, rng=8)))
    spec = "white,random_walk"
    fit = fit_series(x, FS, spec)[0]
    ho = holdout_part(x, FS, spec, fit)
    moved = [c for c in ho["changed"] if c["param"] == "random_walk.K"]
    assert moved and moved[0]["source"] == "allan", ho
    assert moved[0]["values"][0] > 1e-5 > moved[0]["values"][1]


def test_a_held_resonance_that_moves_is_named_too(moving_peak):
    # the diagnosis writes a resonance's f0 and Q into the model; the halves' spectra still
    # measure them
    x = moving_peak
    spec = "white,resonance:f0=20.3:Q=30"
    fit = fit_series(x, FS, spec)[0]
    moved = [c for c in holdout_part(x, FS, spec, fit)["changed"] if c["param"] == "resonance.f0"]
    assert moved and moved[0]["source"] == "psd"
    assert moved[0]["values"] == pytest.approx([20.7, 19.9], abs=0.1)


def test_a_change_seen_only_through_correlated_parameters_is_named():
    # the white level rises 0.6 % between the halves; a moving average's taps are estimated
    # from the same short-tau points, so neither parameter's own interval shows the change
    # (seed 1 is a record where the marginal comparison names nothing). Judged with the
    # other parameters held equal, one of the two is named
    x = np.concatenate([simulate([("white", {"N": 1e-3 * f}), ("moving_average", {"taps": 1.3})],
                                 N // 2, FS, rng=s) for f, s in ((1.0, 52), (1.006, 53))])
    spec = "white,moving_average"
    fit = fit_series(x, FS, spec)[0]
    setup = holdout_halves(x, FS, spec, fit)
    a, b = (_half(setup, k).fit for k in (0, 1))
    changed = _changed(a, b)
    assert [c["test"] for c in changed] == ["joint"], changed
    # two parameters compared: the Bonferroni level is norm.isf(0.05 / 4) = 2.50
    assert changed[0]["param"] in ("white.N", "moving_average.taps") and changed[0]["z"] > 2.50
    assert "the other parameters held equal" in parts_line(1.0, {"holdout": {"changed": changed}})


def test_a_stationary_record_with_a_filter_names_no_change():
    # the joint comparison's own level is 5 % (chi-square over the compared parameters, then
    # Bonferroni per parameter); 60 such records named none. 6 seeds: one false naming has
    # probability below 0.3
    model = [("white", {"N": 7.7e-4}), ("bias_instability", {"B": 1.3e-4}),
             ("moving_average", {"taps": 4.0})]
    spec = "white,bias_instability,moving_average"
    named = together = 0
    for seed in range(6):
        x = simulate(model, N, FS, rng=40 + seed)
        fit = fit_series(x, FS, spec)[0]
        ho = holdout_part(x, FS, spec, fit)
        named += any(c.get("test") == "joint" for c in ho["changed"])
        together += "joint_difference" in ho
    # nor a difference taken together (none in 30 records of this model, seeds 500-529, nor
    # in 30 of white, bias instability and random walk)
    assert named <= 1 and together <= 1


def test_flicker_that_trades_places_with_the_random_walk_is_not_a_change():
    # a stationary record (seed 31 of 60): the second half's fit puts bias instability at
    # zero and takes its long-tau rise as a larger random walk. On the intervals alone B
    # "vanished" (z 3.0 against the Bonferroni level 2.4); held at the near end of the first
    # half's interval, the second half's curve fits as well, so no change is named
    model = [("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-4}),
             ("random_walk", {"K": 1e-5})]
    spec = "white,bias_instability,random_walk"
    x = simulate(model, N, FS, rng=1031)
    fit = fit_series(x, FS, spec)[0]
    setup = holdout_halves(x, FS, spec, fit)
    done = [_half(setup, k) for k in (0, 1)]
    a, b = (d.fit for d in done)
    assert b.terms[1].ci95["B"][0] == 0.0 < a.terms[1].ci95["B"][0]
    assert [c["param"] for c in _changed(a, b)] == ["bias_instability.B"]
    assert setup.part(done)["changed"] == []


def test_a_half_fit_is_searched_again_only_when_it_misses_beyond_the_wholes_misfit() -> None:
    from types import SimpleNamespace

    from imunoise.analysis.model_error import _start_misled

    def fit(per_dof: float, dof: int = 12) -> SimpleNamespace:
        return SimpleNamespace(chi2_per_dof=per_dof, misfit=SimpleNamespace(dof=dof))

    # a misfit model: a half costs no more per degree of freedom than the whole
    assert _start_misled(fit(6554.0), fit(233.0))
    assert not _start_misled(fit(138.0), fit(233.0))
    # a right model (chi2/dof about 1): 1 + 3 sqrt(2/12) = 2.22 is the limit
    assert not _start_misled(fit(2.2), fit(0.8))
    assert _start_misled(fit(2.3), fit(0.8))


def test_the_profile_change_combines_both_halves_rises_scaled_by_their_misfit() -> None:
    from imunoise.analysis.model_error import _profile_changed

    def fit(k: float, per_dof: float) -> SimpleNamespace:
        # the misfit of every parameter's taus taken as the half's chi2/dof
        return SimpleNamespace(terms=[TermFit("white", {"N": 1.0}, {}),
                                      TermFit("random_walk", {"K": k}, {})],
                               chi2_per_dof=per_dof,
                               dispersion_of=lambda index, param: max(1.0, per_dof))

    rises = {(0, "N"): 0.5, (1, "N"): 0.5, (0, "K"): 99.0, (1, "K"): 32.0}
    asked: list[tuple] = []

    def refit(items):
        asked.extend(items)
        return [rises[(half, param)] for half, _, param, _ in items]

    # white.N has one value on both halves (held): not compared; K alone is, so the level is
    # norm.isf(0.05 / 2) = 1.96. Half b's rise 32 counts as 32 / 2.85
    a, b = fit(5.9e-4, 0.9), fit(1.6e-4, 2.85)
    out = _profile_changed(a, b, [], refit)
    assert [c["param"] for c in out] == ["random_walk.K"] and out[0]["test"] == "profile"
    assert out[0]["z"] == pytest.approx((1.0 / (1.0 / 99.0 + 2.85 / 32.0)) ** 0.5)
    assert out[0]["values"] == [5.9e-4, 1.6e-4]
    # each half held at the other's value
    assert asked == [(0, 1, "K", 1.6e-4), (1, 1, "K", 5.9e-4)]
    # a parameter already named is not named twice; a half whose curve does not mind the
    # other's value (no rise) names nothing
    assert _profile_changed(a, b, [{"param": "random_walk.K"}], refit) == []
    rises[(1, "K")] = 0.0
    assert _profile_changed(a, b, [], refit) == []
    # the combination is below either rise: with half a's rise below the level (1.96^2),
    # half b is not refitted
    rises[(0, "K")], rises[(1, "K")] = 3.8, 1e6
    asked.clear()
    assert _profile_changed(a, b, [], refit) == [] and [h for h, *_ in asked] == [0]


def test_a_model_that_misses_a_stationary_record_names_no_change_by_the_curves() -> None:
    # the halves miss each other's curves because the model lacks a Markov term, not because
    # anything changed: each half's misfit widens its own profile, and the profile test,
    # which runs only here (hold-out part far beyond its noise), names nothing. 12 of 12
    # records of 2^20 samples named nothing; these are three of 2^19
    model = [("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-4}),
             ("random_walk", {"K": 1e-5}), ("gauss_markov", {"sigma": 2e-3, "T": 2.0})]
    spec = "white,bias_instability,random_walk"
    for seed in range(3):
        x = simulate(model, N, FS, rng=70 + seed)
        fit = fit_series(x, FS, spec)[0]
        ho = holdout_part(x, FS, spec, fit)
        assert ho["chi2_per_dof"] > 10.0
        assert not [c for c in ho["changed"] if c.get("test") == "profile"], ho["changed"]


def test_a_named_change_left_free_lets_the_halves_predict_each_other() -> None:
    # the white level is 5 % higher in the second half: held at the other half's level, each
    # half's model misses the shortest taus; with white.N fitted on the half predicted (a
    # finding, not a failure of the model) the prediction is that of a right model
    spec = "white,random_walk"
    x = np.concatenate([simulate([("white", {"N": 1e-3 * f}), ("random_walk", {"K": 1e-5})],
                                 N // 2, FS, rng=s) for f, s in ((1.0, 81), (1.05, 82))])
    fit = fit_series(x, FS, spec)[0]
    ho = holdout_part(x, FS, spec, fit)
    assert "white.N" in {c["param"] for c in ho["changed"]}
    assert ho["chi2_per_dof"] > 10.0
    free = ho["changes_free"]
    assert free["params"] == sorted(c["param"] for c in ho["changed"])
    assert free["chi2_per_dof"] < right_model_limit(15)
    assert f"({free['chi2_per_dof']:.3g} with the changes below fitted)" \
        in parts_line(1.0, {"holdout": ho})


def test_no_change_named_no_changes_free_part() -> None:
    x = simulate(MODEL, N, FS, rng=91)
    fit = fit_series(x, FS, SPEC)[0]
    ho = holdout_part(x, FS, SPEC, fit)
    assert ho["changed"] == [] and "changes_free" not in ho


def _halves_differing_by(z: float, se: float = 0.01) -> tuple[SimpleNamespace, SimpleNamespace]:
    """Two halves' fits of white, bias instability and random walk whose log-parameters differ
    by ``z`` of their combined standard error each (the halves' errors ``se``, independent)."""
    def fit(shift: float) -> SimpleNamespace:
        values = {"N": 1e-3, "B": 1e-4, "K": 1e-5}
        terms = [TermFit(name, {k: values[k] * np.exp(shift)},
                         {k: (values[k] * np.exp(shift - 1.959963984540054 * se),
                              values[k] * np.exp(shift + 1.959963984540054 * se))})
                 for name, k in (("white", "N"), ("bias_instability", "B"),
                                 ("random_walk", "K"))]
        return SimpleNamespace(terms=terms, free_params=[(0, "N"), (1, "B"), (2, "K")],
                               param_cov=np.eye(3) * se * se, chi2_per_dof=1.0,
                               dispersion_of=lambda index, param: 1.0)

    return fit(z * se * np.sqrt(2.0)), fit(0.0)


def test_halves_that_differ_only_taken_together_are_a_finding_naming_no_parameter() -> None:
    from imunoise.analysis.distributions import chi2
    from imunoise.analysis.model_error import _joint_difference

    # three parameters, each 1.8 standard errors apart: below the Bonferroni level over
    # three (norm.isf(0.05 / 6) = 2.39) on its own interval and with the others held equal,
    # yet 3 x 1.8^2 = 9.72 lies beyond the chi-square(3) 5 % level 7.81
    a, b = _halves_differing_by(1.8)
    assert _changed(a, b) == []
    joint = _joint_difference(a, b, set())
    assert joint is not None
    assert joint["params"] == ["white.N", "bias_instability.B", "random_walk.K"]
    assert joint["dof"] == 3 and joint["chi2"] == pytest.approx(3 * 1.8 ** 2, rel=1e-9)
    assert joint["p"] == pytest.approx(float(chi2.sf(9.72, 3)), rel=1e-9)
    line = parts_line(1.0, {"holdout": {"changed": [], "joint_difference": joint}})
    assert ("finding: the halves differ in white.N, bias_instability.B, random_walk.K taken "
            "together (chi2 9.7 over 3 parameters, p 0.021), none beyond its own level") in line
    # a named parameter is left out: the other two at 1.8 give 6.48, beyond the
    # chi-square(2) level 5.99
    assert _joint_difference(a, b, {"white.N"})["params"] == ["bias_instability.B",
                                                              "random_walk.K"]
    # 1.5 standard errors each: 6.75 < 7.81, no finding
    assert _joint_difference(*_halves_differing_by(1.5), set()) is None



def test_a_random_walk_one_half_cannot_resolve_is_where_its_prediction_misses():
    # a random walk in the first half only: the second half's model (K at its bound, its
    # interval reaching 0) predicts the first half's long taus below what they measure, and
    # the miss names the amplitude the second half did not resolve
    halves = [simulate([("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-4})]
                       + ([("random_walk", {"K": 1e-4})] if k == 0 else []),
                       N // 2, FS, rng=40 + k) for k in (0, 1)]
    x = np.concatenate(halves)
    spec = "white,bias_instability,random_walk"
    ho = holdout_part(x, FS, spec, fit_series(x, FS, spec)[0])
    first = next(m for m in ho["misses"] if m["half"] == 1)
    assert first["by"] == 2
    assert [f["direction"] for f in first["failures"]] == ["measured above model"]
    lo, hi = first["failures"][0]["tau_s"]
    assert 5.0 <= lo <= 21.0 and hi > 300.0  # the long taus only
    (k,) = [u for u in first["unresolved"] if u["param"] == "random_walk.K"]
    assert k["ci95"][0] <= 1e-4 <= k["ci95"][1]  # the first half's own estimate
    # the change is named, and with it fitted the halves predict each other: no miss left
    assert "random_walk.K" in [c["param"] for c in ho["changed"]]
    assert ho["changes_free"]["misses"] == []
    assert not [f for f in holdout_findings(ho) if "misses" in f]


def test_a_miss_reads_as_where_and_what_the_predicting_half_left_unresolved():
    fail = {"tau_s": [20.48, 655.36], "max_abs_z": 7.16, "direction": "measured above model"}
    one = {"tau_s": [2.56, 2.56], "max_abs_z": 2.9, "direction": "measured below model"}
    misses = [{"half": 1, "by": 2, "failures": [fail],
               "unresolved": [{"param": "random_walk.K", "value": 3.63e-4,
                               "ci95": [2.64e-4, 5.01e-4]}]},
              {"half": 2, "by": 1, "failures": [one], "unresolved": []}]
    ho = {"chi2_per_dof": 31.4, "parts": 2, "changed": [], "misses": [],
          "changes_free": {"chi2_per_dof": 5.0, "params": ["white.N"], "misses": misses}}
    assert holdout_findings(ho) == [
        "the second half's model with the changes fitted misses the first half: measured "
        "above model at tau 20.5-655 s (max |z| 7.2); random_walk.K is not resolved on the "
        "second half (its interval reaches 0) but is 0.000363 [0.000264, 0.000501] on the "
        "first",
        "the first half's model with the changes fitted misses the second half: measured "
        "below model at tau 2.56 s (max |z| 2.9)"]
    # without named changes the plain predictions' misses are the ones told
    plain = {"chi2_per_dof": 3.2, "parts": 2, "changed": [], "misses": misses[1:]}
    assert holdout_findings(plain) == [
        "the first half's model misses the second half: measured below model at tau 2.56 s "
        "(max |z| 2.9)"]


# white noise, flicker and random walk with a Markov term the model leaves out: the model
# misses at 2-300 s, its shortest taus fit
_MISSED_MARKOV = [("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-4}),
                  ("random_walk", {"K": 1e-5}), ("gauss_markov", {"sigma": 4e-4, "T": 60.0})]
_WBK = "white,bias_instability,random_walk"


def test_a_misfit_widens_only_the_intervals_of_the_parameters_resting_on_its_taus() -> None:
    fit = fit_series(simulate(_MISSED_MARKOV, N, FS, rng=3), FS, _WBK,
                     intervals="jacobian")[0]
    assert fit.chi2_per_dof > 3.0  # the missing term costs it
    # the white level rests on the shortest taus, which fit: no widening
    assert fit.dispersion_of(0, "N") == 1.0
    # flicker rests on the taus of the miss, which fit worse than the curve as a whole
    # (6.7 per degree of freedom): the chi2/dof caps it
    assert fit.dispersion_of(1, "B") == pytest.approx(fit.chi2_per_dof, rel=1e-12)
    # a parameter the fit does not estimate gets the chi2/dof
    assert fit.dispersion_of(0, "tau") == pytest.approx(fit.chi2_per_dof, rel=1e-12)


def test_log_sensitivities_are_the_standardised_derivatives_of_the_log_allan_variance() -> None:
    from imunoise.analysis.fit.result import log_sensitivities

    fit = fit_series(simulate([("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5})],
                              1 << 16, FS, rng=2), FS, "white,random_walk",
                     intervals="jacobian")[0]
    n_sens, k_sens = log_sensitivities(fit, [(0, "N"), (1, "K")])
    # each amplitude's share of the Allan variance, twice (avar goes as its square), in
    # standard deviations of ln avar
    share = fit.term_avar[0] / fit.avar_fit
    unit = np.sqrt(fit.misfit.nu / 2.0)
    np.testing.assert_allclose(n_sens, 2.0 * share * unit, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(k_sens, 2.0 * (1.0 - share) * unit, rtol=1e-6, atol=1e-6)


def _white_changed_by(change: float, seed: int) -> tuple[np.ndarray, object]:
    """A record whose second half's white level is ``1 + change`` times its first's, with
    the Markov term the model leaves out, and its fit."""
    x = np.concatenate([simulate([(n, dict(p, N=p["N"] * scale) if n == "white" else p)
                                  for n, p in _MISSED_MARKOV], N, FS, rng=10 * seed + h)
                        for h, scale in ((0, 1.0), (1, 1.0 + change))])
    return x, fit_series(x, FS, _WBK, intervals="jacobian")[0]


def test_a_white_level_change_is_named_beside_a_misfit_at_long_tau(monkeypatch) -> None:
    # the white level 0.4 % higher in the second half. Each half's model misses at long tau
    # (chi2/dof 2-4), where the white level plays no part: its intervals are widened by the
    # misfit of its own taus, not by the chi2/dof. Over seeds 0-5, 5 of 6 name it this way
    # and 2 of 6 by the chi2/dof; with no change, none of 20 (the random walk, whose taus
    # the missing term disturbs, in 2 of 20 both ways)
    x, fit = _white_changed_by(0.004, seed=0)
    setup = holdout_halves(x, FS, _WBK, fit)
    done = [_half(setup, k) for k in (0, 1)]
    a, b = (d.fit for d in done)
    assert min(a.chi2_per_dof, b.chi2_per_dof) > 2.0
    named = {c["param"]: c for c in setup.part(done)["changed"]}
    assert "white.N" in named and named["white.N"]["values"][1] > named["white.N"]["values"][0]
    from imunoise.analysis.fit.result import FitResult

    monkeypatch.setattr(FitResult, "dispersion_of",
                        lambda self, index, param: max(1.0, float(self.chi2_per_dof)))
    assert "white.N" not in {c["param"] for c in _changed(a, b)}


def test_an_unchanged_white_level_beside_a_misfit_at_long_tau_is_not_named() -> None:
    x, fit = _white_changed_by(0.0, seed=0)
    assert holdout_part(x, FS, _WBK, fit)["changed"] == []
