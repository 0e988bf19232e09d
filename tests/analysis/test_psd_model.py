"""The model PSD as the log-frequency estimator's expectation, against simulation, term by term.

For each model, R seeded records are simulated and estimated with ``log_psd``; the mean of the
estimates at each point has relative standard deviation ``sqrt(2/(nu R))`` (``nu`` the point's
degrees of freedom). The standardised differences z against the expectation must behave like
standard normals: largest |z| below 4.5 over the ~190 points (probability of exceeding it about
1e-3) and mean z^2 within 0.7-1.4 (its spread over 190 mildly correlated points is near 0.12).
Where the expectation differs from the model PSD at the point (lines, resonances, filters, the
ramp), the same test on the point value must fail, so the test can fail.
"""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.psd import log_psd
from imunoise.analysis.psd_model import expected_log_psd, psd_z, whittle_part
from imunoise.analysis.terms import model_psd

FS = 100.0
N = 1 << 17
R = 8

CASES = {
    "white": ([("white", {"N": 1e-3})], False),
    "quantization": ([("white", {"N": 1e-4}), ("quantization", {"Q": 1e-4})], False),
    "bias_instability": ([("white", {"N": 1e-4}), ("bias_instability", {"B": 1e-3})], True),
    "random_walk": ([("white", {"N": 1e-4}), ("random_walk", {"K": 1e-4})], False),
    "rate_ramp": ([("white", {"N": 1e-5}), ("rate_ramp", {"R": 1e-4})], True),
    "gauss_markov": ([("white", {"N": 1e-4}), ("gauss_markov", {"sigma": 1e-3, "T": 0.05})],
                     False),
    "sinusoid": ([("white", {"N": 1e-4}), ("sinusoid", {"A": 1e-3, "f": 7.3})], True),
    "resonance": ([("white", {"N": 1e-4}), ("resonance", {"sigma": 1e-3, "f0": 20.7, "Q": 30.0})],
                  True),
    "moving_average": ([("white", {"N": 1e-3}), ("random_walk", {"K": 1e-5}),
                        ("moving_average", {"taps": 4.0})], True),
    "bartlett": ([("white", {"N": 1e-3}), ("bartlett", {"taps": 2.0})], True),
    "lowpass": ([("white", {"N": 1e-3}), ("lowpass", {"fc": 10.0})], False),
    "two_markov_and_line": ([("white", {"N": 1e-4}), ("gauss_markov", {"sigma": 1e-3, "T": 0.02}),
                             ("gauss_markov", {"sigma": 3e-4, "T": 30.0}),
                             ("sinusoid", {"A": 3e-4, "f": 31.0})], True),
}


def _mean_estimate(model, n=N, r=R, seed=1000):
    ests = [log_psd(simulate(model, n, FS, rng=seed + s), FS) for s in range(r)]
    return ests[0], np.mean([e.psd for e in ests], axis=0)


def _z(mean, expected, dof, r=R):
    return (mean - expected) / (expected * np.sqrt(2.0 / (dof * r)))


@pytest.mark.parametrize("case", sorted(CASES))
def test_expectation_matches_the_mean_of_simulated_estimates(case):
    model, point_value_fails = CASES[case]
    est, mean = _mean_estimate(model)
    expected = expected_log_psd(model, est, FS)
    z = _z(mean, expected, est.dof)
    assert len(est) > 150
    assert np.max(np.abs(z)) < 4.5, (case, float(est.f_hz[np.argmax(np.abs(z))]))
    assert 0.7 < float(np.mean(z**2)) < 1.4
    naive = model_psd(model, est.f_hz, FS)
    z_naive = _z(mean, naive, est.dof)
    if point_value_fails:
        assert not np.all(np.abs(z_naive) < 4.5)


def test_narrow_resonance_core_and_tails():
    """A resonance narrower than the convolution grid: its core is a line, its Lorentzian
    tails (4 % of the white level three bins away) stay on the grid. The peak's power is
    itself random over a record (coherence time Q/(pi f0) = 46 s): the peak point is held to
    25 % (its spread over 8 records of 2621 s is near 7 %), the others to the dof."""
    model = [("white", {"N": 1e-4}), ("resonance", {"sigma": 1e-3, "f0": 20.7, "Q": 3000.0})]
    est, mean = _mean_estimate(model, n=1 << 18)
    expected = expected_log_psd(model, est, FS)
    peak = int(np.argmin(np.abs(est.f_hz - 20.7)))
    assert abs(mean[peak] / expected[peak] - 1.0) < 0.25
    z = _z(mean, expected, est.dof)
    z[peak] = 0.0
    assert np.max(np.abs(z)) < 4.5
    tails = model_psd([model[0]], est.f_hz, FS)
    z_tails = _z(mean, tails, est.dof)
    z_tails[peak] = 0.0
    assert np.max(np.abs(z_tails)) > 6.0  # without the tails the neighbours fail


