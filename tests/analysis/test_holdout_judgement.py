"""How a suggestion's hold-out part is judged against the given model's: the plain
prediction and, where the part names changed parameters, the prediction with them fitted."""

from __future__ import annotations

from imunoise.analysis.diagnosis.holdout import _holdout_worse
from imunoise.analysis.model_error import right_model_limit

DOF = 15.0  # right_model_limit(15) = 2.10; a part of 1 has sd sqrt(2/15) = 0.37


def _part(plain: float | None, free: float | None = None) -> dict:
    out: dict = {"chi2_per_dof": plain, "parts": 2}
    if free is not None:
        out["changes_free"] = {"chi2_per_dof": free, "halves": [free, free], "params": ["x.y"]}
    return out


def test_a_right_model_keeps_its_prediction_within_noise() -> None:
    assert right_model_limit(DOF) < 2.2
    # 1.0 -> 2.0 is within three sd (1.10) of a right model's part; 1.0 -> 2.2 is not
    assert _holdout_worse(_part(1.0), _part(2.0), DOF, claims=True) is None
    why = _holdout_worse(_part(1.0), _part(2.2), DOF, claims=True)
    assert why == ("it does not keep the hold-out part (the model fitted on one half "
                   "predicting the other: chi2/dof 1 -> 2.2).")


def test_a_model_that_does_not_predict_needs_a_term_that_lowers_the_part() -> None:
    assert _holdout_worse(_part(5.0), _part(4.9), DOF, claims=True) is None
    why = _holdout_worse(_part(5.0), _part(5.0), DOF, claims=True)
    assert why is not None and why.startswith("it does not lower the hold-out part")
    # a removal claims nothing new: it only must not make the prediction worse
    assert _holdout_worse(_part(5.0), _part(5.0), DOF, claims=False) is None


def test_the_prediction_with_named_changes_fitted_is_judged_too() -> None:
    # the plain part is dominated by a named change and falls a little; with the change
    # fitted on each half the prediction doubles
    why = _holdout_worse(_part(67.9, 3.21), _part(67.0, 6.12), DOF, claims=True)
    assert why == ("it does not lower the hold-out part (the changes it names fitted on "
                   "each half: chi2/dof 3.21 -> 6.12).")
    assert _holdout_worse(_part(67.9, 3.21), _part(67.0, 3.0), DOF, claims=True) is None
    # below a right model's limit it needs only to keep it
    assert _holdout_worse(_part(67.9, 1.5), _part(67.0, 1.6), DOF, claims=True) is None


def test_a_part_that_cannot_be_computed_judges_nothing() -> None:
    assert _holdout_worse(_part(5.0, 3.0), _part(None, 9.0), DOF, claims=True) is None
    # where only one side names changes, the plain part alone judges
    assert _holdout_worse(_part(67.9, 3.21), _part(60.0), DOF, claims=True) is None
    assert _holdout_worse(_part(5.0), _part(4.0, 9.0), DOF, claims=True) is None


def test_a_fall_with_changes_fitted_does_not_excuse_a_rise_of_the_plain_part() -> None:
    # ADIS16405 run 3 gyro_z with two resonances (plain 9.87, 5.40 with the 20 Hz peak's
    # named move fitted): a Markov term at the shortest time allowed (0.02 s) lowers the
    # Allan part from 3.71 to 0.96, and its part with its own named changes fitted to 5.02,
    # but those changes are the halves trading the second resonance between 19.4 and 9.5 Hz
    # and the random walk between 2.8e-5 and 3.1e-6; the plain part rises to 14.4. Judged
    # by changes_free alone the loop took it, and refitted on each half with those changes
    # free the model predicted the other half at chi2/dof 47.6 (5.4 without it)
    why = _holdout_worse(_part(9.87, 5.40), _part(14.4, 5.02), DOF, claims=True)
    assert why == ("it does not lower the hold-out part (the model fitted on one half "
                   "predicting the other: chi2/dof 9.87 -> 14.4).")
