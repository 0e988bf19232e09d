"""Diagnosis on real recordings (reference data under ../shared/data)."""

from pathlib import Path

import numpy as np
import pytest

from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.evidence import outliers, robust_z, spectral_lines
from imunoise.analysis.terms import get_term
from tests.shared_paths import SHARED_DATA

DATA = SHARED_DATA
BASE = "white,bias_instability,random_walk"


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"reference data {path} not available (needs ../shared next to the repo)")
    return path


def _adis_gyro(run: int) -> np.ndarray:
    d = np.load(_need(DATA / "adis16405" / f"run{run}.npz"))
    return d["gyro_counts"] * float(d["gyro_scale_dps"]) * np.pi / 180.0


def test_adis_run4_shock_is_flagged_near_sample_404608():
    g = _adis_gyro(4)
    for axis in (0, 1):  # the shock shows on x and y
        idx = np.array(outliers([g[:, axis]], 100.0).details["indices"])
        assert np.min(np.abs(idx - 404608)) <= 10


def test_adis_run1_has_no_spectral_line():
    g = _adis_gyro(1)
    for axis in range(3):
        assert not spectral_lines([g[:, axis]], 100.0).significant


def test_adis_run1_gyro_y_misfit_is_the_sensor_filter():
    # The classic three-term model fits gyro Y from 0.16 s on; below, the ADIS16405's
    # decimation filter pulls the Allan deviation under any sum of noise terms. The diagnosis
    # names an output filter first, adding it closes the channel, and no noise term (nor a
    # spectral line) is invented for it.
    d = diagnose(_adis_gyro(1)[:, 1], 100.0, BASE)
    assert d.fit.chi2_per_dof > 5
    assert d.fit.z[0] < -3  # the shortest tau lies below the model
    top = d.suggestions[0]
    assert top.significant and get_term(top.term).kind == "filter", top.term
    assert top.chi2_per_dof_after < 3
    assert "filter" in top.why
    assert not any(s.significant and s.term == "sinusoid" for s in d.suggestions)


def test_mtig_outliers_are_found():
    m = np.load(_need(DATA / "mtig_outliers" / "gyro_x.npz"))["gyro_x"].astype(float)
    f = outliers([m], 100.0)
    assert f.significant and f.details["count"] >= 100
    # Every sample beyond 10 standard deviations is flagged or next to a flagged peak.
    z = np.abs(robust_z(m))
    big = np.flatnonzero(np.abs(m - np.median(m)) > 10 * m.std())
    assert 80 <= big.size <= 130
    near = np.max(np.stack([z[np.clip(big + k, 0, m.size - 1)] for k in (-1, 0, 1)]), axis=0)
    assert np.all(near > f.details["threshold_z"])


def test_mtig_noise_level_is_steady_once_outliers_are_left_out():
    from imunoise.analysis.evidence import noise_level_windows, outlier_indices

    m = np.load(_need(DATA / "mtig_outliers" / "gyro_x.npz"))["gyro_x"].astype(float)
    with_spikes = noise_level_windows([m], 100.0)
    clean = noise_level_windows([m], 100.0, exclude=outlier_indices([m]))
    assert with_spikes.params["level_ratio"] > clean.params["level_ratio"]
    assert not clean.significant
