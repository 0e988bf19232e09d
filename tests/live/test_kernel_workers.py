"""Real-time priority for the kernel's unbound workers: raised while asked, found again when
new ones appear, given back when the last holder stops (not before, and also when a holder
died without stopping), left alone when already real-time; the keeper process gives them back
when its parent is killed; and `serve` raises them by default for a serial device, reports
them in /health and restores them when it ends.

The raising is tried on real processes of this test (a ``sleep``), so that nothing here
depends on which kernel workers exist; where the system refuses real-time priority, the test
checks the refusal is reported and nothing changed."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from imunoise.cli import build_parser
from imunoise.commands.serve import raise_kernel_workers
from imunoise.live.kernel_workers import (
    FIFO_PRIORITY,
    KernelWorkerBoost,
    KernelWorkerKeeper,
    WorkerLedger,
    is_unbound_worker,
    process_name,
    process_start,
    processes,
    worker_name,
)
from tests.live_helpers import free_port, wait_until

REPO = Path(__file__).resolve().parents[2]


def _started(child: subprocess.Popen, name: str) -> subprocess.Popen:
    """``child`` once ``nice`` has handed over to the program: before that the process is
    named ``nice``, and a worker recorded under that name is not given back (its name no
    longer matches at the stop)."""
    assert wait_until(lambda: process_name(child.pid) == name[:15]), f"{name} never started"
    return child


def _sleeper(nice: int = 0) -> subprocess.Popen:
    return _started(subprocess.Popen(["nice", "-n", str(nice), "sleep", "60"]), "sleep")


def _only(*children: subprocess.Popen):
    pids = {c.pid for c in children}
    return lambda pid, comm: pid in pids


def _policy(pid: int) -> tuple[int, int, int]:
    return (os.sched_getscheduler(pid), os.sched_getparam(pid).sched_priority,
            os.getpriority(os.PRIO_PROCESS, pid))


def test_unbound_workers_are_told_apart_by_name():
    assert is_unbound_worker(1, "kworker/u8:2-events_unbound")
    assert is_unbound_worker(1, "kworker/u9:0")
    assert not is_unbound_worker(1, "kworker/0:1H-kblockd")
    assert not is_unbound_worker(1, "python")


def test_a_worker_keeps_its_name_whatever_work_it_runs():
    assert worker_name("kworker/u8:2-events_unbound") == "kworker/u8:2"
    assert worker_name("kworker/u8:2+events_unbound") == "kworker/u8:2"  # running it now
    assert worker_name("kworker/u8:2+ext4-rsv-conversion") == "kworker/u8:2"
    assert worker_name("kworker/u9:0") == "kworker/u9:0"


def test_processes_lists_live_processes_with_their_names():
    found = dict(processes())
    assert found[os.getpid()] == Path("/proc/self/comm").read_text().strip()
    assert all(isinstance(pid, int) and pid > 0 for pid in found)
    assert dict(processes(Path("/no/such/proc"))) == {}


def test_process_start_names_a_process_for_good():
    child = _sleeper()
    start = process_start(child.pid)
    assert start is not None and start >= process_start(1)
    child.kill()
    child.wait()
    assert process_start(child.pid) is None


def test_raised_while_running_and_given_back_at_stop(tmp_path):
    child = _sleeper(nice=5)
    try:
        wait_until(lambda: os.getpriority(os.PRIO_PROCESS, child.pid) == 5)
        before = _policy(child.pid)
        assert before == (os.SCHED_OTHER, 0, 5)
        boost = KernelWorkerBoost(match=_only(child),
                                  ledger=WorkerLedger(tmp_path / "ledger.json")).start()
        try:
            if boost.refused is not None:  # no right to real-time priority here
                assert boost.refused.startswith("SCHED_FIFO for kernel workers: ")
                assert _policy(child.pid) == before
                assert boost.status()["threads"] == 0
                return
            assert _policy(child.pid)[:2] == (os.SCHED_FIFO, FIFO_PRIORITY)
            assert boost.status() == {"policy": f"SCHED_FIFO {FIFO_PRIORITY}", "threads": 1,
                                      "holders": 1, "refused": None}
        finally:
            boost.stop()
        assert _policy(child.pid) == before
        assert boost.status()["threads"] == 0
    finally:
        child.kill()
        child.wait()


def _named_sleeper(tmp_path: Path, name: str, nice: int = 0) -> subprocess.Popen:
    """A ``sleep`` whose process name is ``name`` (a copy of the program under that name)."""
    program = tmp_path / name
    if not program.exists():
        shutil.copy(shutil.which("sleep") or "/bin/sleep", program)
    return _started(subprocess.Popen(["nice", "-n", str(nice), str(program), "60"]), name)


def _can_raise(child: subprocess.Popen) -> bool:
    try:
        os.sched_setscheduler(child.pid, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
        os.sched_setscheduler(child.pid, os.SCHED_OTHER, os.sched_param(0))
        return True
    except PermissionError:
        return False


_RENAMED = """
import sys
def name(n):
    with open("/proc/self/comm", "w") as f:
        f.write(n)
