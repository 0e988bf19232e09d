"""OAVAR of the ADIS16405 run 1 recording against the published curve ``adis_av``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imunoise.analysis.allan import oadev
from tests.shared_paths import SHARED_DATA

RUN1 = SHARED_DATA / "adis16405/run1.npz"
CURVES = SHARED_DATA / "avar_curves/avar_curves.json"

pytestmark = pytest.mark.skipif(
    not (RUN1.is_file() and CURVES.is_file()),
    reason="reference data ../shared/data/adis16405 or avar_curves not present",
)

# published channel name -> (array in run1.npz, column, scale key); units deg/s and g
CHANNELS = {
    "Gyro. X": ("gyro_counts", 0, "gyro_scale_dps"),
    "Gyro. Y": ("gyro_counts", 1, "gyro_scale_dps"),
    "Gyro. Z": ("gyro_counts", 2, "gyro_scale_dps"),
    "Accel. X": ("accel_counts", 0, "accel_scale_g"),
    "Accel. Y": ("accel_counts", 1, "accel_scale_g"),
    "Accel. Z": ("accel_counts", 2, "accel_scale_g"),
}


@pytest.fixture(scope="module")
def run1():
    with np.load(RUN1) as d:
        return {k: d[k] for k in d.files}


@pytest.mark.parametrize("channel", list(CHANNELS))
def test_oavar_matches_adis_av(run1, channel):
    ref = json.loads(CURVES.read_text())["adis_av"]["channels"][channel]
    key, col, scale = CHANNELS[channel]
    fs = float(run1["fs_hz"])
    rate = run1[key][:, col] * float(run1[scale])
    tau = np.asarray(ref["tau_s"])
    m = np.round(tau * fs).astype(np.int64)
    np.testing.assert_allclose(m / fs, tau, rtol=1e-12)
    curve = oadev(rate, fs, m=m)
    np.testing.assert_array_equal(curve.m, m)
    np.testing.assert_allclose(curve.avar, ref["avar"], rtol=1e-5, atol=0)
    # the interval is a proper bracket around the estimate at every tau
    assert np.all(curve.ci_low < curve.dev) and np.all(curve.dev < curve.ci_high)
