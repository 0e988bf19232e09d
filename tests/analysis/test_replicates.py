"""Replicates of one unit: shapes shared when they agree, named when they differ.

Three simulated runs of 2^17 samples at 100 Hz (white, random walk, a resonance at 20 Hz with
Q = 50). The homogeneity test is set at a family-wise 5 %: on runs with identical parameters
the share of seeds where any parameter is named is about 5 %; 20 seeds with at most 2 named
fails with probability 8 % if the rate were exactly 5 % and < 1 % if it were 1 % (the
Bonferroni level is conservative), so a false-alarm rate well above 5 % fails.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from imunoise.analysis.noise_stream import NoiseStream
from imunoise.analysis.replicates import Estimate, Run, fit_replicates, homogeneity

FS = 100.0
N = 1 << 17
MODEL = "white,random_walk,resonance"


def _runs(seed: int, f0s: list[float]) -> list[Run]:
    out = []
    for r, f0 in enumerate(f0s):
        model = [("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5}),
                 ("resonance", {"sigma": 1e-2, "f0": f0, "Q": 50.0})]
        out.append(Run(f"run{r + 1}", NoiseStream(model, FS, seed=1000 * seed + r).take(N), FS))
    return out


def test_homogeneity_is_the_chi_square_of_the_log_estimates() -> None:
    # symmetric intervals in log space: sd = 0.1 each; values e^0, e^0.2
    e = [Estimate(1.0, (math.exp(-0.1 * 1.959964), math.exp(0.1 * 1.959964))),
         Estimate(math.exp(0.2), (math.exp(0.2 - 0.1 * 1.959964),
                                  math.exp(0.2 + 0.1 * 1.959964)))]
    pooled, ci, q, dof, p, used = homogeneity(e, ["a", "b"])
    assert pooled == pytest.approx(math.exp(0.1))
    assert q == pytest.approx(2.0)  # (0.1/0.1)^2 twice
    assert dof == 1 and p == pytest.approx(stats.chi2.sf(2.0, 1))
    # se 0.1/sqrt(2) widened by sqrt(q/dof) = sqrt(2): 0.1
    assert ci[1] == pytest.approx(math.exp(0.1 + 1.959964 * 0.1), rel=1e-6)
    assert used == ["a", "b"]


def test_an_interval_reaching_zero_is_left_out() -> None:
    e = [Estimate(1.0, (0.9, 1.1)), Estimate(1e-9, (0.0, 0.5)), None,
         Estimate(1.05, (0.95, 1.15))]
    *_, dof, _, used = homogeneity(e, ["a", "b", "c", "d"])
    assert used == ["a", "d"] and dof == 1


def test_the_side_of_the_interval_facing_the_pooled_value_weighs() -> None:
    # run b lies above a; only b's lower half-interval matters, and it is wide
    e = [Estimate(1.0, (0.98, 1.02)), Estimate(1.5, (1.0, 1.52))]
    *_, q, dof, p, _ = homogeneity(e, ["a", "b"])
    assert q < 3.84 and p > 0.05


def test_identical_runs_name_no_parameter() -> None:
    named = []
    for seed in range(20):
        res = fit_replicates(_runs(seed, [20.0, 20.0, 20.0]), MODEL, intervals="jacobian",
                             error_parts=False)
        assert [h.param for h in res.shared] == ["f0", "Q"]
        f0 = res.shared[0]
        assert 19.0 < f0.pooled < 21.0 and f0.ci95[0] < f0.pooled < f0.ci95[1]
        if res.differ:
            named.append((seed, [(h.term, h.param, round(h.q, 2)) for h in res.differ]))
    assert len(named) <= 2, named


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_resonance_moved_by_5_percent_is_named(seed: int) -> None:
    res = fit_replicates(_runs(seed, [20.0, 20.0, 21.0]), MODEL, intervals="jacobian",
                         error_parts=False)
    names = [(h.term, h.param) for h in res.differ]
    assert ("resonance", "f0") in names
    f0_runs = res.per_run_values(res.differ[names.index(("resonance", "f0"))])
    f0 = [e.value for e in f0_runs]
    assert f0[2] / f0[0] == pytest.approx(1.05, abs=0.01)
    # each run's f0 is its spectrum's peak, to about 0.01 Hz (the Allan curve gives 0.05 Hz)
    assert all(e.source == "psd" and e.ci95[1] - e.ci95[0] < 0.04 for e in f0_runs), f0_runs
    assert all(abs(v - t) < 0.05 for v, t in zip(f0, (20.0, 20.0, 21.0), strict=True)), f0
    # amplitudes are compared on the curve's own fits, whose intervals carry the shapes'
    sigma = next(h for h in res.amplitudes if h.param == "sigma")
    assert all(e.source == "allan" and e.ci95[0] < e.value < e.ci95[1]
               for e in res.per_run_values(sigma))
    # a shape that differs is not held: each run keeps its own f0 in the refit
    assert res.tied_fits[2].terms[2].params["f0"] == pytest.approx(f0[2], rel=1e-3)
    # the Q that agrees is held at its pooled value in every run's refit
    q = next(h for h in res.shared if h.param == "Q")
    assert not q.differs
    assert all(f.terms[2].params["Q"] == pytest.approx(q.pooled) for f in res.tied_fits)


def test_one_run_is_no_replicate() -> None:
    with pytest.raises(ValueError, match="at least two"):
        fit_replicates(_runs(0, [20.0]), MODEL)


def test_loop_per_run_and_the_common_term_set() -> None:
    # runs with a strong resonance: one round of the loop from white,random_walk adds it in
    # each run, and that set is fitted to the unit
    runs = _runs(5, [20.0, 20.0])
    res = fit_replicates(runs, "white,random_walk", rounds=1, intervals="jacobian",
                         error_parts=False)
    assert res.per_run_terms == [["white", "random_walk", "resonance"]] * 2, res.per_run_terms
    assert res.common_terms == (["white", "random_walk", "resonance"], 2)
    assert "resonance" in res.term_set
    assert np.isfinite(res.to_dict()["shared"][0]["value"])


def test_repeated_terms_are_matched_by_shape_not_by_order() -> None:
    from types import SimpleNamespace

    from imunoise.analysis.fit import TermFit
    from imunoise.analysis.replicates import _order

    names = ["white", "resonance", "resonance"]
    run_a = SimpleNamespace(terms=[TermFit("white", {"N": 1.0}, {}),
                                   TermFit("resonance", {"sigma": 1, "f0": 0.56, "Q": 5}, {}),
                                   TermFit("resonance", {"sigma": 1, "f0": 13.7, "Q": 4}, {})])
    run_b = SimpleNamespace(terms=[run_a.terms[0], run_a.terms[2], run_a.terms[1]])
    assert _order(run_a, names) == [0, 1, 2]
    assert _order(run_b, names) == [0, 2, 1]  # the 0.56 Hz resonance is the first in both


def test_a_runs_loop_applies_a_cut_to_that_run_and_goes_on(monkeypatch) -> None:
    # the loop on a file alone: a warm-up cut judged first is applied to the record (the next
    # round sees the samples after it, on the time scale of the file), then a term
    from types import SimpleNamespace

    import imunoise.analysis.diagnosis as diagnosis
    from imunoise.analysis.replicates import loop_terms

    calls: list[dict] = []

    def suggestion(args: list[str], model: str) -> SimpleNamespace:
        return SimpleNamespace(significant=True, term="x", apply={"model": model, "args": args})

    rounds = [[suggestion(["--skip", "100"], "white,random_walk")],
              [suggestion(["--split", "50"], "white,random_walk")],
              [suggestion([], "white,random_walk,gauss_markov")],
              []]

    def fake(values, fs_hz, model, **kw):
        calls.append({"n": len(values), "model": model, **kw})
        return SimpleNamespace(suggestions=rounds[len(calls) - 1])

    monkeypatch.setattr(diagnosis, "diagnose", fake)
    x = np.zeros(int(1000 * FS))
    run = Run("r", x, FS, diagnose_kwargs={"t0_s": 7.0, "units": "m/s^2"})
    assert loop_terms(run, "white,random_walk", 5) == ["white", "random_walk", "gauss_markov"]
    assert [c["n"] for c in calls] == [x.size, x.size - 10000, x.size - 10000, x.size - 10000]
    assert [c["t0_s"] for c in calls] == [7.0, 107.0, 107.0, 107.0]
    assert [c["time_origin_s"] for c in calls] == [0.0, 100.0, 100.0, 100.0]
    # the split (50 s after the first sample analysed) makes a segment of its own
    assert list(calls[2]["segment_starts"]) == [0, 5000]
    assert calls[3]["model"] == "white,random_walk,gauss_markov"
    assert all(c["units"] == "m/s^2" for c in calls)
    # a cut uses a round: with two rounds the term is never reached
    calls.clear()
    assert loop_terms(run, "white,random_walk", 2) == ["white", "random_walk"]
    assert len(calls) == 2
