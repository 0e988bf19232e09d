"""Channels with one spectral shape and no common signal: a filter of the chain, named."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from imunoise.analysis.coherence import cross_spectra, log_coherence
from imunoise.analysis.shared_shape import (
    MAX_COMMON_POWER,
    MAX_UNEXPLAINED,
    MIN_RANGE,
    annotate_shapes,
    pair_shape,
    shared_shapes,
)

FS = 100.0
N = 2**18
NAMES = ["gyro_x", "gyro_y", "accel_x", "accel_y"]


def _view(x: np.ndarray, names: list[str] = NAMES):
    return log_coherence(cross_spectra(x, FS, names), intervals=False)


def _through(cutoff_hz: float, w: np.ndarray) -> np.ndarray:
    # a steep lowpass (a decimation filter's passband and stopband) and a floor 1e-3 of the
    # passband after it: the PSD spans about a factor 1000
    sos = signal.butter(6, cutoff_hz, fs=FS, output="sos")
    return signal.sosfilt(sos, w, axis=0) + 0.03 * w[::-1]


def test_independent_noise_through_one_filter_is_named_as_one_shape():
    rng = np.random.default_rng(11)
    w = rng.standard_normal((N, 4)) * np.array([1e-3, 2e-3, 5e-2, 3e-2])
    shapes = shared_shapes(_view(_through(5.0, w)))
    assert len(shapes) == 1
    s = shapes[0]
    assert s.channels == tuple(NAMES)
    assert s.explained >= 1.0 - MAX_UNEXPLAINED
    assert s.span > 100.0
    assert s.common_power <= MAX_COMMON_POWER
    assert set(s.kinds) == {"gyro", "accel"}
    # one exact shape: each PSD follows the others' to the scatter of the estimates (about
    # 1 + 1/3 for four channels; over 10 seeds of this record 1.49 on average, standard
    # deviation 0.37 per channel, so each below the mean plus four of them)
    assert s.deviance_expected == pytest.approx(4.0 / 3.0)
    dev = list(s.deviance.values())
    assert all(v < 3.0 for v in dev) and 1.0 < float(np.mean(dev)) < 2.0, s.deviance
    assert "share one spectral shape and no signal" in s.text()
    assert s.text().endswith("the chain_filter term takes the chain's response from the "
                             "other channels (--model ...,chain_filter).")
    assert "different quantities" in s.text()
    doc = s.to_dict()
    assert doc["channels"] == NAMES and doc["text"] == s.text()


def test_a_constant_channel_leaves_out_only_itself():
    rng = np.random.default_rng(15)
    x = _through(5.0, rng.standard_normal((N, 4)))
    x[:, 1] = 0.25  # a stuck axis: no spectrum at all
    with np.errstate(invalid="ignore", divide="ignore"):
        shapes = shared_shapes(_view(x))
    assert [s.channels for s in shapes] == [("gyro_x", "accel_x", "accel_y")]
    assert np.isfinite(shapes[0].span) and shapes[0].f_hi_hz > 40.0


def test_a_group_whose_channels_have_no_point_in_common_is_left_out():
    # three random walks (one 1/f^2 shape, no coherence), each missing a third of the points
    # so that every pair shares twelve of them but no point has all three
    import dataclasses

    rng = np.random.default_rng(16)
    co = _view(np.cumsum(rng.standard_normal((N, 3)), axis=0), NAMES[:3])
    psd = np.array(co.psd, dtype=np.float64)
    k = np.arange(psd.shape[1])
    third = psd.shape[1] // 3
    psd[0, k >= 2 * third] = 0.0
    psd[1, k < third] = 0.0
    psd[2, (k >= third) & (k < 2 * third)] = 0.0
    cut = dataclasses.replace(co, psd=psd)
    assert pair_shape(cut, "gyro_x", "gyro_y").explained > 0.95
    assert shared_shapes(cut) == []
    assert [s.channels for s in shared_shapes(co)] == [tuple(NAMES[:3])]


def test_only_the_shaping_suggestions_of_a_grouped_channel_are_annotated():
    rng = np.random.default_rng(17)
    shapes = shared_shapes(_view(_through(5.0, rng.standard_normal((N, 4)))))
    sug = {"gyro_x": [{"term": "resonance", "why": "A peak."}, {"term": "sinusoid", "why": ""},
                      {"term": "bias_step", "why": ""}, {"term": "lowpass", "why": ""},
                      {"term": "no_such_term", "why": ""}],
           "elsewhere": [{"term": "resonance", "why": ""}]}
    assert annotate_shapes(sug, shapes) == 2
    res, line, step, lowpass, unknown = sug["gyro_x"]
    assert res["why"] == ("A peak. The channel's spectrum has the shape of gyro_y, accel_x, "
                          "accel_y with no signal in common (coherence.shared_shapes): this "
                          "term may describe the filter the samples pass through, not the "
                          "sensing element.")
    assert lowpass["why"].startswith("The channel's spectrum has the shape of gyro_y, ")
    assert all(s["why"] == "" for s in (line, step, unknown))
    assert sug["elsewhere"][0]["why"] == ""


def test_a_pair_through_one_filter_has_its_ratio_and_the_others_are_not_joined():
    rng = np.random.default_rng(12)
    w = rng.standard_normal((N, 4))
    x = np.column_stack([_through(5.0, w[:, :2]), _through(15.0, w[:, 2:3]),
                         w[:, 3:] * 0.1])  # another cutoff; white noise, no shape at all
    co = _view(x)
    p = pair_shape(co, "gyro_x", "gyro_y")
    assert p.explained > 0.99
    assert p.ratio == pytest.approx(1.0, rel=0.05)  # equal amplitudes, equal filters
    assert pair_shape(co, "gyro_x", "accel_x").explained < 0.5
    shapes = shared_shapes(co)
    assert [s.channels for s in shapes] == [("gyro_x", "gyro_y")]
    assert "a filter the channels have in common" in shapes[0].text()


def test_white_channels_have_no_shape_to_share():
    rng = np.random.default_rng(13)
    co = _view(rng.standard_normal((N, 4)))
    assert pair_shape(co, "gyro_x", "accel_x").explained < 0.5  # nothing but scatter
    assert shared_shapes(co) == []
    # left out for want of a shape: each flat spectrum spans far less than the threshold
    from imunoise.analysis.shared_shape import _log_psd, _span

    logs, w = _log_psd(co)
    assert all(_span(logs[k], w[k]) < MIN_RANGE / 2 for k in range(4))


def test_a_motion_every_channel_sees_is_not_a_filter():
    # one filtered motion in every channel, far above their own noise: the same shape, and
    # coherent, so the shape is the motion's (the environment view's case), not the chain's
    rng = np.random.default_rng(14)
    motion = _through(5.0, rng.standard_normal((N, 1)))
    x = motion * np.array([1.0, -0.5, 2.0, 0.7]) + 1e-2 * rng.standard_normal((N, 4))
    co = _view(x)
    assert pair_shape(co, "gyro_x", "accel_x").common_power > 0.9
    assert shared_shapes(co) == []


def test_the_galaxy_s5_channels_share_their_decimation_filter(shared_data):
    # the phone log, already decimated to 10 Hz: every gyro and accelerometer axis has one
    # shape (a fall of more than a factor 100 from 0.01 to 4.5 Hz) and no two are coherent
    d = np.load(shared_data / "galaxy_s5" / "galaxy_s5_static_10hz.npz")
    x = np.column_stack([d["gyro"], d["accel"]])
    names = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    co = log_coherence(cross_spectra(x, float(d["fs"]), names), intervals=False)
    shapes = shared_shapes(co)
    assert len(shapes) == 1
    assert shapes[0].channels == tuple(names)
    assert shapes[0].span > 100.0
    assert shapes[0].explained > 0.99
    # the others' shape times a constant follows each channel to a deviance of 0.74-3.6 per
    # point; the loop's fitted models reach 20-32 on analyze's points
    assert max(shapes[0].deviance.values()) < 5.0


def test_the_adis16405_channels_have_no_shared_shape(shared_data):
    # gyro_x and gyro_y share the sensor's short averaging filter, but it bends their PSD by a
    # factor of about two only; the accelerometers share the bench's motion (coherent)
    d = np.load(shared_data / "adis16405" / "run1.npz")
    x = np.column_stack([d["gyro_counts"], d["accel_counts"]]).astype(np.float64)
    names = ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    co = log_coherence(cross_spectra(x, float(d["fs_hz"]), names), intervals=False)
    assert pair_shape(co, "gyro_x", "gyro_y").explained > 0.99
    assert pair_shape(co, "accel_x", "accel_y").common_power > 0.5
    assert shared_shapes(co) == []
