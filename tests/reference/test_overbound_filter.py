"""A one-axis attitude filter (angle and bias) on simulated data whose true noise is the model
fitted to a real gyro: with the fitted (nominal) noise parameters and with the over-bounding
ones. The bounding filter is conservative: its normalised estimation error squared (NEES),
averaged over the runs and the aiding instants of each one-minute window, stays at or below the
95 % chi-square bound in every window."""

from __future__ import annotations

import numpy as np
from scipy import stats

from imunoise.analysis.allan import oadev
from imunoise.analysis.discrete import DiscreteModel, discretize
from imunoise.analysis.fit import fit_allan
from imunoise.analysis.noise_stream import simulate
from imunoise.analysis.overbound import overbound

FS = 50.0  # filter rate, Hz
SECONDS = 600.0
AID_EVERY = 50  # an absolute angle measurement each second
AID_SIGMA = 2e-3  # rad
RUNS = 100
WINDOW_AIDS = 60  # NEES windows of one minute: 60 aiding instants x 100 runs


def attitude_nees(dm: DiscreteModel, gyro: np.ndarray) -> np.ndarray:
    """Mean NEES of the angle per window (over the runs and the window's aiding instants,
    just before each update) for a filter built on ``dm``.

    States: angle, random-walk bias and one state per Markov bias of ``dm``; the gyro reading
    drives the angle, an absolute angle is measured every ``AID_EVERY`` samples. ``gyro`` is
    (runs, samples) of a sensor at rest, so the true angle is zero. The covariance does not
    depend on the data and is propagated once for all runs."""
    dt = 1.0 / FS
    a = np.array([s.a_d for s in dm.markov])
    q = np.array([s.driving_sigma**2 for s in dm.markov])
    nx = 2 + a.size
    F = np.eye(nx)
    F[0, 1:] = -dt
    F[2:, 2:] = np.diag(a)
    Q = np.diag(np.concatenate(([(dm.white_sigma * dt) ** 2, dm.random_walk_step**2], q)))
    P = np.diag(np.concatenate(([AID_SIGMA**2, 1e-4], [s.sigma**2 for s in dm.markov])))
    H = np.zeros(nx)
    H[0] = 1.0
    x = np.zeros((gyro.shape[0], nx))
    per_aid = []
    for k in range(gyro.shape[1]):
        x = x @ F.T
        x[:, 0] += gyro[:, k] * dt
        P = F @ P @ F.T + Q
        if (k + 1) % AID_EVERY == 0:
            per_aid.append(float(np.mean(x[:, 0] ** 2) / P[0, 0]))  # the true angle is 0
            z = np.random.default_rng(k).normal(0.0, AID_SIGMA, gyro.shape[0])
            gain = P[:, 0] / (P[0, 0] + AID_SIGMA**2)
            x += np.outer(z - x[:, 0], gain)
            P = P - np.outer(gain, H @ P)
    return np.array(per_aid).reshape(-1, WINDOW_AIDS).mean(axis=1)


def test_bounding_parameters_keep_the_filter_conservative(shared_data):
    d = np.load(shared_data / "adis16405" / "run1.npz")
    y = d["gyro_counts"][:, 0] * float(d["gyro_scale_dps"]) * np.pi / 180
    curve = oadev(y, 100.0, m="octave", ci=0.95)
    fitted = fit_allan(curve, "white,bias_instability,random_walk")
    model = fitted.params  # the truth of this simulation: the model fitted to the real gyro
    # the same channel seen at the filter's rate: the model's curve and the measured band
    upper = np.fmax(curve.ci_high, np.sqrt(fitted.model_avar(curve.tau_s)))
    keep = curve.tau_s >= 1.0 / FS
    bound = overbound(curve.tau_s[keep], upper[keep], FS, duration_s=y.size / 100.0)
    assert bound.holds
    nominal = discretize(model, FS, tau_range_s=(1.0 / FS, SECONDS))
    gyro = np.stack([simulate(model, int(SECONDS * FS), FS, rng=500 + r) for r in range(RUNS)])
    nees_nominal = attitude_nees(nominal, gyro)
    nees_bound = attitude_nees(bound.discrete(), gyro)
    dof = RUNS * WINDOW_AIDS  # one dof per run and aiding instant
    limit = stats.chi2.ppf(0.95, dof) / dof
    assert np.all(nees_bound <= limit), (nees_bound.max(), limit)
    assert nees_bound.mean() < nees_nominal.mean()
    # the nominal filter is about consistent (mean NEES near 1), the bounding one below it
    assert 0.6 < nees_nominal.mean() < 1.6
    print(f"NEES mean/max over {nees_bound.size} windows, bound {limit:.3f}: nominal "
          f"{nees_nominal.mean():.3f}/{nees_nominal.max():.3f} "
          f"({int(np.sum(nees_nominal > limit))} above), bounding "
          f"{nees_bound.mean():.3f}/{nees_bound.max():.3f} ({int(np.sum(nees_bound > limit))} "
          "above)")
