"""Real data: six static replicate runs of one ADIS16405 (../shared/data/adis16405).

Default model white + bias_instability + random_walk on every axis. Gyros: the fitted N follows
each run's white plateau and agrees across the replicates within 3 % except run 5, whose raw
curve is 5-10 % higher (the replicates disagree there, in the data, not in the fit).
Accelerometers: the default model does not describe them and the fit must say so. Run 4 holds a
real shock around sample 404608 (a few samples, up to 17 deg/s): replacing it must change
nothing that matters. Figures: docs/fit.md.
"""

import math

import numpy as np
import pytest

from imunoise.analysis.fit import fit_allan
from tests._avar_batch import Curve
from tests.shared_paths import SHARED_DATA

DATA = SHARED_DATA / "adis16405"
FS = 100.0
MODEL = "white,bias_instability,random_walk"
CHANNELS = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
SHOCK = 404608

pytestmark = pytest.mark.skipif(not DATA.is_dir(),
                                reason="reference data ../shared/data/adis16405 not present")


def _load(run: int) -> np.ndarray:
    d = np.load(DATA / f"run{run}.npz")
    gyro = d["gyro_counts"] * float(d["gyro_scale_dps"]) * math.pi / 180.0
    accel = d["accel_counts"] * float(d["accel_scale_g"]) * 9.80665
    return np.column_stack([gyro, accel]).astype(np.float64)


@pytest.fixture(scope="module")
def fits():
    out = {ch: [] for ch in CHANNELS}
    raw = {ch: [] for ch in CHANNELS}
    for run in range(1, 7):
        data = _load(run)
        for j, ch in enumerate(CHANNELS):
            curve = Curve(data[:, j], FS)
            out[ch].append(fit_allan(curve, MODEL, intervals="jacobian"))
            raw[ch].append(_plateau(data[:, j]))
    return out, raw


def _cv(values) -> float:
    v = np.asarray(values)
    return float(v.std(ddof=1) / v.mean())


def _plateau(x: np.ndarray) -> float:
    """Raw white-noise level: median of adev * sqrt(tau) over tau = 0.32 .. 1.28 s, where the
    filter has let go and bias instability has not yet lifted the curve."""
    c = Curve(x, FS, max_m=128)
    sel = c.tau_s >= 0.32
    return float(np.median(c.dev[sel] * np.sqrt(c.tau_s[sel])))


@pytest.mark.parametrize("ch", CHANNELS[:3])
def test_gyro_white_noise_agrees_across_replicates(fits, ch):
    n = np.array([r.terms[0].params["N"] for r in fits[0][ch]])
    plateau = np.array(fits[1][ch])
    # the fit reads the white level where it is white, not where the sensor's filter bends
    # the shortest taus down (gyro z also carries a line near 20 Hz, so its plateau is not
    # a clean reference)
    if ch != "gyro_z":
        assert np.all(np.abs(n / plateau - 1) < 0.03), n / plateau
    # runs 1-4 and 6 agree within 3 %; run 5 is a different case, and the raw curve says so:
    # its white plateau lies 5-10 % above the others' (estimation error about 0.3 %)
    agree = np.delete(n, 4)
    assert _cv(agree) < 0.03, n
    others = np.delete(plateau, 4).mean()
    assert 1.05 < plateau[4] / others < 1.10


@pytest.mark.parametrize("ch", CHANNELS[3:])
def test_accelerometers_reject_the_default_model(fits, ch):
    # the accelerometer curves carry a hump near tau = 0.6 s and a steep rise beyond 10 s
    # that white + bias instability + random walk cannot follow: the fit must say so
    for r in fits[0][ch]:
        assert r.failures and r.chi2_per_dof > 10
def test_gyro_bias_instability_matches_the_published_floor(fits):
    # the Allan deviation minimum of run 1 is about 0.007 deg/s near tau = 80 s
    b = [r.terms[1].params["B"] for r in fits[0]["gyro_x"] + fits[0]["gyro_y"]]
    floor_dps = 0.664 * np.median(b) * 180 / math.pi
    assert 0.004 < floor_dps < 0.012


def test_shock_in_run_4_does_not_drag_the_estimates():
    data = _load(4)
    x = data[:, CHANNELS.index("gyro_x")]
    window = slice(SHOCK - 4, SHOCK + 2)  # the event spans a few samples on every axis
    assert np.max(np.abs(x[window])) > 12 * np.std(x[:SHOCK - 4])  # the shock is there
    clean = x.copy()
    clean[window] = np.linspace(x[SHOCK - 5], x[SHOCK + 2], SHOCK + 2 - (SHOCK - 4) + 2)[1:-1]
    with_shock = fit_allan(Curve(x, FS), MODEL, intervals="jacobian")
    without = fit_allan(Curve(clean, FS), MODEL, intervals="jacobian")
    n1, n0 = with_shock.terms[0].params["N"], without.terms[0].params["N"]
    assert abs(n1 / n0 - 1) < 1e-3
    b1, b0 = with_shock.terms[1].params["B"], without.terms[1].params["B"]
    lo, hi = without.terms[1].ci95["B"]
    assert lo <= b1 <= hi and abs(b1 / b0 - 1) < 0.05
