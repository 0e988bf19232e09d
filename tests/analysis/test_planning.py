"""The record-length planner: the predicted length gives intervals of the asked width."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.allan import oadev
from imunoise.analysis.fit import fit_allan
from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.planning import parse_targets, plan

FS = 10.0
CASES = [
    ("white:N=1e-3,random_walk:K=1e-4", "K=20%"),
    ("white:N=1e-3,gauss_markov:sigma=3e-3:T=5", "T=15%"),
    ("white:N=1e-3,bias_instability:B=2e-4,random_walk:K=2e-5", "B=10%"),
]


def _pairs(spec: str) -> list[tuple[str, dict[str, float]]]:
    out = []
    for entry in spec.split(","):
        name, *params = entry.split(":")
        out.append((name, {k: float(v) for k, v in (p.split("=") for p in params)}))
    return out


@pytest.mark.slow
@pytest.mark.parametrize(("spec", "target"), CASES, ids=["K", "T", "B"])
def test_predicted_length_gives_the_target_width(spec, target):
    """16 records of the predicted length, each fitted as imunoise fit does: the median
    relative half-width of the target's 95 % interval is within 25 % of the target (measured:
    0.99, 1.00 and 0.98 of it with 24 seeds)."""
    (p,) = plan(spec, FS, parse_targets(target, spec))
    n = int(round(p.record_s * FS))
    pairs = _pairs(spec)
    names = [n_ for n_, _ in pairs]
    widths = []
    for seed in range(16):
        curve = oadev(simulate(pairs, n, FS, rng=1000 + seed), FS, m="octave", ci=0.95)
        term = fit_allan(curve, names).terms[names.index(p.target.label)]
        lo, hi = term.ci95[p.target.param]
        widths.append((hi - lo) / (2 * term.params[p.target.param]))
    assert np.median(widths) == pytest.approx(p.target.relative, rel=0.25)


def test_the_likelihood_bound_is_never_longer_than_the_allan_fit():
    spec = CASES[0][0]
    (allan_plan,) = plan(spec, FS, parse_targets("K=20%", spec))
    (bound,) = plan(spec, FS, parse_targets("K=20%", spec), method="likelihood")
    assert bound.record_s <= allan_plan.record_s * 1.01
    assert bound.record_s == pytest.approx(allan_plan.record_s, rel=0.2)  # K: both near 33 min


def test_halving_the_width_needs_a_longer_record():
    spec = CASES[0][0]
    a, b = plan(spec, FS, parse_targets("random_walk.K=20%,white.N=2%", spec))
    (c,) = plan(spec, FS, parse_targets("K=10%", spec))
    assert c.record_s > 2.5 * a.record_s  # K's width falls faster than n^-1/2 but not as n^-1
    assert b.target.label == "white" and b.record_s < a.record_s


def test_unreachable_and_bad_targets():
    spec = "white:N=1e-3,random_walk:K=1e-12"
    (p,) = plan(spec, FS, parse_targets("K=1%", spec))
    assert p.record_s is None and not p.to_dict()["reachable"]
    with pytest.raises(ValueError, match="no parameter 'Q'"):
        parse_targets("Q=10%", spec)
    with pytest.raises(ValueError, match="write TERM.sigma"):
        parse_targets("sigma=10%", "white:N=1,gauss_markov:sigma=1:T=5,gauss_markov:sigma=1:T=50")
    with pytest.raises(ValueError, match="not a number"):
        parse_targets("K=ten%", spec)
    with pytest.raises(ValueError, match="give K"):
        plan("white:N=1e-3,random_walk", FS, [])
