"""Unit conversions between the SI units used inside imunoise and the conventional units of
inertial-sensor data sheets.

Inside the project every quantity is SI: rad/s and m/s^2 for rates and accelerations, and the
noise-term parameters in the channel's SI units (see the term table of docs/terms.md). Data sheets
and reports use degrees, hours and g. Each conversion here is a named pair of functions (or a
factor) so that no caller writes ``* 180 / pi * 60`` inline.

Standard gravity is ``G0 = 9.80665 m/s^2`` (CGPM 1901).

Identities worth keeping in mind:

- 1 rad/s/sqrt(Hz) = 1 rad/sqrt(s): the white-noise density N and the angle random walk are the
  same number. 1 rad/sqrt(s) = 180/pi * 60 deg/sqrt(h), since sqrt(1 h) = 60 sqrt(s).
- 1 m/s^2/sqrt(Hz) = 1 m/s/sqrt(s) = 60 m/s/sqrt(h) (velocity random walk).
- Rate random walk K in rad/s/sqrt(s) = rad/s^1.5: 1 rad/s^1.5 = 180/pi * 3600 * 60 deg/h/sqrt(h).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

G0 = 9.80665
"""Standard gravity in m/s^2."""

DEG = math.pi / 180.0
"""One degree in rad."""

DEG_PER_RAD = 180.0 / math.pi
SQRT_S_PER_SQRT_H = 60.0  # sqrt(3600 s)
S_PER_H = 3600.0
ARCSEC_PER_RAD = DEG_PER_RAD * 3600.0

CI95 = 0.95
"""Confidence level of every interval the user sees: JSON, text, dashboard, reports, exports."""

ONE_SIGMA_CI = 0.683
"""The 68.3 % level of Stable32's tables, used to compare with them."""

Kind = Literal["gyro", "accel"]

ArrayLike = float | np.ndarray


# --- angular rate --------------------------------------------------------------------------

def rad_s_to_deg_s(x: ArrayLike) -> ArrayLike:
    """Angular rate: rad/s -> deg/s."""
    return x * DEG_PER_RAD


def deg_s_to_rad_s(x: ArrayLike) -> ArrayLike:
    """Angular rate: deg/s -> rad/s."""
    return x / DEG_PER_RAD


def rad_s_to_deg_h(x: ArrayLike) -> ArrayLike:
    """Angular rate (bias, bias instability): rad/s -> deg/h."""
    return x * DEG_PER_RAD * S_PER_H


def deg_h_to_rad_s(x: ArrayLike) -> ArrayLike:
    """Angular rate: deg/h -> rad/s."""
    return x / (DEG_PER_RAD * S_PER_H)


# --- gyro white noise (angle random walk) ---------------------------------------------------

def arw_rad_s_rthz_to_deg_rth(x: ArrayLike) -> ArrayLike:
    """Gyro white-noise density N: rad/s/sqrt(Hz) -> angle random walk in deg/sqrt(h)."""
    return x * DEG_PER_RAD * SQRT_S_PER_SQRT_H


def arw_deg_rth_to_rad_s_rthz(x: ArrayLike) -> ArrayLike:
    """Angle random walk: deg/sqrt(h) -> rad/s/sqrt(Hz)."""
    return x / (DEG_PER_RAD * SQRT_S_PER_SQRT_H)


def rad_s_rthz_to_deg_h_rthz(x: ArrayLike) -> ArrayLike:
    """Gyro noise density: rad/s/sqrt(Hz) -> deg/h/sqrt(Hz)."""
    return x * DEG_PER_RAD * S_PER_H


def deg_h_rthz_to_rad_s_rthz(x: ArrayLike) -> ArrayLike:
    """Gyro noise density: deg/h/sqrt(Hz) -> rad/s/sqrt(Hz)."""
    return x / (DEG_PER_RAD * S_PER_H)


def rad_s_rthz_to_deg_s_rthz(x: ArrayLike) -> ArrayLike:
    """Gyro noise density: rad/s/sqrt(Hz) -> deg/s/sqrt(Hz) (the usual data-sheet unit)."""
    return x * DEG_PER_RAD


# --- gyro rate random walk ------------------------------------------------------------------

