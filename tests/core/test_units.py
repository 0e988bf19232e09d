"""Unit conversions against values computed by hand (pi/180 = 0.0174532925199..., g0 = 9.80665)."""

import numpy as np
import pytest

from imunoise.core import units as u


def test_rate_conversions():
    assert u.deg_s_to_rad_s(1.0) == pytest.approx(0.017453292519943295, rel=1e-15)
    assert u.rad_s_to_deg_s(1.0) == pytest.approx(57.29577951308232, rel=1e-15)
    # 1 rad/s = 57.2957795 deg/s * 3600 s/h
    assert u.rad_s_to_deg_h(1.0) == pytest.approx(206264.80624709636, rel=1e-15)
    # Earth rate 15.041 deg/h = 7.2921e-5 rad/s
    assert u.deg_h_to_rad_s(15.041067) == pytest.approx(7.2921159e-5, rel=1e-6)


def test_angle_random_walk():
    # 1 deg/sqrt(h) = (pi/180) rad / 60 sqrt(s) = 2.908882e-4 rad/s/sqrt(Hz)
    assert u.arw_deg_rth_to_rad_s_rthz(1.0) == pytest.approx(2.908882086657216e-4, rel=1e-14)
    # Petkov & Slavov ADIS16350 N = 5.75e-2 deg/sqrt(s) = 5.75e-2 * 60 deg/sqrt(h) = 3.45
    n_si = 5.75e-2 * np.pi / 180.0
    assert u.arw_rad_s_rthz_to_deg_rth(n_si) == pytest.approx(3.45, rel=1e-12)
    # 1 deg/h/sqrt(Hz) = pi/180/3600 = 4.848137e-6 rad/s/sqrt(Hz)
    assert u.deg_h_rthz_to_rad_s_rthz(1.0) == pytest.approx(4.84813681109536e-6, rel=1e-14)
    assert u.rad_s_rthz_to_deg_h_rthz(4.84813681109536e-6) == pytest.approx(1.0, rel=1e-14)
    assert u.rad_s_rthz_to_deg_s_rthz(1e-3) == pytest.approx(0.05729577951308232, rel=1e-14)


def test_rate_random_walk():
    # 1 deg/h/sqrt(h) = pi/180 / 3600 / 60 = 8.0802280e-8 rad/s/sqrt(s)
    assert u.rrw_deg_h_rth_to_rad_s_rts(1.0) == pytest.approx(8.080228018492267e-8, rel=1e-14)
    assert u.rrw_rad_s_rts_to_deg_h_rth(8.080228018492267e-8) == pytest.approx(1.0, rel=1e-14)


def test_acceleration():
    assert u.m_s2_to_g(9.80665) == 1.0
    assert u.g_to_m_s2(2.0) == pytest.approx(19.6133, rel=1e-15)
    assert u.mg_to_m_s2(1.0) == pytest.approx(9.80665e-3, rel=1e-15)
    assert u.m_s2_to_mg(0.0980665) == pytest.approx(10.0, rel=1e-14)
    # 100 ug/sqrt(Hz) = 9.80665e-4 m/s^2/sqrt(Hz)
    assert u.ug_rthz_to_m_s2_rthz(100.0) == pytest.approx(9.80665e-4, rel=1e-15)
    assert u.m_s2_rthz_to_ug_rthz(9.80665e-4) == pytest.approx(100.0, rel=1e-14)


def test_velocity_random_walk():
    # 1 m/s/sqrt(h) = 1/60 m/s^2/sqrt(Hz)
    assert u.vrw_m_s_rth_to_m_s2_rthz(0.294) == pytest.approx(0.0049, rel=1e-14)
    assert u.vrw_m_s2_rthz_to_m_s_rth(0.0049) == pytest.approx(0.294, rel=1e-14)


def test_acceleration_random_walk():
    # 1 m/s^2/sqrt(s) = 3600^1.5 m/s/h^1.5 = 216000
    assert u.arw_accel_m_s2_rts_to_m_s_h15(1.0) == pytest.approx(216000.0, rel=1e-14)
    assert u.arw_accel_m_s_h15_to_m_s2_rts(216000.0) == pytest.approx(1.0, rel=1e-14)
    # 1 mg/sqrt(h) = 9.80665e-3 m/s^2 / 60 sqrt(s) = 1.6344417e-4
    assert u.arw_accel_mg_rth_to_m_s2_rts(1.0) == pytest.approx(1.6344416666666667e-4, rel=1e-14)
    assert u.arw_accel_m_s2_rts_to_mg_rth(1.6344416666666667e-4) == pytest.approx(1.0, rel=1e-14)


def test_arrays_convert_elementwise():
    out = u.rad_s_to_deg_s(np.array([0.0, np.pi]))
    np.testing.assert_allclose(out, [0.0, 180.0], rtol=1e-15)


def test_conventional_param_units():
    label, factor = u.conventional(param="N", kind="gyro")
    assert label == "deg/sqrt(h)" and factor == pytest.approx(3437.7467707849396, rel=1e-14)
    assert u.conventional("B", "gyro") == ("deg/h", pytest.approx(206264.80624709636))
    assert u.conventional("B", "accel") == ("mg", pytest.approx(1e3 / 9.80665))
    assert u.conventional("N", "accel") == ("m/s/sqrt(h)", 60.0)
    assert u.conventional("K", "gyro")[0] == "deg/h/sqrt(h)"
    assert u.si_unit("K", "accel") == "m/s^2/sqrt(s)"
    assert u.si_unit("Q", "gyro") == "rad"
    assert u.si_unit("coef", "gyro") == "rad/s/degC"
    assert u.conventional("T", "accel") == ("s", 1.0)
    # every contract parameter is defined for both kinds, and round trips
    for p in u.PARAMS:
        for kind in ("gyro", "accel"):
            x = 1.234e-3
            assert u.from_conventional(p, kind, u.to_conventional(p, kind, x)) == pytest.approx(x)
    # consistency with the named conversions
    assert u.to_conventional("K", "gyro", 1e-6) == pytest.approx(u.rrw_rad_s_rts_to_deg_h_rth(1e-6))
    assert u.to_conventional("K", "accel", 1e-6) == pytest.approx(
        u.arw_accel_m_s2_rts_to_mg_rth(1e-6))


def test_channel_names_and_errors():
    assert u.param_units("N", "/imu:gyro_y").si == "rad/s/sqrt(Hz)"
    assert u.channel_kind("accel_z") == "accel"
    with pytest.raises(ValueError, match="unknown parameter 'X'.*N, Q, B"):
        u.param_units("X", "gyro")
    with pytest.raises(ValueError, match="neither"):
        u.channel_kind("temp")
