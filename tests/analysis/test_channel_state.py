"""The live per-channel state is plain data: a job is planned, run by the caller, published."""

from __future__ import annotations

import ast

import numpy as np

from imunoise.analysis.channel_state import ChannelState
from tests.shared_paths import REPO

FS = 100.0


def _state(n: int = 60_000, seed: int = 1) -> ChannelState:
    rng = np.random.default_rng(seed)
    s = ChannelState("gyro_x", FS, model=["white", "random_walk"])
    s.update(rng.normal(0, 0.03, n) + np.cumsum(rng.normal(0, 2e-6, n)))
    return s


def test_a_fit_planned_before_a_model_change_is_not_published_after_it() -> None:
    s = _state()
    job = s.plan_refit(full=False, now=1.0)
    assert job is not None and job.fn is not None and s.snapshot().fit is None
    change = s.plan_model_change(["white", "random_walk", "bias_instability"])
    s.finish_model_change(change, change.job.fn(*change.job.args), wall_s=100.0)
    assert s.snapshot().model_revision == 1
    stale = job.fn(*job.args)  # the old model's fit, finished late
    assert s.finish_refit(job, stale, wall_s=101.0) is False
    snap = s.snapshot()
    assert [t.term for t in snap.fit.terms] == ["white", "bias_instability", "random_walk"]
    assert [p.revision for p in snap.history] == [1]


def test_a_refit_of_the_same_samples_reuses_the_fit_and_due_follows_the_given_clock() -> None:
    s = _state()
    job = s.plan_refit(full=True, now=10.0)
    assert s.finish_refit(job, job.fn(*job.args), wall_s=1000.0)
    again = s.plan_refit(full=False, now=11.0)  # same samples: the profile fit serves
    assert again.fn is None and again.cached is s.snapshot().fit
    assert again.intervals == "profile"
    assert s.due(12.0) == (-np.inf, "diagnose")  # a new model revision is diagnosed at once
    diag = s.plan_diagnosis(now=11.2)
    assert s.finish_diagnosis(diag, ([], []))
    s.update(np.zeros(10))
    # new samples: the routine refit 2 s after the last (at 11), the diagnosis 60 s after
    assert s.due(12.9) is None and s.due(13.5) == (13.0, "fit")
    assert s.due(80.0) == (70.0, "full")  # a full fit supersedes the routine one
    assert s.snapshot().fit_wall_s == 1000.0


def test_the_analysis_package_keeps_no_clock_thread_or_process_of_the_live_runtime() -> None:
    """The state module imports no threading or time; no analysis module reads the wall or
    monotonic clock, sleeps, or starts processes (the live runtime in ``live/`` does)."""
    banned_calls = {("time", "time"), ("time", "monotonic"), ("time", "sleep"),
                    ("time", "thread_time")}
    banned_modules = {"multiprocessing", "subprocess", "signal", "sched"}
    found: list[str] = []
    for path in sorted((REPO / "analysis").rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        rel = str(path.relative_to(REPO))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import | ast.ImportFrom):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                    [node.module or ""]
                for name in names:
                    top = name.split(".")[0]
                    if top in banned_modules or (rel == "analysis/channel_state.py" and
                                                 top in ("threading", "time")):
                        found.append(f"{rel}: import {name}")
            elif isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and \
                    (node.value.id, node.attr) in banned_calls:
                found.append(f"{rel}: {node.value.id}.{node.attr}")
    assert not found, found


def test_one_occurrence_of_a_repeated_term_is_removed_by_its_label() -> None:
    s = ChannelState("gyro_x", FS, model=["white", "gauss_markov:T=5", "gauss_markov:T=50",
                                          "random_walk"])
    model = s.model  # in the live service's term order

    def but(*gone: str) -> list[str]:
        return [t for t in model if t not in gone]

    # the label the /coefficients rows carry removes that entry alone
    assert s.without_term("gauss_markov#2") == but("gauss_markov:T=50")
    assert s.without_term("gauss_markov") == but("gauss_markov:T=5", "gauss_markov:T=50")
    assert s.without_term("gauss_markov:T=50") == but("gauss_markov:T=50")
    for absent, message in (("gauss_markov#3", "not in the model"),
                            ("resonance", "not in the model"), ("markov#2", "unknown term")):
        try:
            s.without_term(absent)
        except ValueError as exc:
            assert message in str(exc), exc
        else:
            raise AssertionError(f"{absent} was removed")


def test_the_live_fits_list_repeated_terms_in_shape_order() -> None:
    from imunoise.analysis.allan import oadev
    from imunoise.analysis.channel_state import _job_fit, _job_fit_new_model

    rng = np.random.default_rng(42)  # the solver puts a 12 s Markov term in the first entry
    n = 120_000
    x = rng.normal(0.0, 0.01, n) + np.cumsum(rng.normal(0.0, 2e-5, n))
    curve = oadev(x, FS, m="octave")
    model = ["white", "gauss_markov", "gauss_markov", "random_walk"]
    for fit in (_job_fit(curve, model, None, None, "jacobian"),
                _job_fit_new_model(curve, model, None, {}, None)):
        assert fit.labels == ["white", "gauss_markov", "gauss_markov#2", "random_walk"]
        assert fit.terms[1].params["T"] < 1.0 < 5.0 < fit.terms[2].params["T"]