name(sys.argv[1])
print("named", flush=True)
for line in sys.stdin:
    name(line.strip())
    print("named", flush=True)
"""


def _rename(child: subprocess.Popen, name: str) -> None:
    child.stdin.write(name + "\n")
    child.stdin.flush()
    assert child.stdout.readline() == "named\n"


def test_a_worker_seen_while_it_runs_work_is_still_given_back(tmp_path):
    """The kernel names a worker that runs work at the moment with ``+`` where an idle one
    has ``-`` (``kworker/u8:1+events_unbound``). A rescan that sees it so keeps it on record,
    and the stop gives it back under either name (it was left at SCHED_FIFO for good)."""
    child = subprocess.Popen(["nice", "-n", "4", sys.executable, "-c", _RENAMED,
                              "imnkw/u1:0-idle"], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline() == "named\n"
        boost = KernelWorkerBoost(match=lambda pid, comm: comm.startswith("imnkw/u"),
                                  ledger=WorkerLedger(tmp_path / "ledger.json")).start()
        try:
            if boost.refused is not None:
                pytest.skip("this system refuses real-time priority (the refusal is tested "
                            "above)")
            assert _policy(child.pid)[:2] == (os.SCHED_FIFO, FIFO_PRIORITY)
            _rename(child, "imnkw/u1:0+busy")
            boost.boost_once()
            assert boost.status()["threads"] == 1
        finally:
            boost.stop()
        assert _policy(child.pid) == (os.SCHED_OTHER, 0, 4)
        # raised while it runs work, given back while it runs work again
        boost = KernelWorkerBoost(match=lambda pid, comm: comm.startswith("imnkw/u"),
                                  ledger=WorkerLedger(tmp_path / "ledger.json")).start()
        try:
            _rename(child, "imnkw/u1:0-idle")
            boost.boost_once()
            _rename(child, "imnkw/u1:0+busy")
        finally:
            boost.stop()
        assert _policy(child.pid) == (os.SCHED_OTHER, 0, 4)
    finally:
        child.kill()
        child.wait()


def test_a_worker_that_appears_later_is_raised_and_a_real_time_one_left_alone(tmp_path):
    """The keeper's own rescan (every 0.05 s here) finds a worker started after it."""
    rt = _named_sleeper(tmp_path, "imnkw-late")
    try:
        try:
            os.sched_setscheduler(rt.pid, os.SCHED_FIFO, os.sched_param(2))
        except PermissionError:
            pytest.skip("this system refuses real-time priority (the refusal is tested above)")
        keeper = KernelWorkerKeeper(prefix="imnkw-late", every_s=0.05,
                                    ledger=tmp_path / "ledger.json").start()
        late = None
        try:
            assert keeper.status()["threads"] == 0  # the real-time one is not taken over
            late = _named_sleeper(tmp_path, "imnkw-late", nice=3)
            assert wait_until(lambda: os.sched_getscheduler(late.pid) == os.SCHED_FIFO)
            assert wait_until(lambda: keeper.status()["threads"] == 1)
        finally:
            keeper.stop()
            assert _policy(rt.pid)[:2] == (os.SCHED_FIFO, 2)  # never changed, never "restored"
            if late is not None:
                assert _policy(late.pid) == (os.SCHED_OTHER, 0, 3)
                late.kill()
                late.wait()
    finally:
        rt.kill()
        rt.wait()


