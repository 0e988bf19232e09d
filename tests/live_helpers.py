"""Helpers for the live-service tests: a synthetic block source and a real uvicorn server."""

from __future__ import annotations

import contextlib
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import uvicorn

from imunoise.core.blocks import SampleBlock

GYRO_N = 3e-3      # rad/s/sqrt(Hz)
GYRO_K = 2e-5      # rad/s/sqrt(s)
SINE_A = 1e-2      # rad/s
SINE_F = 2.7       # Hz


@dataclass
class SourceStats:
    state: str = "streaming"
    dropped: int = 0
    gaps: int = 0
    reconnects: int = 0
    samples: int = 0
    max_late_s: float = 0.0  # worst lateness of a paced block against its schedule


@dataclass
class SyntheticImu:
    """Blocks of gyro_x (white + random walk + a 2.7 Hz sinusoid) and gyro_y (white + random walk).

    ``pace``: emit in real time (a live device); otherwise as fast as consumed. ``unplug()``
    stops the flow and reports ``disconnected``; ``replug()`` resumes with a gap before the next
    block, like a device that came back.
    """

    fs_hz: float = 100.0
    block: int = 100
    n_blocks: int | None = None
    pace: bool = False
    seed: int = 7
    stats: SourceStats = field(default_factory=SourceStats)

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._plugged = threading.Event()
        self._plugged.set()
        self._rng = np.random.default_rng(self.seed)
        self._rw = np.zeros(2)
        self._i = 0

    def unplug(self) -> None:
        self._plugged.clear()
        self.stats.state = "disconnected"

    def replug(self) -> None:
        self.stats.state = "streaming"
        self.stats.reconnects += 1
        self._plugged.set()

    def stop(self) -> None:
        self._stop.set()
        self._plugged.set()

    def close(self) -> None:
        self.stop()

    def _make(self, gap: int) -> SampleBlock:
        n, fs = self.block, self.fs_hz
        idx = self._i + np.arange(n)
        t = idx / fs
        steps = self._rng.normal(0.0, GYRO_K / np.sqrt(fs), (2, n))
        rw = self._rw[:, None] + np.cumsum(steps, axis=1)
        self._rw = rw[:, -1]
        white = self._rng.normal(0.0, GYRO_N * np.sqrt(fs), (2, n))
        chans = {"gyro_x": white[0] + rw[0] + SINE_A * np.sin(2 * np.pi * SINE_F * t),
                 "gyro_y": white[1] + rw[1]}
        self._i += n
        return SampleBlock(stream="/sim/imu", t=t, channels=chans, fs_hz=fs, gap_before=gap)

    def __iter__(self) -> Iterator[SampleBlock]:
        t0 = time.monotonic()
        emitted = 0
        gap = 0
        count = 0
        while not self._stop.is_set() and (self.n_blocks is None or count < self.n_blocks):
            if not self._plugged.is_set():
                self._plugged.wait()
                if self._stop.is_set():
                    break
                gap = -1
                self.stats.gaps += 1
                t0, emitted = time.monotonic(), 0
            if self.pace:
                due = t0 + (emitted + self.block) / self.fs_hz
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                late = time.monotonic() - due  # oversleep or a late start, both count
                self.stats.max_late_s = max(self.stats.max_late_s, late)
                if not self._plugged.is_set():
                    continue
            block = self._make(gap)
            gap = 0
            emitted += self.block
            count += 1
            self.stats.samples += self.block
            yield block


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(cond, timeout: float = 10.0, every_s: float = 0.05) -> bool:
    """Whether ``cond()`` became true within ``timeout`` seconds (asked every ``every_s``)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(every_s)
    return bool(cond())


@contextlib.contextmanager
def running_server(app, host: str = "127.0.0.1") -> Iterator[str]:
    """Serve ``app`` with uvicorn on a free loopback port in a thread; yields the base URL."""
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host=host, port=port, log_level="warning",
                                           timeout_graceful_shutdown=1))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started:
        if time.monotonic() > deadline or not thread.is_alive():
            raise RuntimeError("uvicorn did not start")
        time.sleep(0.02)
    try:
        yield f"http://{host}:{port}"
    finally:
        server.should_exit = True
        thread.join(10)


class CountingSink:
    """A sink that counts what it is given (samples, blocks after a gap), like a recorder."""

    def __init__(self) -> None:
        self.samples = 0
        self.gap_blocks = 0
        self.closed = False

    def write(self, block: SampleBlock) -> None:
        self.samples += len(block)
        if block.gap_before != 0:
            self.gap_blocks += 1

    def close(self) -> None:
        self.closed = True


def interrupt(proc: subprocess.Popen, timeout: float = 30.0) -> str:
    """Ctrl-C a command-line process, wait for it (kill it after ``timeout`` s) and return its
    stderr text."""
    proc.send_signal(signal.SIGINT)
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        _, err = proc.communicate()
    return err.decode() if isinstance(err, bytes) else err


def touch_then_sleep(path: str, seconds: float) -> float:
    """A job for a worker process that stands for a long fit: says it started (``path``
    created), then sleeps."""
    with open(path, "w") as f:
        f.write("started")
    time.sleep(seconds)
    return seconds