def rrw_rad_s_rts_to_deg_h_rth(x: ArrayLike) -> ArrayLike:
    """Rate random walk K: rad/s/sqrt(s) -> deg/h/sqrt(h)."""
    return x * DEG_PER_RAD * S_PER_H * SQRT_S_PER_SQRT_H


def rrw_deg_h_rth_to_rad_s_rts(x: ArrayLike) -> ArrayLike:
    """Rate random walk K: deg/h/sqrt(h) -> rad/s/sqrt(s)."""
    return x / (DEG_PER_RAD * S_PER_H * SQRT_S_PER_SQRT_H)


# --- acceleration ---------------------------------------------------------------------------

def m_s2_to_g(x: ArrayLike) -> ArrayLike:
    """Acceleration: m/s^2 -> g (standard gravity)."""
    return x / G0


def g_to_m_s2(x: ArrayLike) -> ArrayLike:
    """Acceleration: g -> m/s^2."""
    return x * G0


def m_s2_to_mg(x: ArrayLike) -> ArrayLike:
    """Acceleration (bias, bias instability): m/s^2 -> mg."""
    return x / G0 * 1e3


def mg_to_m_s2(x: ArrayLike) -> ArrayLike:
    """Acceleration: mg -> m/s^2."""
    return x * G0 * 1e-3


# --- accelerometer white noise (velocity random walk) ---------------------------------------

def m_s2_rthz_to_ug_rthz(x: ArrayLike) -> ArrayLike:
    """Accelerometer noise density: m/s^2/sqrt(Hz) -> ug/sqrt(Hz)."""
    return x / G0 * 1e6


def ug_rthz_to_m_s2_rthz(x: ArrayLike) -> ArrayLike:
    """Accelerometer noise density: ug/sqrt(Hz) -> m/s^2/sqrt(Hz)."""
    return x * G0 * 1e-6


def vrw_m_s2_rthz_to_m_s_rth(x: ArrayLike) -> ArrayLike:
    """Accelerometer white-noise density N: m/s^2/sqrt(Hz) -> velocity random walk m/s/sqrt(h)."""
    return x * SQRT_S_PER_SQRT_H


def vrw_m_s_rth_to_m_s2_rthz(x: ArrayLike) -> ArrayLike:
    """Velocity random walk: m/s/sqrt(h) -> m/s^2/sqrt(Hz)."""
    return x / SQRT_S_PER_SQRT_H


# --- accelerometer random walk --------------------------------------------------------------

def arw_accel_m_s2_rts_to_mg_rth(x: ArrayLike) -> ArrayLike:
    """Acceleration random walk K: m/s^2/sqrt(s) -> mg/sqrt(h)."""
    return x / G0 * 1e3 * SQRT_S_PER_SQRT_H


def arw_accel_mg_rth_to_m_s2_rts(x: ArrayLike) -> ArrayLike:
    """Acceleration random walk K: mg/sqrt(h) -> m/s^2/sqrt(s)."""
    return x * G0 * 1e-3 / SQRT_S_PER_SQRT_H


def arw_accel_m_s2_rts_to_m_s_h15(x: ArrayLike) -> ArrayLike:
    """Acceleration random walk K: m/s^2/sqrt(s) -> m/s/h^1.5 (1 h^1.5 = 3600^1.5 s^1.5)."""
    return x * S_PER_H**1.5


def arw_accel_m_s_h15_to_m_s2_rts(x: ArrayLike) -> ArrayLike:
    """Acceleration random walk K: m/s/h^1.5 -> m/s^2/sqrt(s)."""
    return x / S_PER_H**1.5


# --- noise-term parameters ------------------------------------------------------------------

@dataclass(frozen=True)
class ParamUnits:
    """Units of one noise-term parameter for one channel kind.

    ``conventional_value = si_value * factor``.
    """

    si: str
    conventional: str
    factor: float


_RAD_S_TO_DEG_H = DEG_PER_RAD * S_PER_H
_M_S2_TO_MG = 1e3 / G0

