"""The sentence a line's suggestion gets when its Allan refit leaves no room for the amplitude
the spectrum measures (:func:`imunoise.analysis.diagnosis.candidates._line_disagreement`).

The numbers are those of ADIS16405 run 3 accel_x at its final model: a line at 0.4434 Hz,
4.7 times the spectrum's floor (amplitude 1.38e-3 m/s^2), refitted by the Allan curve at
zero with a 95 % upper limit of 8.69e-4 m/s^2.
"""

from __future__ import annotations

from imunoise.analysis.diagnosis.candidates import _line_disagreement
from imunoise.analysis.evidence.finding import Finding

F_LINE = 0.44340159481259983
A_SPECTRUM = 1.38e-3


def _line(p_value: float = 1e-12, ratio: float = 4.68, nu: int = 60) -> Finding:
    return Finding("spectral_line", "sinusoid", 22.0, "F", p_value, 0.05,
                   params={"A": A_SPECTRUM, "f": F_LINE},
                   details={"nu": nu, "lines": [{"f_hz": F_LINE, "A": A_SPECTRUM,
                                                  "ratio": ratio}]})


def test_an_allan_interval_below_the_spectrum_amplitude_is_named_with_both_numbers():
    text, clause = _line_disagreement("sinusoid", _line(), {"f": F_LINE, "A": 1.1e-24},
                                      {"A": (0.0, 8.6881e-4), "f": (0.4419, 0.4449)},
                                      "m/s^2")
    # an amplitude whose interval reaches zero is not printed as a number
    assert "at zero (95 % upper limit 0.000869 m/s^2)" in text
    assert "1.1e-24" not in text
    assert "below the spectrum's 0.00138 m/s^2" in text
    assert "tau = 0.834 s" in text  # 0.37 / f, where a line bends the Allan curve
    # the held-back reason the text output prints names the spectrum's amplitude too
    assert clause == ", whose refit leaves no room for the 0.00138 m/s^2 the spectrum measures"


def test_a_resolved_amplitude_below_the_spectrum_is_given_with_its_interval():
    text, _ = _line_disagreement("sinusoid", _line(), {"f": F_LINE, "A": 6e-4},
                                 {"A": (4e-4, 8e-4)}, "m/s^2")
    assert "at 0.0006 m/s^2 (95 % 0.0004 .. 0.0008)" in text


def test_nothing_is_said_where_the_allan_interval_reaches_the_spectrum_amplitude():
    assert _line_disagreement("sinusoid", _line(), {"f": F_LINE, "A": 1e-3},
                              {"A": (0.0, 1.5e-3)}, "m/s^2") == ("", "")


def test_the_spectrum_amplitude_own_noise_is_allowed_for():
    # ratio 4.68 over nu = 60: the excess is 3.68 floors with a standard deviation of 0.85,
    # so the amplitude is at least 1.38e-3 sqrt(1 - 2 x 0.855 / 3.68) = 1.01e-3
    assert _line_disagreement("sinusoid", _line(), {"f": F_LINE, "A": 1e-24},
                              {"A": (0.0, 0.99e-3)}, "m/s^2") != ("", "")
    assert _line_disagreement("sinusoid", _line(), {"f": F_LINE, "A": 1e-24},
                              {"A": (0.0, 1.03e-3)}, "m/s^2") == ("", "")
    # a line barely above its floor in a bin of few dof measures no amplitude to compare
    assert _line_disagreement("sinusoid", _line(ratio=2.0, nu=16), {"f": F_LINE, "A": 1e-24},
                              {"A": (0.0, 1e-5)}, "m/s^2") == ("", "")


def test_nothing_is_said_of_a_line_refitted_elsewhere_or_without_spectral_evidence():
    moved = {"f": 0.61, "A": 1e-24}
    assert _line_disagreement("sinusoid", _line(), moved, {"A": (0.0, 8e-4)}, "m/s^2") == ("", "")
    held = {"f": F_LINE, "A": 1e-24}
    assert _line_disagreement("sinusoid", _line(p_value=0.3), held, {"A": (0.0, 8e-4)},
                              "m/s^2") == ("", "")
    # not a line: a resonance's amplitude is not what the line search measures
    assert _line_disagreement("resonance", _line(), {"f0": F_LINE, "sigma": 1e-24},
                              {"sigma": (0.0, 8e-4)}, "m/s^2") == ("", "")
