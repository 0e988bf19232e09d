"""Real-time priority for the kernel's unbound workers: raised while asked, found again when
new ones appear, given back at stop, left alone when already real-time; and `serve
--realtime-kernel-workers` reports it in /health and restores the workers when it ends.

The raising is tried on real processes of this test (a ``sleep``), so that nothing here
depends on which kernel workers exist; where the system refuses real-time priority, the test
checks the refusal is reported and nothing changed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from live.kernel_workers import (
    FIFO_PRIORITY,
    KernelWorkerBoost,
    is_unbound_worker,
    processes,
)
from tests.live_helpers import free_port, wait_until


def _sleeper(nice: int = 0) -> subprocess.Popen:
    return subprocess.Popen(["nice", "-n", str(nice), "sleep", "60"])


def _policy(pid: int) -> tuple[int, int, int]:
    return (os.sched_getscheduler(pid), os.sched_getparam(pid).sched_priority,
            os.getpriority(os.PRIO_PROCESS, pid))


def test_unbound_workers_are_told_apart_by_name():
    assert is_unbound_worker(1, "kworker/u8:2-events_unbound")
    assert is_unbound_worker(1, "kworker/u9:0")
    assert not is_unbound_worker(1, "kworker/0:1H-kblockd")
    assert not is_unbound_worker(1, "python")


def test_processes_lists_live_processes_with_their_names():
    found = dict(processes())
    assert found[os.getpid()] == Path("/proc/self/comm").read_text().strip()
    assert all(isinstance(pid, int) and pid > 0 for pid in found)
    assert dict(processes(Path("/no/such/proc"))) == {}


def test_raised_while_running_and_given_back_at_stop():
    child = _sleeper(nice=5)
    try:
        wait_until(lambda: os.getpriority(os.PRIO_PROCESS, child.pid) == 5)
        before = _policy(child.pid)
        assert before == (os.SCHED_OTHER, 0, 5)
        boost = KernelWorkerBoost(match=lambda pid, comm: pid == child.pid).start()
        try:
            if boost.refused is not None:  # no right to real-time priority here
                assert boost.refused.startswith("SCHED_FIFO for kernel workers: ")
                assert _policy(child.pid) == before
                assert boost.status()["threads"] == 0
                return
            assert _policy(child.pid)[:2] == (os.SCHED_FIFO, FIFO_PRIORITY)
            assert boost.status() == {"policy": f"SCHED_FIFO {FIFO_PRIORITY}", "threads": 1,
                                      "refused": None}
        finally:
            boost.stop()
        assert _policy(child.pid) == before
        assert boost.status()["threads"] == 0
    finally:
        child.kill()
        child.wait()


def test_a_worker_that_appears_later_is_raised_and_a_real_time_one_left_alone():
    pids: set[int] = set()
    rt = _sleeper()
    try:
        try:
            os.sched_setscheduler(rt.pid, os.SCHED_FIFO, os.sched_param(2))
        except PermissionError:
            pytest.skip("this system refuses real-time priority (the refusal is tested above)")
        pids.add(rt.pid)
        boost = KernelWorkerBoost(match=lambda pid, comm: pid in pids, every_s=0.05).start()
        late = _sleeper()
        try:
            assert boost.status()["threads"] == 0  # the real-time one is not taken over
            pids.add(late.pid)
            assert wait_until(lambda: os.sched_getscheduler(late.pid) == os.SCHED_FIFO)
            assert boost.status()["threads"] == 1
        finally:
            boost.stop()
            assert os.sched_getscheduler(late.pid) == os.SCHED_OTHER
            assert _policy(rt.pid)[:2] == (os.SCHED_FIFO, 2)  # never changed, never "restored"
            late.kill()
            late.wait()
    finally:
        rt.kill()
        rt.wait()


@pytest.mark.parametrize("source, message", [
    (["--device", "sim:adis16350", "--acquisition", "thread"],
     "serve: --realtime-kernel-workers needs --acquisition process"),
    (["--replay", "night.mcap"],
     "serve: --realtime-kernel-workers applies to a device, not to --replay"),
])
def test_serve_refuses_the_option_without_an_acquisition_process(source, message):
    run = subprocess.run([sys.executable, "-m", "imunoise", "serve", *source,
                          "--realtime-kernel-workers", "--port", str(free_port())],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2
    assert run.stderr.strip().splitlines()[-1] == f"imunoise: {message}"


def _at_fifo_1(pid: int) -> bool:
    try:
        return (os.sched_getscheduler(pid) == os.SCHED_FIFO
                and os.sched_getparam(pid).sched_priority == FIFO_PRIORITY)
    except ProcessLookupError:
        return False


def test_serve_reports_the_workers_in_health_and_restores_them_when_it_ends(tmp_path):
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "imunoise", "serve", "--device",
                             "sim:adis16350", "--port", str(port), "--out", str(tmp_path),
                             "--priority", "normal", "--realtime-kernel-workers"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    health: dict = {}
    raised: set[int] = set()
    try:
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and not health.get("samples", {}).get("received"):
            try:
                with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=5) as r:
                    health = json.load(r)
            except OSError:
                time.sleep(0.5)
        assert health, f"serve did not come up: {proc.stderr.read()[-2000:]}"
        workers = health["acquisition_process"]["kernel_workers"]
        assert workers["policy"] == f"SCHED_FIFO {FIFO_PRIORITY}"
        visible = [pid for pid, comm in processes() if is_unbound_worker(pid, comm)]
        if workers["refused"] is None and not visible:
            assert workers["threads"] == 0  # in a container that does not show them
        elif workers["refused"] is None:
            raised = {pid for pid in visible if _at_fifo_1(pid)}
            assert raised and workers["threads"] > 0
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
    assert proc.returncode == 0
    assert not [pid for pid in raised if _at_fifo_1(pid)]  # ended workers count as given back