# Parameter names of the contract's term table -> units for gyro and accelerometer channels.
_PARAM_UNITS: dict[tuple[str, str], ParamUnits] = {
    ("N", "gyro"): ParamUnits("rad/s/sqrt(Hz)", "deg/sqrt(h)", DEG_PER_RAD * SQRT_S_PER_SQRT_H),
    ("N", "accel"): ParamUnits("m/s^2/sqrt(Hz)", "m/s/sqrt(h)", SQRT_S_PER_SQRT_H),
    ("Q", "gyro"): ParamUnits("rad", "arcsec", ARCSEC_PER_RAD),
    ("Q", "accel"): ParamUnits("m/s", "mm/s", 1e3),
    ("B", "gyro"): ParamUnits("rad/s", "deg/h", _RAD_S_TO_DEG_H),
    ("B", "accel"): ParamUnits("m/s^2", "mg", _M_S2_TO_MG),
    ("K", "gyro"): ParamUnits("rad/s/sqrt(s)", "deg/h/sqrt(h)",
                              _RAD_S_TO_DEG_H * SQRT_S_PER_SQRT_H),
    ("K", "accel"): ParamUnits("m/s^2/sqrt(s)", "mg/sqrt(h)", _M_S2_TO_MG * SQRT_S_PER_SQRT_H),
    ("R", "gyro"): ParamUnits("rad/s^2", "deg/h^2", _RAD_S_TO_DEG_H * S_PER_H),
    ("R", "accel"): ParamUnits("m/s^3", "mg/h", _M_S2_TO_MG * S_PER_H),
    ("sigma", "gyro"): ParamUnits("rad/s", "deg/h", _RAD_S_TO_DEG_H),
    ("sigma", "accel"): ParamUnits("m/s^2", "mg", _M_S2_TO_MG),
    ("T", "gyro"): ParamUnits("s", "s", 1.0),
    ("T", "accel"): ParamUnits("s", "s", 1.0),
    ("A", "gyro"): ParamUnits("rad/s", "deg/s", DEG_PER_RAD),
    ("A", "accel"): ParamUnits("m/s^2", "mg", _M_S2_TO_MG),
    ("f", "gyro"): ParamUnits("Hz", "Hz", 1.0),
    ("f", "accel"): ParamUnits("Hz", "Hz", 1.0),
    ("coef", "gyro"): ParamUnits("rad/s/degC", "deg/h/degC", _RAD_S_TO_DEG_H),
    ("coef", "accel"): ParamUnits("m/s^2/degC", "mg/degC", _M_S2_TO_MG),
}

PARAMS: tuple[str, ...] = ("N", "Q", "B", "K", "R", "sigma", "T", "A", "f", "coef")


def channel_kind(channel: str) -> Kind:
    """``"gyro"`` or ``"accel"`` from a channel name such as ``gyro_x`` or ``/imu:accel_z``."""
    base = channel.split(":")[-1]
    if base.startswith("gyro"):
        return "gyro"
    if base.startswith("accel"):
        return "accel"
    raise ValueError(f"channel {channel!r} is neither a gyro nor an accelerometer channel")


def param_units(param: str, kind: str) -> ParamUnits:
    """SI and conventional units of a noise-term parameter for a channel kind.

    Args:
        param: parameter name from the term table (N, Q, B, K, R, sigma, T, A, f, coef).
        kind: ``"gyro"`` or ``"accel"`` (a channel name is accepted too).
    """
    if kind not in ("gyro", "accel"):
        kind = channel_kind(kind)
    try:
        return _PARAM_UNITS[(param, kind)]
    except KeyError:
        raise ValueError(f"unknown parameter {param!r}; known: {', '.join(PARAMS)}") from None


def si_unit(param: str, kind: str) -> str:
    """SI unit label of a parameter, e.g. ``si_unit("N", "gyro") -> "rad/s/sqrt(Hz)"``."""
    return param_units(param, kind).si


def conventional(param: str, kind: str) -> tuple[str, float]:
    """Conventional unit label and factor (conventional = SI * factor) of a parameter.

    ``conventional(param="N", kind="gyro") -> ("deg/sqrt(h)", 3437.746...)``.
    """
    u = param_units(param, kind)
    return u.conventional, u.factor


def to_conventional(param: str, kind: str, value: ArrayLike) -> ArrayLike:
    """A parameter value in SI units converted to its conventional unit."""
    return value * param_units(param, kind).factor


def from_conventional(param: str, kind: str, value: ArrayLike) -> ArrayLike:
    """A parameter value in its conventional unit converted to SI units."""
    return value / param_units(param, kind).factor
