"""A held line's fitted amplitude against the spectrum's
(:func:`imunoise.analysis.evidence.line_power.line_powers`)."""

from __future__ import annotations

import math
import pathlib

import numpy as np
import pytest

from imunoise.analysis.evidence import line_powers, spectral_lines
from imunoise.analysis.noise_stream import simulate

FS = 50.0
N = int(2 * 3600 * FS)
BASE = [("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
        ("random_walk", {"K": 2e-6})]
F1, A1 = 0.55, 2e-4       # Hz, rad/s: the line the model holds
F2, A2 = 0.47, 1.2e-4     # Hz, rad/s: a second line 15 % below it
N_SEEDS = 40
SHARED = pathlib.Path(__file__).resolve().parents[2].parent / "shared" / "data"


def _record(seed: int, second: bool = False) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.arange(N) / FS
    x = simulate(BASE, N, FS, rng=seed) + A1 * np.sin(2 * np.pi * F1 * t + rng.uniform(0, 6.3))
    if second:
        x += A2 * np.sin(2 * np.pi * F2 * t + rng.uniform(0, 6.3))
    return x


def _exact(a: float) -> tuple[str, float, float, tuple[float, float]]:
    """The line held at amplitude ``a`` with an interval far narrower than the spectrum's:
    the comparison then measures the spectrum's estimate alone."""
    return ("sinusoid", F1, a, (a * (1 - 1e-4), a * (1 + 1e-4)))


def test_the_spectrum_amplitude_interval_covers_the_truth():
    # 95 % intervals on 40 records: 35-40 cover when the stated spread is right (binomial 5 %
    # tails); the z spread within 0.75-1.3 (the sd of 40 normal draws lies in 0.8-1.2)
    covered, zs = 0, []
    for seed in range(N_SEEDS):
        f = line_powers([_record(2000 + seed)], FS, [_exact(A1)])
        line = f.details["lines"][0]
        lo, hi = line["A_spectrum_ci95"]
        covered += lo <= A1 <= hi
        zs.append(line["z"])
    assert 35 <= covered <= 40
    assert 0.75 <= float(np.std(zs)) <= 1.3
    assert abs(float(np.mean(zs))) < 0.5  # no bias: the mean of 40 has sd 0.16


def test_a_line_fitted_with_its_neighbours_power_is_named_with_the_neighbour():
    x = _record(7, second=True)
    found = spectral_lines([x], FS, exclude_hz=[F1]).details["lines"]
    lumped = math.hypot(A1, A2)  # what an Allan fit holding one line gives it at most
    f = line_powers([x], FS, [_exact(lumped)], found=found, units="rad/s")
    assert f.significant
    line = f.details["lines"][0]
    assert line["A_spectrum"] == pytest.approx(A1, rel=0.08)
    assert [round(n["f_hz"], 2) for n in line["neighbours"]] == [F2]
    assert line["neighbours"][0]["A"] == pytest.approx(A2, rel=0.15)
    assert "The 0.55 Hz line is fitted at 0.000233 rad/s" in f.why
    assert "the line beside it that the model lacks (0.4699 Hz, 0.000119 rad/s)" in f.why
    assert "the fit gives it that line's power too" in f.why


def test_a_right_amplitude_is_not_flagged():
    x = _record(7)
    f = line_powers([x], FS, [_exact(A1)])
    assert not f.significant
    assert f.details["lines"][0]["neighbours"] == []
    assert "Each line of the model has the power the spectrum gives it" in f.why


def test_an_amplitude_the_fit_does_not_resolve_is_not_compared():
    f = line_powers([_record(7)], FS, [("sinusoid", F1, 1e-30, (0.0, 3e-4)),
                                       ("sinusoid#2", 3.3, 2e-4, None)])
    assert f.p_value == 1.0 and not f.details.get("lines")
    assert "no line of the model resolved both in the fit and in the spectrum" in f.why


def test_a_line_the_spectrum_does_not_show_is_not_compared():
    # the model holds a line at 1.7 Hz that the record does not have
    f = line_powers([_record(7)], FS, [("sinusoid", 1.7, 2e-4, (1.5e-4, 2.5e-4))])
    assert not f.details.get("lines")


@pytest.mark.skipif(not (SHARED / "adis16405" / "run6.npz").exists(),
                    reason="../shared/data (ADIS16405 recordings) not present")
def test_adis16405_run6_accel_x_line_at_1_69_hz_carries_the_1_59_hz_line():
    d = np.load(SHARED / "adis16405" / "run6.npz")
    x = d["accel_counts"][:, 0] * float(d["accel_scale_g"]) * 9.80665
    fs = float(d["fs_hz"])
    # the loop's final model there: the two lines' frequencies and Allan-fitted amplitudes
    held = [("sinusoid", 0.56465, 0.009747, (0.0096, 0.00988)),
            ("sinusoid#2", 1.69340, 0.003425, (0.00308, 0.00377))]
    found = spectral_lines([x], fs, exclude_hz=[0.56465, 1.6934]).details["lines"]
    f = line_powers([x], fs, held, found=found, units="m/s^2")
    assert f.significant
    by_f = {round(c["f_hz"], 2): c for c in f.details["lines"]}
    # the 0.565 Hz line agrees with the spectrum; the 1.69 Hz line is 1.6 times its own
    assert abs(by_f[0.56]["z"]) < 2.5
    assert 0.0019 < by_f[1.69]["A_spectrum"] < 0.0024
    assert by_f[1.69]["z"] > 4.0
    assert [round(n["f_hz"], 2) for n in by_f[1.69]["neighbours"]] == [1.59]
