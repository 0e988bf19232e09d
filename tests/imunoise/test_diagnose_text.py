"""The diagnosis text says why a term with strong evidence is held back."""

from __future__ import annotations

import numpy as np

from imunoise.analysis.diagnosis import diagnose
from imunoise.commands.diagnose import diagnosis_text
from imunoise.core.series import ChannelSeries


def test_a_held_back_term_is_named_where_the_model_fails():
    """White noise plus a strong sinusoid, diagnosed with white noise alone: the sinusoid is
    the top suggestion. With every significant term held back (as the hold-out check does
    to a term that predicts the other half worse), the text gives each one's reason and
    names them instead of saying that no term explains the failure."""
    fs, n = 50.0, 2**17
    rng = np.random.default_rng(7)
    t = np.arange(n) / fs
    x = 1e-3 * rng.standard_normal(n) * np.sqrt(fs) + 5e-3 * np.sin(2 * np.pi * 1.3 * t)
    diag = diagnose(x, fs, "white", holdout=False, transients=False)
    assert diag.suggestions[0].term == "sinusoid" and diag.fit.failures
    held = [s for s in diag.suggestions if s.significant]
    for s in held:
        s.significant = False
        s.held_by = "holdout"
        s.held_reason = ("it does not lower the hold-out part (the model fitted on one half "
                         "predicting the other: chi2/dof 9 -> 20).")
    series = ChannelSeries("x", "rad/s", fs, x, np.zeros(1, dtype=np.int64))
    text = diagnosis_text("x", series, diag)
    assert "        held back: it does not lower the hold-out part (the model fitted on one " \
           "half predicting the other: chi2/dof 9 -> 20)." in text
    # with them, in the ranking's order, a term held back by its own rule (here a Markov
    # term at two sample periods beside the significant filters)
    named = [s.term for s in diag.suggestions if s.p_value < diag.alpha and s.held_by]
    assert set(named) > {s.term for s in held}
    assert f"the model fails; {', '.join(named)} lower its error" in text
    assert "no single added term explains" not in text