def test_shared_workers_are_given_back_only_when_the_last_holder_stops(tmp_path):
    child = _named_sleeper(tmp_path, "imnkw-shared", nice=5)
    try:
        if not _can_raise(child):
            pytest.skip("this system refuses real-time priority (the refusal is tested above)")
        wait_until(lambda: os.getpriority(os.PRIO_PROCESS, child.pid) == 5)
        ledger = tmp_path / "ledger.json"
        keeper = KernelWorkerKeeper(prefix="imnkw-shared", every_s=0.1, ledger=ledger).start()
        try:
            assert keeper.status()["threads"] == 1 and keeper.status()["refused"] is None
            assert _policy(child.pid)[:2] == (os.SCHED_FIFO, FIFO_PRIORITY)
            here = KernelWorkerBoost(match=_only(child), ledger=WorkerLedger(ledger)).start()
            assert here.status() == {"policy": f"SCHED_FIFO {FIFO_PRIORITY}", "threads": 1,
                                     "holders": 2, "refused": None}
        finally:
            keeper.stop()
        assert _policy(child.pid)[:2] == (os.SCHED_FIFO, FIFO_PRIORITY)  # still held here
        here.stop()
        assert _policy(child.pid) == (os.SCHED_OTHER, 0, 5)
        assert json.loads(ledger.read_text()) == {"holders": [], "changed": {}}
    finally:
        child.kill()
        child.wait()


def test_a_holder_that_died_without_stopping_is_dropped(tmp_path):
    child = _sleeper(nice=5)
    gone = subprocess.Popen(["true"])
    gone.wait()
    try:
        if not _can_raise(child):
            pytest.skip("this system refuses real-time priority (the refusal is tested above)")
        wait_until(lambda: os.getpriority(os.PRIO_PROCESS, child.pid) == 5)
        # what a holder killed with SIGKILL leaves: itself listed, the worker it raised
        os.sched_setscheduler(child.pid, os.SCHED_FIFO, os.sched_param(FIFO_PRIORITY))
        ledger = tmp_path / "ledger.json"
        ledger.write_text(json.dumps({"holders": [[gone.pid, 12345]],
                                      "changed": {str(child.pid): ["sleep", os.SCHED_OTHER, 5]}}))
        boost = KernelWorkerBoost(match=_only(child), ledger=WorkerLedger(ledger)).start()
        assert boost.status()["holders"] == 1 and boost.status()["threads"] == 1  # dropped
        assert json.loads(ledger.read_text())["holders"] == [[os.getpid(),
                                                              process_start(os.getpid())]]
        boost.stop()
        assert _policy(child.pid) == (os.SCHED_OTHER, 0, 5)
    finally:
        child.kill()
        child.wait()


def test_an_unreadable_ledger_is_started_afresh_and_a_link_refused(tmp_path):
    ledger = tmp_path / "ledger.json"
    ledger.write_text("{not json")
    with WorkerLedger(ledger).locked() as state:
        assert state == {"holders": [], "changed": {}}
    assert json.loads(ledger.read_text()) == {"holders": [], "changed": {}}
    link = tmp_path / "link.json"
    link.symlink_to(tmp_path / "elsewhere.json")
    boost = KernelWorkerBoost(match=lambda pid, comm: False, ledger=WorkerLedger(link))
    boost.start()
    boost.stop()
    assert boost.status()["refused"].startswith(f"ledger {link}: ")
    assert not (tmp_path / "elsewhere.json").exists()


_PARENT = """
import json, sys, time
from pathlib import Path
from imunoise.live.kernel_workers import KernelWorkerKeeper
keeper = KernelWorkerKeeper(prefix=sys.argv[1], every_s=0.1, ledger=Path(sys.argv[2])).start()
print(keeper.pid, json.dumps(keeper.status()), flush=True)
if sys.argv[3] == "exit":
    sys.exit(0)  # without keeper.stop()
time.sleep(60)
"""


