"""The command line's job map: candidates, hold-out halves and profile intervals refitted side
by side in forked processes give the serial results exactly."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from imunoise.analysis.diagnosis import diagnose
from imunoise.pipeline import workers
from imunoise.pipeline.workers import can_fork, cpu_job_map, forked_map

pytestmark = pytest.mark.skipif(not can_fork(), reason="needs fork and a single thread")


def _pid_and_square(shared: dict, item: int) -> tuple[int, int]:
    return os.getpid(), shared["k"] * item * item


def _fails_on_three(shared: None, item: int) -> int:
    if item == 3:
        raise ValueError(f"item {item} is refused")
    return item


def _single_threaded() -> None:
    """Skip where another test left a thread running in this process (a test runner's worker
    runs many tests): the job map then rightly stays serial."""
    if not can_fork():
        names = [t.name for t in threading.enumerate() if t is not threading.main_thread()]
        pytest.skip(f"threads still running here: {', '.join(names)}")


def test_results_come_back_in_order_from_other_processes() -> None:
    _single_threaded()
    out = forked_map(_pid_and_square, {"k": 2}, list(range(7)), workers=2)
    assert [v for _, v in out] == [2 * i * i for i in range(7)]
    assert os.getpid() not in {pid for pid, _ in out}
    assert workers._SHARED is None  # nothing of the job is left behind


def test_one_worker_or_one_item_runs_here() -> None:
    for count, items in ((1, [1, 2, 3]), (4, [5])):
        out = forked_map(_pid_and_square, {"k": 1}, items, count)
        assert {pid for pid, _ in out} == {os.getpid()}


def test_with_another_thread_running_nothing_is_forked() -> None:
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        assert not can_fork()
        out = forked_map(_pid_and_square, {"k": 1}, [1, 2, 3], workers=2)
    finally:
        stop.set()
        t.join()
    assert {pid for pid, _ in out} == {os.getpid()}


def test_a_job_that_raises_raises_in_the_caller() -> None:
    with pytest.raises(ValueError, match="item 3 is refused"):
        forked_map(_fails_on_three, None, [1, 2, 3, 4], workers=2)
    assert workers._SHARED is None


def _white_walk_and_line(seed: int, fs: float = 100.0, n: int = 200_000) -> np.ndarray:
    """White noise, a rate random walk and a 3.1 Hz line (rad/s)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    return rng.normal(0.0, 1e-3 * np.sqrt(fs), n) \
        + np.cumsum(rng.normal(0.0, 2e-5 / np.sqrt(fs), n)) + 2e-3 * np.sin(2 * np.pi * 3.1 * t)


def test_diagnosis_with_two_workers_equals_the_serial_one() -> None:
    fs = 100.0
    x = _white_walk_and_line(11, fs)
    serial = diagnose(x, fs, "white,random_walk", holdout=False, transients=False)
    forked = diagnose(x, fs, "white,random_walk", holdout=False, transients=False,
                      job_map=cpu_job_map(2))
    assert [s.term for s in forked.suggestions] == [s.term for s in serial.suggestions]
    assert any(s.significant for s in serial.suggestions)  # the line is found
    for a, b in zip(serial.suggestions, forked.suggestions, strict=True):
        assert (a.significant, a.log_p, a.params) == (b.significant, b.log_p, b.params)
        assert a.chi2_per_dof_after == b.chi2_per_dof_after \
            or (np.isnan(a.chi2_per_dof_after) and np.isnan(b.chi2_per_dof_after))


def test_holdout_part_with_two_workers_equals_the_serial_one() -> None:
    from imunoise.analysis.fit import fit_series
    from imunoise.analysis.model_error import holdout_part

    rng = np.random.default_rng(12)
    fs, n = 100.0, 200_000
    x = rng.normal(0.0, 1e-3 * np.sqrt(fs), n) \
        + np.cumsum(rng.normal(0.0, 2e-5 / np.sqrt(fs), n))
    x[n // 2:] *= 1.05  # the second half 5 % noisier: a change to name
    fit, _ = fit_series(x, fs, "white,random_walk", intervals="jacobian")
    serial = holdout_part(x, fs, "white,random_walk", fit)
    forked = holdout_part(x, fs, "white,random_walk", fit, job_map=cpu_job_map(2))
    assert forked == serial
    assert [c["param"] for c in serial["changed"]] == ["white.N"]


def test_profile_intervals_with_two_workers_equal_the_serial_ones() -> None:
    from imunoise.analysis.fit import fit_series

    rng = np.random.default_rng(13)
    fs, n = 100.0, 100_000
    x = rng.normal(0.0, 1e-3 * np.sqrt(fs), n) \
        + np.cumsum(rng.normal(0.0, 2e-5 / np.sqrt(fs), n))
    serial, _ = fit_series(x, fs, "white,bias_instability,random_walk")
    forked, _ = fit_series(x, fs, "white,bias_instability,random_walk",
                           job_map=cpu_job_map(2))
    assert [t.params for t in forked.terms] == [t.params for t in serial.terms]
    assert [t.ci95 for t in forked.terms] == [t.ci95 for t in serial.terms]


def test_diagnosis_parts_with_two_workers_equal_the_serial_ones() -> None:
    # the given model's hold-out halves run among the candidates' refits, the evidence beside
    # the transient and PSD tests: the error parts and the ranking do not change
    fs = 100.0
    x = _white_walk_and_line(14, fs)
    serial = diagnose(x, fs, "white,random_walk")
    forked = diagnose(x, fs, "white,random_walk", job_map=cpu_job_map(2))
    assert forked.error_parts == serial.error_parts
    assert serial.error_parts["holdout"]["chi2_per_dof"] > 0.0
    assert serial.error_parts["time_domain"]["statistic"] is not None
    assert [(s.term, s.significant, s.log_p) for s in forked.suggestions] \
        == [(s.term, s.significant, s.log_p) for s in serial.suggestions]
    assert [f.kind for f in forked.findings] == [f.kind for f in serial.findings]


def _pid_and_sum(values: list[int]) -> tuple[int, int]:
    return os.getpid(), sum(values)


def _refuse(what: str) -> None:
    raise ValueError(f"{what} is refused")


def _die_unless_in(pid: int) -> int:
    if os.getpid() != pid:
        os._exit(3)  # the child killed before it sends anything
    return 42


@pytest.mark.skipif(workers.available_cpus() < 2, reason="one CPU: computed in this process")
def test_background_computes_in_another_process_and_starts_no_thread() -> None:
    _single_threaded()
    job = workers.Background(_pid_and_sum, [1, 2, 3])
    assert threading.active_count() == 1  # a job map may still fork meanwhile
    out = forked_map(_pid_and_square, {"k": 1}, [1, 2], workers=2)
    assert os.getpid() not in {pid for pid, _ in out}
    pid, total = job.result()
    assert total == 6 and pid != os.getpid()
    assert job.result() == (pid, 6)  # asked again: the same result, not a second run


def test_background_raises_what_the_function_raises() -> None:
    job = workers.Background(_refuse, "the record")
    with pytest.raises(ValueError, match="the record is refused"):
        job.result()


def test_background_whose_child_dies_is_computed_here() -> None:
    job = workers.Background(_die_unless_in, os.getpid())
    assert job.result() == 42


def test_background_with_another_thread_running_is_computed_here() -> None:
    stop = threading.Event()
    t = threading.Thread(target=stop.wait)
    t.start()
    try:
        job = workers.Background(_pid_and_sum, [4, 5])
    finally:
        stop.set()
        t.join()
    assert job.result() == (os.getpid(), 9)