def test_whittle_part_and_z_of_a_correct_model():
    model = CASES["gauss_markov"][0]
    x = simulate(model, 1 << 18, FS, rng=7)
    est = log_psd(x, FS)
    expected = expected_log_psd(model, est, FS)
    part = whittle_part(est.psd, est.dof, expected)
    assert part is not None and part["bins"] == len(est)
    assert 0.75 < part["deviance_per_bin"] < 1.3
    assert part["outside_95"] < 0.12
    z = psd_z(est.psd, est.dof, expected)
    assert abs(float(np.mean(z))) < 0.3 and 0.7 < float(np.std(z)) < 1.3
    wrong = whittle_part(est.psd, est.dof, 2.0 * expected)
    assert wrong["deviance_per_bin"] > 10.0


def test_psd_z_far_tails_are_finite_and_signed():
    z = psd_z(np.array([1e-6, 1.0, 1e6]), np.array([50.0, 50.0, 50.0]), np.ones(3))
    assert z[0] < -8 and abs(z[1]) < 0.5 and z[2] > 8 and np.all(np.isfinite(z))


def test_layout_mismatch_is_refused():
    est = log_psd(simulate([("white", {"N": 1e-3})], 1 << 16, FS, rng=1), FS)
    with pytest.raises(ValueError, match="bin layout"):
        expected_log_psd([("white", {"N": 1e-3})], est, FS, nperseg=128)


def test_the_hann_kernel_in_closed_form_is_the_windows_transform() -> None:
    # against the direct sum over the window's samples, at whole cycles (where the closed
    # form divides by nearly zero), at the main lobe's edges and between
    from imunoise.analysis.dsp import hann
    from imunoise.analysis.psd_model import _hann_kernel

    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 256, 4096):
        u = np.concatenate([rng.uniform(-0.6, 0.6, 100),
                            [0.0, 1.0, -2.0, 1.0 / n, -1.0 / n, 2.0 / n, 0.5, 1e-9]])
        w = hann(n)
        direct = np.abs(np.exp(-2j * np.pi * np.outer(u, np.arange(n))) @ w) ** 2 \
            / np.sum(w**2)
        assert np.allclose(_hann_kernel(u, n), direct, rtol=1e-8, atol=1e-11 * direct.max())
    # its integral over one period is 1
    u = np.linspace(-0.5, 0.5, 200001)
    assert np.trapezoid(_hann_kernel(u, 64), u) == pytest.approx(1.0, rel=1e-6)


def test_cascade_gains_handed_to_another_process_give_the_same_expectation(monkeypatch):
    # the diagnosis's spectrum worker hands its gains to the parent, whose later workers
    # must compute bit for bit what they would have computed themselves
    from imunoise.analysis import psd_model

    model = CASES["gauss_markov"][0]
    est = log_psd(simulate(model, 1 << 18, FS, rng=3), FS)
    monkeypatch.setattr(psd_model, "_GRID_GAINS", type(psd_model._GRID_GAINS)())
    computed = expected_log_psd(model, est, FS)
    gains = psd_model.grid_gains()
    assert len(gains) >= 6  # levels 1.. of the cascade, three folds each
    # what a worker sends back is a pickled copy
    sent = {k: np.array(v) for k, v in gains.items()}
    monkeypatch.setattr(psd_model, "_GRID_GAINS", type(psd_model._GRID_GAINS)())
    psd_model.adopt_grid_gains(sent)
    sizes: list[int] = []
    cascade = psd_model._cascade_gain

    def counted(f, fs, level):
        sizes.append(len(f))
        return cascade(f, fs, level)
    monkeypatch.setattr(psd_model, "_cascade_gain", counted)
    again = expected_log_psd(model, est, FS)
    assert np.array_equal(again.view(np.int64), computed.view(np.int64))
    grid = {k[1] for k in gains}
    assert sizes and not grid & set(sizes)  # no grid gain computed again
    assert not any(g.flags.writeable for g in psd_model.grid_gains().values())


def test_cascade_gains_kept_are_bounded(monkeypatch):
    from imunoise.analysis import psd_model

    monkeypatch.setattr(psd_model, "_GRID_GAINS", type(psd_model._GRID_GAINS)())
    many = {(100.0, 64, j, 0): np.ones(64) for j in range(1, psd_model._GRID_GAINS_KEPT + 40)}
    psd_model.adopt_grid_gains(many)
    kept = psd_model.grid_gains()
    assert len(kept) == psd_model._GRID_GAINS_KEPT
    assert (100.0, 64, psd_model._GRID_GAINS_KEPT + 39, 0) in kept  # the newest stay
