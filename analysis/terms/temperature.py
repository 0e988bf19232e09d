"""Thermal sensitivity of the bias, coef (removed by regression on the temperature record)."""

from __future__ import annotations

import numpy as np

from imunoise.analysis.terms.base import Param, Term, TermSimulator


class _TemperatureSim(TermSimulator):
    """``coef (temperature - temperature[0])``: the temperature record (degC) passed to
    :meth:`take`; the reference is the first temperature sample the stream saw."""

    def __init__(self, coef: float) -> None:
        self.coef = coef
        self.t_ref: float | None = None

    def take(self, n: int, temperature: np.ndarray | None = None) -> np.ndarray:
        if temperature is None:
            raise ValueError("the temperature term needs a temperature record: "
                             "take(n, temperature=array_degC)")
        temp = np.asarray(temperature, dtype=np.float64)
        if temp.shape != (n,):
            raise ValueError(f"temperature must have shape ({n},), got {temp.shape}")
        if self.t_ref is None and n:
            self.t_ref = float(temp[0])
        return self.coef * (temp - (self.t_ref or 0.0))


class Temperature(Term):
    name = "temperature"
    order = 80
    params = (Param("coef", "rate/degC", -10.0, 10.0, "bias change per degree Celsius",
                    lo_open=False),)
    amplitude = "coef"
    role = "regressor"
    live = False  # regressing the whole record needs the whole record
    needs_record = "temperature"
    avar_extras = ("temp_avar", "temp_psd")
    allan_signature = "coef^2 x Allan variance of the temperature record"
    effect = "thermal sensitivity of the bias"
    explanation = (
        "The bias follows the sensor temperature. Its Allan and spectral signature copy "
        "those of the temperature record scaled by coef^2, usually a slow rise at long "
        "averaging times. It is removed by regressing the rate on the recorded temperature; "
        "the remaining terms are then judged on the corrected series.")
    small_default = {"coef": 0.0}

    def _avar(self, tau: np.ndarray, fs: float, coef: float,
              temp_avar: np.ndarray | None = None, temp_psd: np.ndarray | None = None
              ) -> np.ndarray:
        if temp_avar is None:
            return np.zeros_like(tau)
        return coef * coef * np.broadcast_to(np.asarray(temp_avar, dtype=np.float64),
                                             tau.shape)

    def _psd(self, f: np.ndarray, fs: float, coef: float,
             temp_avar: np.ndarray | None = None, temp_psd: np.ndarray | None = None
             ) -> np.ndarray:
        if temp_psd is None:
            return np.zeros_like(f)
        return coef * coef * np.broadcast_to(np.asarray(temp_psd, dtype=np.float64), f.shape)

    def simulator(self, params, fs_hz, rng, **options):
        return _TemperatureSim(float(params["coef"]))

    def add_discrete(self, dm, params):
        dm.temperature_coef += params["coef"]


TERM = Temperature()
