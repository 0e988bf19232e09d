"""A simulated ADIS16350 behind its emulated Bus Pirate, in a process of its own.

In one process with the driver, the simulated chip and bridge share the driver's interpreter
and clock: a stall of the driver's process stalls the "hardware" too, and the simulation can
hide (or cause) losses a real device would not. Here the chip model and the emulated bridge
run in their own process on the real clock, behind a pseudo-terminal, and the acquisition
process opens that terminal with the real driver and the real pyserial, exactly as it opens
a Bus Pirate on ``/dev/ttyUSB0``.

The simulated part counts the samples it made that were never read
(:attr:`imunoise.daq.sim.adis16350.Adis16350Sim.samples_never_read`) into shared memory as they
occur:
:attr:`SimulatorProcess.samples_never_read` is the truth against which the driver's own
estimate of the samples lost at the device (from the host's clock) can be checked.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from typing import Any

from imunoise.live.termination import TermFlag, end_process

START_TIMEOUT_S = 60.0


def _simulator_main(rate_hz: float, seed: int, conn: Any, stop: Any, parent_pid: int,
                    priority: str, never_read: Any, bench: Any = None) -> None:
    import sys

    from imunoise.live.process_priority import GIL_SWITCH_S, raise_priority, settle_heap

    term = TermFlag().install()
    sys.setswitchinterval(GIL_SWITCH_S)
    raise_priority(priority)
    from imunoise.analysis.noise_stream import stream_factory
    from imunoise.daq.clock import RealClock
    from imunoise.daq.drivers.adis16350 import sample_rate_hz, smpl_prd_for_rate
    from imunoise.daq.sim.adis16350 import Adis16350Sim
    from imunoise.daq.sim.buspirate_pty import BusPirateEmulator, ChipClock
    from imunoise.daq.sim.signals import default_sources

    fs = sample_rate_hz(smpl_prd_for_rate(rate_hz))
    gyro, accel = default_sources("adis16350", fs, seed, stream_factory)
    chip_clock = ChipClock(RealClock())
    sim = Adis16350Sim(chip_clock, gyro, accel, None, source_rate_hz=fs)
    sim.on_never_read = lambda n: setattr(never_read, "value", n)
    if bench is not None:  # an imunoise.daq.sim.bench.BenchPlacement
        sim.environment = bench.view()
    emulator = BusPirateEmulator(sim, seed=seed, chip_clock=chip_clock).start()
    sim.emulator = emulator
    settle_heap()
    conn.send(emulator.port)
    try:
        while not term and not stop.wait(0.5):
            if os.getppid() != parent_pid:
                break
    finally:
        emulator.close()


class SimulatorProcess:
    """Start and stop the simulated ADIS16350's process; :meth:`start` returns its port.
    ``bench``: a :class:`imunoise.daq.sim.bench.BenchPlacement` the part sits on, or None."""

    def __init__(self, rate_hz: float, seed: int = 0, priority: str = "normal",
                 bench: Any = None) -> None:
        self.rate_hz = float(rate_hz)
        self.seed = int(seed)
        self.bench = bench
        self.priority = priority
        self._ctx = mp.get_context("spawn")
        self._stop = self._ctx.Event()
        self._never_read = self._ctx.RawValue("q", 0)
        self._proc: Any = None

    def start(self, timeout_s: float = START_TIMEOUT_S) -> str:
        """Start the simulator; the path of its serial port."""
        recv, send = self._ctx.Pipe(duplex=False)
        proc = self._ctx.Process(
            target=_simulator_main, name="imunoise-simulator",
            args=(self.rate_hz, self.seed, send, self._stop, os.getpid(), self.priority,
                  self._never_read, self.bench))
        try:
            proc.start()
        finally:
            send.close()
        self._proc = proc  # only a started process: stop() joins it
        if not recv.poll(timeout_s):
            self.stop()
            raise OSError(f"the simulator process did not start within {timeout_s:g} s")
        try:
            return str(recv.recv())
        except EOFError:
            self.stop()
            raise OSError(f"the simulator process ended at start (exit code "
                          f"{self._proc.exitcode})") from None

    @property
    def samples_never_read(self) -> int:
        """Samples the simulated part made and overwrote unread, between two reads of fresh
        data (readable after the process ended, too)."""
        return int(self._never_read.value)

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def stop(self, timeout_s: float = 5.0) -> None:
        end_process(self._proc, self._stop, timeout_s)
