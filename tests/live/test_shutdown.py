"""Stopping the live service never waits for a fit: the worker process is ended at once."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from imunoise.live.scheduler import WorkerClosed, WorkerProcess
from imunoise.live.service import LiveService
from tests.live_helpers import SourceStats, SyntheticImu, touch_then_sleep


def _wait_for(path: Path, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert time.monotonic() < deadline, "the worker never started the job"
        time.sleep(0.05)


def test_closing_the_worker_abandons_a_running_job_at_once(tmp_path: Path) -> None:
    worker = WorkerProcess()
    flag = tmp_path / "started"
    outcome: list[BaseException | tuple] = []

    def call() -> None:
        try:
            outcome.append(worker(touch_then_sleep, str(flag), 120.0))
        except BaseException as exc:  # noqa: BLE001 - the test inspects it
            outcome.append(exc)

    t = threading.Thread(target=call)
    t.start()
    _wait_for(flag)
    processes = list(worker._pool._processes.values())
    manager = worker._pool._executor_manager_thread
    t0 = time.monotonic()
    worker.close()
    t.join(30)
    assert not t.is_alive() and time.monotonic() - t0 < 15  # not the job's 120 s
    assert len(outcome) == 1 and isinstance(outcome[0], WorkerClosed)
    assert processes and not any(p.is_alive() for p in processes)
    # and the executor's own thread has ended, so that nothing of it is left for the
    # interpreter's exit to trip over (a "Bad file descriptor" after a clean stop)
    assert manager is not None and not manager.is_alive()
    assert worker.fallback is None  # closing is not a failure: no in-process fallback
    with pytest.raises(WorkerClosed):
        worker(touch_then_sleep, str(flag), 0.0)


class _SlowAnalysis:
    """Analyzers whose every job is a long fit in a real worker process."""

    def __init__(self, flag: Path) -> None:
        self.flag = flag
        self.worker = WorkerProcess()
        self.channels: list[str] = []
        self.revision = 0

    def update(self, block) -> None:
        pass

    def refresh(self, force: bool = False) -> bool:
        self.worker(touch_then_sleep, str(self.flag), 120.0)
        return True

    def stats(self) -> dict:
        return {}

    def close(self) -> None:
        self.worker.close()


class _CountingSink:
    def __init__(self) -> None:
        self.samples = 0
        self.closed = False

    def write(self, block) -> None:
        self.samples += len(block.t)

    def close(self) -> None:
        self.closed = True


def test_stopping_the_service_during_a_fit_closes_the_sinks_without_waiting(tmp_path: Path):
    source = SyntheticImu(block=100, pace=True)
    sink = _CountingSink()
    svc = LiveService(source, _SlowAnalysis(tmp_path / "started"), sinks=[sink]).start()
    try:
        _wait_for(tmp_path / "started")
    finally:
        t0 = time.monotonic()
        svc.stop()
        took = time.monotonic() - t0
    assert took < 10  # the fit would have taken 120 s
    assert sink.closed and sink.samples == source.stats.samples > 0
    assert svc.error is None  # the abandoned fit is not reported as a failure


class _GatedAnalysis:
    """Analyzers whose first update waits for a gate (a stall in the streaming estimates)."""

    def __init__(self) -> None:
        self.entered = threading.Event()
        self.gate = threading.Event()
        self.channels: list[str] = []
        self.revision = 0
        self.samples = 0

    def update(self, block) -> None:
        self.entered.set()
        self.gate.wait(30)
        self.samples += len(block.t)

    def refresh(self, force: bool = False) -> bool:
        return False

    def stats(self) -> dict:
        return {}

    def close(self) -> None:
        pass


def test_blocks_handed_over_before_a_stop_are_all_counted_in() -> None:
    # a stop while the analysis is busy with one block, blocks queued behind it: each block
    # the acquisition received is analysed or counted as not analysed, none is left over
    source = SyntheticImu(block=10, pace=True)
    analysis = _GatedAnalysis()
    svc = LiveService(source, analysis, sinks=[]).start()
    assert analysis.entered.wait(30)
    deadline = time.monotonic() + 30
    while svc.blocks_received < 4:
        assert time.monotonic() < deadline
        time.sleep(0.02)
    stopper = threading.Thread(target=svc.stop)
    stopper.start()
    while not (svc._abandon and svc._acq_done.is_set()):
        assert time.monotonic() < deadline
        time.sleep(0.01)
    analysis.gate.set()
    stopper.join(30)
    assert not stopper.is_alive()
    assert svc.samples_received >= 40
    assert svc.samples_analysed + svc.samples_not_analysed == svc.samples_received
    assert analysis.samples == svc.samples_analysed


def test_a_stop_signal_ends_the_recording_first_and_no_final_fit_is_awaited(tmp_path: Path):
    """``serve`` calls ``stop_acquisition`` from its signal handler: the source ends (the file
    closes) at once, while a fit is still running and the HTTP side winds down; the stop
    that follows abandons the fit instead of running the final full fits of a finished
    replay."""
    source = SyntheticImu(block=100, pace=True)
    sink = _CountingSink()
    svc = LiveService(source, _SlowAnalysis(tmp_path / "started"), sinks=[sink]).start()
    try:
        _wait_for(tmp_path / "started")
        svc.stop_acquisition()
        assert svc.wait(5.0)  # the acquisition ended though the 120 s fit still runs
        assert not svc.running
    finally:
        t0 = time.monotonic()
        svc.stop()
        took = time.monotonic() - t0
    assert took < 10  # neither the running fit nor a final one is awaited
    assert sink.closed and sink.samples == source.stats.samples > 0
    assert svc.error is None


class _BatchedSource:
    """Like the acquisition: reads a batch of blocks from the device, counts its samples, then
    hands the blocks out one by one; after a stop, what was read is handed out last."""

    def __init__(self) -> None:
        self.stats = SourceStats()
        self._stop = threading.Event()
        self._imu = SyntheticImu(block=10)

    def stop(self) -> None:
        self._stop.set()

    def _read(self, n: int) -> list:
        blocks = [self._imu._make(0) for _ in range(n)]
        self.stats.samples += sum(len(b.t) for b in blocks)
        return blocks

    def blocks(self):
        while not self._stop.is_set():
            yield from self._read(3)
        yield from self._read(1)  # the device's last samples, read as the stop arrives


class _StopOnFirstBlockSink(_CountingSink):
    """Stops the service as the first block arrives, in the middle of the source's batch."""

    def __init__(self) -> None:
        super().__init__()
        self.svc: LiveService | None = None
        self.stopper: threading.Thread | None = None

    def write(self, block) -> None:
        super().write(block)
        if self.stopper is None and self.svc is not None:
            stopper = threading.Thread(target=self.svc.stop)
            stopper.start()
            self.stopper = stopper  # seen by the test only once started
            while not self.svc._stop.is_set():
                time.sleep(0.001)


