"""The diagnosis's hold-out check of its significant suggestions: checked best first, at most
``HOLDOUT_CHECKS``, and none left significant unchecked behind those that failed it."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from imunoise.analysis.diagnosis import holdout as holdout_module
from imunoise.analysis.diagnosis.holdout import HOLDOUT_CHECKS, _check_holdout
from imunoise.analysis.diagnosis.result import Suggestion


def _suggestion(term: str) -> Suggestion:
    return Suggestion(term=term, params={}, ci95={}, chi2_per_dof_before=3.6,
                      chi2_per_dof_after=2.0, p_value=1e-6, log_p=float(np.log(1e-6)),
                      significant=True, why=f"{term}.", fit=SimpleNamespace(),
                      apply={"model": f"white,{term}", "args": []}, action="add")


@pytest.mark.parametrize("passing", [None, 1])
def test_no_suggestion_stays_significant_unchecked_behind_failed_ones(
        monkeypatch: pytest.MonkeyPatch, passing: int | None) -> None:
    # every suggestion's prediction of the other half is worse than the given model's,
    # except the one at ``passing``
    names = [f"term{k}" for k in range(HOLDOUT_CHECKS + 2)]
    calls: list[str] = []

    def fake_part(x: Any, fs: float, model: str, fit: Any, starts: Any, **kw: Any) -> dict:
        calls.append(model)
        good = passing is not None and model.endswith(names[passing])
        return {"chi2_per_dof": 5.0 if good else 40.0}

    monkeypatch.setattr(holdout_module, "holdout_part", fake_part)
    ctx = SimpleNamespace(base=SimpleNamespace(misfit=SimpleNamespace(dof=15.0)), x=None,
                          fs_hz=100.0, starts=None, job_map=None)
    suggestions = [_suggestion(n) for n in names]
    _check_holdout(ctx, suggestions, {"chi2_per_dof": 9.9})  # type: ignore[arg-type]
    significant = [s.term for s in suggestions if s.significant]
    if passing is None:
        assert len(calls) == HOLDOUT_CHECKS and significant == []
        unchecked = [s for s in suggestions if "not computed" in s.why]
        assert [s.term for s in unchecked] == names[HOLDOUT_CHECKS:]
        assert all(s.held_by == "holdout" for s in unchecked)
    else:
        # the first that passes is the one to apply; nothing after it is judged
        assert len(calls) == passing + 1 and significant[0] == names[passing]
        assert suggestions[0].term == names[passing]
