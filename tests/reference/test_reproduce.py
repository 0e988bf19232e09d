"""Seed-paper figures recomputed from their definitions."""

import math

import numpy as np
import pytest

from imunoise.analysis.reproduce import (
    HEMERLY,
    PETKOV_GYRO,
    arma01_from_sigmas,
    markov_coefficient,
    markov_driving_std,
    moment_matrix,
    petkov2010,
    white_density_from_rms,
)
from imunoise.cli import main


def test_petkov_markov_coefficient_and_driving_noise():
    a = markov_coefficient(0.01, 120.0)
    assert round(a, 6) == PETKOV_GYRO["a_d"]
    # A discrete Markov process driven at this level keeps the stationary sigma.
    drive = markov_driving_std(1.0, 0.01, 120.0)
    assert drive**2 / (1 - a * a) == pytest.approx(1.0, rel=1e-12)


def test_petkov_white_level_from_rms_matches_their_n():
    n = white_density_from_rms(PETKOV_GYRO["rms_dps"], 0.01)
    assert n == pytest.approx(PETKOV_GYRO["N_dps_rts"], rel=0.02)


def test_hemerly_arma01_relations():
    e0, e1 = arma01_from_sigmas(HEMERLY["sigma1"], HEMERLY["sigma2"])
    assert (round(e0, 1), round(e1, 1)) == (133.7, -98.1)
    # The MA(1) autocovariances equal those of the differenced random walk plus white noise.
    s1, s2 = HEMERLY["sigma1"], HEMERLY["sigma2"]
    assert e0**2 + e1**2 == pytest.approx(s1**2 + 2 * s2**2)
    assert e0 * e1 == pytest.approx(-(s2**2))


def test_hemerly_condition_number_explodes_towards_unit_root():
    c = np.linalg.cond(moment_matrix(HEMERLY["alpha"]))
    assert 1e8 < c < 1e10
    assert np.linalg.cond(moment_matrix(0.99)) < c / 1e3


def test_moment_matrix_predicts_simulated_autocovariances():
    # Markov + random walk + white, differenced by (1 - aL)(1 - L): lags 0..2 follow M.
    rng = np.random.default_rng(5)
    a, n = 0.9, 400_000
    qm, qr, sv = 0.5, 0.2, 1.0
    from scipy.signal import lfilter

    y = (lfilter([1.0], [1.0, -a], rng.normal(0, math.sqrt(qm), n))
         + np.cumsum(rng.normal(0, math.sqrt(qr), n)) + rng.normal(0, math.sqrt(sv), n))
    z = lfilter([1.0, -(1 + a), a], [1.0], y)[10:]
    acov = [np.mean(z[k:] * z[: z.size - k]) for k in range(3)]
    pred = moment_matrix(a) @ np.array([qm, qr, sv])
    assert np.allclose(acov, pred, rtol=0.03, atol=0.02)


def test_petkov_table_without_simulation_has_verdicts():
    rows = petkov2010(simulate_models=False)
    assert [r.verdict.split()[0] for r in rows if r.paper is not None] == ["agrees"] * 3


def test_reproduce_rejects_unknown_paper(capsys):
    assert main(["reproduce", "smith1999"]) == 2
    assert "smith1999" in capsys.readouterr().err
