"""NIST SP 1065 NBS14 test sets: the deviations to the digits printed in the publication."""

from __future__ import annotations

import json
from decimal import Decimal

import numpy as np
import pytest

from imunoise.analysis.allan import adev, allan, mdev, oadev, ohdev
from tests.shared_paths import SHARED_DATA

REF = SHARED_DATA / "stable32/nbs14_reference.json"

pytestmark = pytest.mark.skipif(not REF.is_file(), reason=f"reference file {REF} not present")

ESTIMATORS = {"ADEV": adev, "OADEV": oadev, "MDEV": mdev, "OHDEV": ohdev}


def _half_unit(value: float) -> float:
    """Half a unit in the last printed digit of ``value`` (as stored in the JSON file)."""
    exponent = Decimal(repr(value)).as_tuple().exponent
    return 0.5 * 10.0**exponent


def _reference() -> dict:
    return json.loads(REF.read_text())


def _nbs14_1000_freq() -> np.ndarray:
    n = np.empty(1000, dtype=np.int64)
    state = 1234567890
    for i in range(1000):
        n[i] = state
        state = (16807 * state) % 2147483647
    return n / 2147483647.0


def test_generator_matches_published_check_values():
    n1 = (16807 * 1234567890) % 2147483647
    n2 = (16807 * n1) % 2147483647
    n3 = (16807 * n2) % 2147483647
    assert (n1, n2, n3) == (395529916, 1209410747, 633705974)


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
@pytest.mark.parametrize("source", ["freq", "phase"])
def test_nbs14_10_point(name, source):
    ref = _reference()["nbs14_10point"]
    ms = np.array(ref["taus"], dtype=np.int64)
    if source == "freq":
        curve = ESTIMATORS[name](np.array(ref["freq"]), 1.0 / ref["tau0"], m=ms)
    else:
        curve = allan(
            np.array(ref["phase"]), 1.0 / ref["tau0"], name.lower(), m=ms, data_type="phase"
        )
    expected = ref["expected"][name]
    for got, want in zip(curve.dev, expected, strict=True):
        assert abs(got - want) <= _half_unit(want), (name, got, want)


@pytest.mark.parametrize("name", sorted(ESTIMATORS))
def test_nbs14_1000_point(name):
    ref = _reference()["nbs14_1000point"]
    freq = _nbs14_1000_freq()
    curve = ESTIMATORS[name](freq, 1.0, m=np.array(ref["taus"], dtype=np.int64))
    for got, want in zip(curve.dev, ref["expected"][name], strict=True):
        assert abs(got - want) <= _half_unit(want), (name, got, want)


def test_phase_and_rate_inputs_agree():
    freq = _nbs14_1000_freq()
    phase = np.concatenate(([0.0], np.cumsum(freq)))  # tau0 = 1 s
    for kind in ("oadev", "adev", "mdev", "ohdev"):
        a = allan(freq, 1.0, kind, m="octave")
        b = allan(phase, 1.0, kind, m="octave", data_type="phase")
        np.testing.assert_allclose(a.dev, b.dev, rtol=1e-12)
        np.testing.assert_array_equal(a.n_terms, b.n_terms)