def test_a_stop_in_the_middle_of_a_batch_still_records_every_sample_read() -> None:
    source = _BatchedSource()
    sink = _StopOnFirstBlockSink()
    analysis = _GatedAnalysis()
    analysis.gate.set()
    svc = LiveService(source, analysis, sinks=[sink])
    sink.svc = svc
    svc.start()
    deadline = time.monotonic() + 30
    while sink.stopper is None:
        assert time.monotonic() < deadline
        time.sleep(0.01)
    sink.stopper.join(30)
    assert not sink.stopper.is_alive() and sink.closed
    # the batch's other two blocks and the last read reach the file: 4 blocks of 10
    assert sink.samples == source.stats.samples == 40


def test_a_stop_while_the_threads_start_still_waits_for_the_acquisition(monkeypatch) -> None:
    # the starting thread is descheduled right after the acquisition starts, until the first
    # block has set off the stop: that stop must still join the acquisition, not find no
    # thread to join
    start = threading.Thread.start
    stop_sent = threading.Event()

    def slow_start(thread: threading.Thread) -> None:
        start(thread)
        if thread.name == "imunoise-acquisition":
            assert stop_sent.wait(30), "the first block never arrived"
            time.sleep(0.1)  # the stop runs meanwhile

    class _SlowAfterTheFirstSink(_StopOnFirstBlockSink):
        def write(self, block) -> None:
            if self.stopper is not None:
                time.sleep(0.2)  # a stop returning early finds these blocks not written yet
            else:
                stop_sent.set()  # the stop starts in this call
            super().write(block)

    monkeypatch.setattr(threading.Thread, "start", slow_start)
    source = _BatchedSource()
    sink = _SlowAfterTheFirstSink()
    analysis = _GatedAnalysis()
    analysis.gate.set()
    svc = LiveService(source, analysis, sinks=[sink])
    sink.svc = svc
    svc.start()
    assert sink.stopper is not None  # the stop arrived while start() was under way
    sink.stopper.join(30)
    assert not sink.stopper.is_alive() and sink.closed
    assert sink.samples == source.stats.samples == 40
