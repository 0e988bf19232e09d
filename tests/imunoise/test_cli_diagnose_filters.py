"""The filter a recording's device configuration states, as the diagnose command reads it."""

from __future__ import annotations

import pytest

from imunoise.commands.diagnose import device_filter


def test_adis_bartlett_at_the_output_rate() -> None:
    md = {"config.device": "adis16350", "config.rate_hz": "819.2", "config.filter_taps": "4"}
    assert device_filter(md, "gyro_x") == ("bartlett", {"taps": pytest.approx(4.0)})
    md["config.rate_hz"] = "409.6"
    assert device_filter(md, "/adis16350/imu:accel_z") == ("bartlett",
                                                           {"taps": pytest.approx(2.0)})
    md["config.rate_hz"] = "102.4"  # the window is shorter than one output sample
    assert device_filter(md, "gyro_x") is None


def test_itg3200_low_pass_below_nyquist_only() -> None:
    md = {"config.device": "itg3200", "config.rate_hz": "100", "config.dlpf_bandwidth_hz": "42"}
    assert device_filter(md, "gyro_y") == ("lowpass", {"fc": 42.0})
    md["config.dlpf_bandwidth_hz"] = "98"
    assert device_filter(md, "gyro_y") is None
    assert device_filter({}, "gyro_x") is None
