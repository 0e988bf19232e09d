"""The filter a record's channels share, measured from the other channels and fitted as a term."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from imunoise.analysis import chain_shape
from imunoise.analysis.chain_shape import ChainShape, ChainSource
from imunoise.analysis.coherence import cross_spectra, log_coherence
from imunoise.analysis.fit import fit_series
from imunoise.analysis.model_error import error_parts
from imunoise.analysis.terms import TermError, get_term
from imunoise.analysis.terms.moving_average import _fractional_response
from imunoise.analysis.terms.registry import model_avar

FS = 100.0
N = 2**18
NAMES = ["gyro_x", "gyro_y", "accel_x", "accel_y"]
SIGMA = np.array([1e-3, 2e-3, 5e-2, 3e-2])
FLOOR = 0.03
"""Each channel's white noise also reaches it unfiltered at this fraction (as in
tests/analysis/test_shared_shape.py): the PSD spans about a factor 1000."""
SOS = signal.butter(6, 5.0, fs=FS, output="sos")


def _record(seed: int, n: int = N) -> np.ndarray:
    w = np.random.default_rng(seed).standard_normal((n, 4)) * SIGMA
    return signal.sosfilt(SOS, w, axis=0) + FLOOR * w[::-1]


def _true_power(f: np.ndarray) -> np.ndarray:
    _, h = signal.sosfreqz(SOS, worN=f, fs=FS)
    return (np.abs(h) ** 2 + FLOOR**2) / (1.0 + FLOOR**2)


def _shape(x: np.ndarray, channel: str = "accel_x") -> ChainShape:
    co = log_coherence(cross_spectra(x, FS, NAMES), intervals=False)
    shape = chain_shape.chain_shape(co, channel)
    assert shape is not None
    return shape


def _boxcar_shape(taps: float, bins: int = 4097) -> ChainShape:
    u = np.linspace(0.0, 0.5, bins)
    return ChainShape.from_power(_fractional_response(u, taps), FS, ("a",))


def test_the_shape_is_measured_from_the_other_channels_to_their_scatter():
    x = _record(21)
    shape = _shape(x)
    assert shape.channels == ("gyro_x", "gyro_y", "accel_y")
    assert shape.fs_hz == FS and shape.f_hz[0] == 0.0 and shape.f_hz[-1] == FS / 2
    assert np.all(shape.power[shape.f_hz < FS / 100.0] == 1.0)
    cs = cross_spectra(x, FS, NAMES)
    band = (shape.f_hz > 1.0) & (shape.f_hz < 45.0)
    err = np.log(shape.power[band] / _true_power(shape.f_hz[band]))
    # each bin is the geometric mean of three PSD estimates with n_avg averages each: the
    # log of one has a standard deviation of about 1/sqrt(n_avg), of the mean 1/sqrt(3 n_avg)
    spread = 1.0 / math.sqrt(3.0 * cs.n_avg)
    assert float(np.sqrt(np.mean(err**2))) < 1.5 * spread
    assert abs(float(np.mean(err))) < 0.5 * spread
    # the channel's own spectrum took no part: another channel's shape uses it
    assert _shape(x, "gyro_x").channels == ("gyro_y", "accel_x", "accel_y")


def test_a_measured_boxcar_gives_the_moving_average_allan_variance():
    # the same response, once in closed form and once as a measured power on a grid:
    # white noise through it exactly (the autocorrelation of 4 taps is the grid's inverse
    # transform), flicker through the grid integral both use
    tau = np.array([1, 2, 3, 4, 8, 16, 64, 1000]) / FS
    with chain_shape.using(_boxcar_shape(4.0)):
        for noise in (("white", {"N": 1e-3}), ("bias_instability", {"B": 1e-3})):
            got = model_avar([noise, ("chain_filter", {"depth": 1.0})], tau, FS)
            want = model_avar([noise, ("moving_average", {"taps": 4.0})], tau, FS)
            rtol = 1e-9 if noise[0] == "white" else 2e-3
            np.testing.assert_allclose(got, want, rtol=rtol)
        # depth 2 is the filter applied twice: a triangle of 7 taps. At one sample the Allan
        # variance is R(0) - R(1), the output's variance less its lag-1 covariance (white
        # input of variance N^2 fs)
        two = model_avar([("white", {"N": 1.0}), ("chain_filter", {"depth": 2.0})],
                         np.array([1.0]) / FS, FS)
        tri = np.convolve(np.ones(4), np.ones(4)) / 16.0
        r0, r1 = float(np.sum(tri**2)), float(np.sum(tri[1:] * tri[:-1]))
        assert two[0] == pytest.approx(FS * (r0 - r1), rel=1e-9)


def test_the_response_is_even_and_periodic_in_the_sampling_rate():
    shape = _boxcar_shape(3.0)
    f = np.array([0.0, 3.0, 17.0, 49.0])
    r = shape.response(f)
    np.testing.assert_allclose(shape.response(FS - f), r, rtol=1e-12)
    np.testing.assert_allclose(shape.response(-f), r, rtol=1e-12)
    np.testing.assert_allclose(shape.response(f + 2 * FS), r, rtol=1e-9)
    np.testing.assert_allclose(shape.response(f, 2.0), r**2, rtol=1e-12)
    g = shape.impulse_response()
    assert float(np.sum(g)) == pytest.approx(1.0)
    acf = shape.autocorrelation()
    assert float(np.sum(acf)) == pytest.approx(1.0)
    assert float(acf[len(acf) // 2]) == pytest.approx(1.0 / 3.0, rel=1e-9)  # sum g^2


def test_another_record_with_the_same_depth_is_another_filter():
    # the filter's caches are keyed by the shape: the same parameters on a second record
    # must not find the first record's variances
    tau = np.array([0.01, 0.02, 0.1])
    model = [("white", {"N": 1e-3}), ("chain_filter", {"depth": 1.0})]
    with chain_shape.using(_boxcar_shape(2.0)):
        two = model_avar(model, tau, FS)
    with chain_shape.using(_boxcar_shape(8.0)):
        eight = model_avar(model, tau, FS)
    assert eight[0] < 0.3 * two[0]
    np.testing.assert_allclose(eight, model_avar(
        [("white", {"N": 1e-3}), ("moving_average", {"taps": 8.0})], tau, FS), rtol=1e-9)


def test_without_other_channels_the_term_says_why():
    assert not get_term("chain_filter").usable()
    with pytest.raises(TermError, match="chain_filter needs the record's other channels"):
        model_avar([("white", {"N": 1e-3}), ("chain_filter", {"depth": 1.0})],
                   np.array([0.1]), FS)
    with chain_shape.using(_boxcar_shape(2.0)):
        assert get_term("chain_filter").usable()
        with pytest.raises(TermError, match="measured at 100 Hz, the channel is sampled at "
                                            "50 Hz"):
            get_term("chain_filter").validate({"depth": 1.0}, 50.0)


def test_halves_are_measured_once_each_and_used_inside_their_block():
    calls: list[int | None] = []
    shapes = {None: _boxcar_shape(2.0), 0: _boxcar_shape(3.0), 1: None}

    def whole() -> ChainShape | None:
        calls.append(None)
        return shapes[None]

    def half(k: int) -> ChainShape | None:
        calls.append(k)
        return shapes[k]

    assert chain_shape.current() is None
    with chain_shape.using(ChainSource(whole, half)):
        assert calls == []  # nothing measured until asked
        chain_shape.prepare_halves()
        assert calls == [None, 0, 1]
        assert chain_shape.current() is shapes[None]
        with chain_shape.using_half(0):
            assert chain_shape.current() is shapes[0]
        with chain_shape.using_half(1):  # a half without a shape of its own: the whole's
            assert chain_shape.current() is shapes[None]
        assert chain_shape.current() is shapes[None]
        assert calls == [None, 0, 1]
    assert chain_shape.current() is None
    with chain_shape.using_half(0):  # no source: nothing to choose
        assert chain_shape.current() is None


def test_a_channel_through_the_shared_filter_is_fitted_to_its_white_level():
    x = _record(22)
    with chain_shape.using(_shape(x)):
        fit, _ = fit_series(x[:, 2], FS, ["white", "chain_filter"])
        params = dict(fit.params)
        # the passband level: 2 sigma^2 / fs (one-sided) with the floor's share added, as
        # a white level N (white's PSD is N^2 per Hz one-sided, see analysis/terms/white.py)
        level = 2.0 * SIGMA[2] ** 2 / FS * (1.0 + FLOOR**2)
        n_true = math.sqrt(level / float(get_term("white").psd(np.array([1.0]), FS,
                                                               N=1.0)[0]))
        assert params["white"]["N"] == pytest.approx(n_true, rel=0.02)
        assert params["chain_filter"]["depth"] == pytest.approx(1.0, abs=0.05)
        assert fit.chi2_per_dof < 2.5
        _, parts = error_parts(x[:, 2], FS, "white,chain_filter", fit, units="m/s^2",
                               holdout=False)
        assert parts["psd"]["deviance_per_bin"] < 2.0