@pytest.mark.parametrize("end", ["kill", "exit"])
def test_the_keeper_gives_the_workers_back_when_its_parent_ends_without_stopping_it(
        tmp_path, end):
    child = _named_sleeper(tmp_path, "imnkw-orphan", nice=5)
    try:
        if not _can_raise(child):
            pytest.skip("this system refuses real-time priority (the refusal is tested above)")
        wait_until(lambda: os.getpriority(os.PRIO_PROCESS, child.pid) == 5)
        parent = subprocess.Popen([sys.executable, "-c", _PARENT, "imnkw-orphan",
                                   str(tmp_path / "ledger.json"), end], cwd=REPO,
                                  stdout=subprocess.PIPE, text=True)
        try:
            keeper_pid, status = parent.stdout.readline().split(" ", 1)
            assert json.loads(status)["threads"] == 1
            if end == "exit":
                assert parent.wait(timeout=30) == 0  # not held up by the keeper
        finally:
            parent.kill()
            parent.wait()
        assert wait_until(lambda: _policy(child.pid) == (os.SCHED_OTHER, 0, 5), timeout=10)
        assert wait_until(lambda: process_start(int(keeper_pid)) is None, timeout=10)
    finally:
        child.kill()
        child.wait()


@pytest.mark.parametrize("argv, raised", [
    (["--device", "sim:adis16350"], True),
    (["--device", "adis16350", "--serial", "/dev/ttyUSB0"], True),
    (["--device", "sim:adis16350", "--priority", "nice"], False),
    (["--device", "sim:adis16350", "--no-realtime-kernel-workers"], False),
    (["--device", "sim:razor"], False),
    (["--device", "sim:razor", "--realtime-kernel-workers"], True),
])
def test_serve_raises_the_workers_by_default_only_for_a_serial_device_at_realtime(argv, raised):
    args = build_parser().parse_args(["serve", *argv])
    assert raise_kernel_workers(args, args.device) is raised


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


def _serve(tmp_path: Path, *options: str) -> tuple[subprocess.Popen, dict, set[int]]:
    """``serve`` on the simulated ADIS16350 with ``options``: the process, its /health
    ``kernel_workers`` once samples arrive, and the unbound workers then at SCHED_FIFO 1."""
    port = free_port()
    proc = subprocess.Popen([sys.executable, "-m", "imunoise", "serve", "--device",
                             "sim:adis16350", "--port", str(port), "--out", str(tmp_path),
                             *options],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    health: dict = {}
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
        assert workers is not None and workers["policy"] == f"SCHED_FIFO {FIFO_PRIORITY}"
        visible = [pid for pid, comm in processes() if is_unbound_worker(pid, comm)]
        raised: set[int] = set()
        if workers["refused"] is None and not visible:
            assert workers["threads"] == 0  # in a container that does not show them
        elif workers["refused"] is None:
            raised = {pid for pid in visible if _at_fifo_1(pid)}
            assert raised and workers["threads"] > 0
    except BaseException:
        proc.kill()
        proc.communicate(timeout=60)
        raise
    return proc, workers, raised


def test_serve_reports_the_workers_in_health_and_restores_them_when_it_ends(tmp_path):
    proc, _, raised = _serve(tmp_path, "--priority", "normal", "--realtime-kernel-workers")
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    assert proc.returncode == 0
    assert not [pid for pid in raised if _at_fifo_1(pid)]  # ended workers count as given back


def test_serve_raises_the_workers_by_default_and_gives_them_back_when_killed(tmp_path):
    proc, workers, raised = _serve(tmp_path)
    proc.kill()  # SIGKILL: serve cannot give anything back itself
    _, err = proc.communicate(timeout=60)
    if raised:
        assert f"imunoise: {workers['threads']} kernel worker threads at SCHED_FIFO 1" in err
    assert wait_until(lambda: not [pid for pid in raised if _at_fifo_1(pid)], timeout=10)
