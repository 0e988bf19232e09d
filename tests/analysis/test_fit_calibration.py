"""Calibration of the misfit: data simulated from a known model and fitted with that model.

For each model and record length, 20 seeds: the mean of chi2_per_dof must lie within 1 +- 0.3
and ``failures`` must be empty in at least 90 % of the seeds (the |z| threshold is set for a
10 % family-wise rate). The curves come from the vectorised test helper, which equals the
Allan engine (tests/test_fit.py checks it); the intervals are not under test here, so the fit
uses its quick linearised intervals.
"""

import numpy as np
import pytest

from imunoise.analysis.fit import find_line, fit_allan
from imunoise.analysis.noise_stream import NoiseStream
from tests._avar_batch import Curve

FS = 100.0
SEEDS = 20

MODELS = {
    "white+bias_instability+random_walk": [
        ("white", {"N": 1e-3}), ("bias_instability", {"B": 2e-4}), ("random_walk", {"K": 2e-5})],
    "white+gauss_markov": [("white", {"N": 1e-3}), ("gauss_markov", {"sigma": 5e-4, "T": 20.0})],
    "quantization+white+random_walk": [
        ("quantization", {"Q": 2e-5}), ("white", {"N": 1e-3}), ("random_walk", {"K": 3e-5})],
    "white+sinusoid+random_walk": [
        ("white", {"N": 1e-3}), ("sinusoid", {"A": 2e-3, "f": 2.7}),
        ("random_walk", {"K": 2e-5})],
    "white+random_walk+rate_ramp": [
        ("white", {"N": 1e-3}), ("random_walk", {"K": 2e-5}), ("rate_ramp", {"R": 2e-6})],
}
CASES = [
    ("white+bias_instability+random_walk", 1 << 15),
    ("white+bias_instability+random_walk", 1 << 17),
    ("white+gauss_markov", 1 << 15),
    ("white+gauss_markov", 1 << 18),
    ("quantization+white+random_walk", 1 << 16),
    ("white+sinusoid+random_walk", 1 << 17),
    ("white+random_walk+rate_ramp", 1 << 16),
]


@pytest.mark.parametrize(("name", "n"), CASES)
def test_correct_model_gives_chi2_near_one_and_no_failures(name, n):
    model = MODELS[name]
    chi2, failed = [], 0
    for seed in range(SEEDS):
        x = NoiseStream(model, FS, 1000 + seed).take(n)
        line = find_line(x, FS) if name.count("sinusoid") else None
        res = fit_allan(Curve(x, FS), [t for t, _ in model], line=line, intervals="jacobian")
        chi2.append(res.chi2_per_dof)
        failed += bool(res.failures)
    mean = float(np.mean(chi2))
    assert 0.7 <= mean <= 1.3, (mean, np.round(chi2, 2))
    assert failed <= 2, failed
