"""SIGTERM ends the service's child processes cleanly: the handler only sets a flag, since a
``multiprocessing`` Event set from a handler that interrupted the Event's own wait never
returns (its wake-up waits for the interrupted waiter)."""

from __future__ import annotations

import os
import signal

from imunoise.live.simulator_process import SimulatorProcess
from imunoise.live.termination import TermFlag
from tests.live_helpers import wait_until


def test_the_flag_is_raised_by_sigterm_and_sigint_is_ignored():
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    try:
        term = TermFlag().install()
        assert not term
        os.kill(os.getpid(), signal.SIGINT)  # ignored: no KeyboardInterrupt
        assert not term
        os.kill(os.getpid(), signal.SIGTERM)
        assert wait_until(lambda: bool(term), timeout=5)
    finally:
        signal.signal(signal.SIGTERM, before[0])
        signal.signal(signal.SIGINT, before[1])


def test_the_simulator_process_ends_on_sigterm():
    sim = SimulatorProcess(102.4, seed=1)
    sim.start()
    try:
        os.kill(sim.pid, signal.SIGTERM)
        assert wait_until(lambda: not sim._proc.is_alive(), timeout=10)
        assert sim._proc.exitcode == 0  # ended by itself, its pseudo-terminal closed
    finally:
        sim.stop()
