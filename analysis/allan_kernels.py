"""Compiled one-pass kernels for the overlapping Allan-family sums (numba), with a switch.

Each kernel reads the phase once per averaging factor m: the squared differences of a block
of ``_BLOCK`` (1,024) start indices go to a small buffer that stays in the L1 cache, are summed
pairwise there, and each block total is added to a Neumaier-compensated running sum. The
error is then that of a pairwise sum of 1,024 terms (at most about ten roundings), whatever
the record length, and the result agrees with the numpy path to about 1e-15 relative.
Nearby averaging factors share one sweep over the phase (``groups``), so long records are
read from memory fewer times. The modified Allan sums rest on prefix sums carried in
double-double arithmetic (``running_sum_split``), and the lag-1 noise identification reads
each decimated series once (``diff_products``). ``fastmath`` stays off: no reassociation or
contraction beyond what is written here; every loop is elementwise, so the compiler still
emits SIMD code.

The kernels themselves are in :mod:`imunoise.analysis.allan_compiled`, imported (with numba)
on first use. ``enabled(kind, points)`` says whether they are used on a phase of that length:
numba must import, the kernels must compile (on first use, per kind; ``cache=True`` keeps the
machine code on disk, so only the first run after an install pays the compile time, some
seconds per kind), and the switch must allow it. By default it is automatic: the kernels serve
phases of at least :data:`COMPILED_MIN_POINTS` points, and shorter ones go the numpy way,
which is then faster than loading them. ``set_enabled(True)`` or ``IMUNOISE_ALLAN_KERNEL=numba``
uses them at every length, ``set_enabled(False)`` or ``IMUNOISE_ALLAN_KERNEL=numpy`` never.
"""

from __future__ import annotations

import os
import sys
import time
from typing import Any

import numpy as np

#: Kinds with compiled kernels (``adev`` needs none: it reads only every m-th point).
KERNEL_KINDS = ("oadev", "ohdev", "mdev", "noise_id")

COMPILED_MIN_POINTS = 1 << 21
"""Shortest phase (points) for which the automatic switch uses the compiled kernels. Loading
them (the numba import and the on-disk machine code) costs about 0.6 s per process, while on
an octave grid they save 20-40 ms per curve at 1e6 points (numpy 30-80 ms); a command that
fits a 1e6-sample record computes a few such curves and is faster without them."""

_KERNELS = ("groups", "oadev_sums", "ohdev_sums", "oadev_sum", "ohdev_sum", "mdev_sum",
            "running_sum_split", "diff_products")


def _switch_of(env: str) -> bool | str:
    value = env.strip().lower()
    if value == "numpy":
        return False
    if value in ("numba", "compiled"):
        return True
    return "auto"


# switch (True, False or "auto": by length); per kind: compiled (absent: not tried yet), why
# not, and first-use time in s
_state: dict = {
    "switch": _switch_of(os.environ.get("IMUNOISE_ALLAN_KERNEL", "")),
    "compiled": {},
    "error": {},
    "compile_s": {},
}


def _compiled_module() -> Any:
    from imunoise.analysis import allan_compiled

    return allan_compiled


def __getattr__(name: str) -> Any:
    # the kernels live in allan_compiled, imported (with numba) on first use
    if name in _KERNELS:
        return getattr(_compiled_module(), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _warm_up(kind: str) -> None:
    k = sys.modules[__name__]  # module attributes, so that a replaced kernel is the one run
    u = np.linspace(0.0, 1.0, 64)
    ms = np.array([1, 3], dtype=np.int64)
    if kind == "oadev":
        k.oadev_sum(u, 3, 0, u.size - 6)
        k.oadev_sums(u, ms, u.size - 2 * ms)
    elif kind == "ohdev":
        k.ohdev_sum(u, 3, 0, u.size - 9)
        k.ohdev_sums(u, ms, u.size - 3 * ms)
    elif kind == "mdev":
        hi, lo = k.running_sum_split(u, 0.5)
        k.mdev_sum(hi, lo, 3)
    else:
        k.diff_products(u)
        k.diff_products(u[::3])


def _numba_error() -> str:
    try:  # numba is a declared dependency; the numpy path covers an environment without it
        return str(_compiled_module().NUMBA_ERROR)
    except Exception as exc:  # noqa: BLE001 - numba fails to import in many ways; numpy then
        return f"numba unavailable: {exc}"


def _compile(kind: str) -> None:
    """Compile (or load from the on-disk cache) the kernels of one kind; record the time."""
    t0 = time.perf_counter()
    error = _numba_error()
    if error:
        _state["compiled"][kind] = False
        _state["error"][kind] = error
        _state["compile_s"][kind] = time.perf_counter() - t0
        return
    try:
        _warm_up(kind)
    except Exception as exc:  # noqa: BLE001 - any numba/LLVM failure: numpy instead, say why
        _state["compiled"][kind] = False
        _state["error"][kind] = f"compiled {kind} kernels failed: {type(exc).__name__}: {exc}"
    else:
        _state["compiled"][kind] = True
    _state["compile_s"][kind] = time.perf_counter() - t0


def enabled(kind: str = "oadev", points: int | None = None) -> bool:
    """True when the compiled kernels of ``kind`` (``"oadev"``, ``"ohdev"``, ``"mdev"``, whose
    kernels include the double-double running sums, or ``"noise_id"``, the one-pass products
    of the lag-1 noise identification) are to be used on a phase of ``points`` points: they
    work and the switch is on, or it is automatic (the default) and ``points`` is None or at
    least :data:`COMPILED_MIN_POINTS`. The first such call compiles them (or loads them from
    the cache); below the length they are not even imported."""
    switch = _state["switch"]
    if switch is False or kind not in KERNEL_KINDS:
        return False
    if switch == "auto" and points is not None and points < COMPILED_MIN_POINTS:
        return False
    if kind not in _state["compiled"]:
        _compile(kind)
    return bool(_state["compiled"][kind])


def set_enabled(flag: bool | str) -> bool | str:
    """Switch the compiled kernels on (True: at every length), off (False) or to ``"auto"``
    (by length, the default) for this process; returns the previous setting."""
    if flag not in (True, False, "auto"):
        raise ValueError(f"the kernel switch is True, False or 'auto', not {flag!r}")
    previous = _state["switch"]
    _state["switch"] = flag
    return previous


def status(kind: str = "oadev") -> dict[str, object]:
    """``enabled``, ``error`` (why not, if not) and ``compile_s`` (first-use compile or cache
    load time, s) of the compiled kernels of ``kind``."""
    on = enabled(kind)
    error = _state["error"].get(kind, "")
    return {"enabled": on, "error": error, "compile_s": float(_state["compile_s"].get(kind, 0.0))}
