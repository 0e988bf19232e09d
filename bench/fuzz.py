"""Damaged-file fuzzing: thousands of mutants of small seed recordings in every format.

Run from the repository root:

    python bench/fuzz.py                    # 200 mutants per format, 12 formats: 2400
    python bench/fuzz.py --per-format 20    # a quick look

Seeds and mutations come from ``tests/fuzzing.py`` (the test suite runs a few hundred of the
same). Each mutant is run in a process forked from this one (the imports and compiled kernels
are warmed up once, here), two at once (``--jobs``): ``analyze --channel gyro_x --json`` and
``fit`` on every mutant; streamed ``analyze``, ``replay``, ``diagnose`` and ``export-kalibr``
in turn; ``repair`` on every MCAP mutant, its output read by the official ``mcap`` reader
(CRC validation) and by rosbags. A case that
does not finish within ``--timeout`` seconds is killed and counted as a hang; a process's
address space is limited to ``--memory-mb``.

Printed: mutants per format, wall time, and the counts of tracebacks (an exit other than 0 or
2, or an exception), hangs, unreadable repaired files, exit-2 messages that are not one line
under 300 characters, Python warnings, invalid JSON; then the slowest case and the largest
memory. The first failures are written to ``--log``. Exit status 1 when any count is not 0.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import resource
import shutil
import signal
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests import fuzzing as fz


def _child(case: fz.Case, out: Path, memory_mb: int) -> None:
    """Run the case's commands; write what happened as JSON lines to ``out``."""
    limit = memory_mb << 20
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    results = []
    for argv in fz.commands_for(case, case.path.parent, full=True):
        o = fz.run_cli(argv)
        unreadable = None
        if argv[0] == "repair" and o.code == 0:
            unreadable = fz.check_repaired(Path(argv[-1]))
        results.append({"command": argv[0], "code": o.code, "seconds": o.seconds,
                        "problems": o.problems(), "unreadable": unreadable,
                        "stderr": o.stderr[:300]})
    out.write_text(json.dumps(results))


class _Running:
    """One case's forked process."""

    def __init__(self, case: fz.Case, memory_mb: int) -> None:
        self.case = case
        self.out = case.path.parent / (case.path.name + ".outcome.json")
        self.start = time.perf_counter()
        pid = os.fork()
        if pid == 0:  # the child: never returns
            code = 0
            try:
                devnull = os.open(os.devnull, os.O_WRONLY)
                os.dup2(devnull, 1)
                os.dup2(devnull, 2)
                _child(case, self.out, memory_mb)
            except BaseException:  # noqa: BLE001 - reported by the missing outcome
                code = 3
            os._exit(code)
        self.pid = pid

    def poll(self, timeout: float) -> dict | None:
        """The outcome once the process ended (or was killed after ``timeout`` s), else None."""
        done, status, rusage = os.wait4(self.pid, os.WNOHANG)
        seconds = time.perf_counter() - self.start
        if not done:
            if seconds < timeout:
                return None
            os.kill(self.pid, signal.SIGKILL)
            os.wait4(self.pid, 0)
            return {"hang": True, "seconds": seconds, "rss_mb": 0.0}
        rss_mb = rusage.ru_maxrss / 1024
        if not self.out.exists():
            return {"crash": f"child ended with status {status} and no outcome",
                    "seconds": seconds, "rss_mb": rss_mb}
        return {"results": json.loads(self.out.read_text()), "seconds": seconds,
                "rss_mb": rss_mb}


def _warm_up(folder: Path) -> None:
    """Import and compile everything once, before forking."""
    seeds = fz.write_seeds(folder)
    for k in range(4):
        case = fz.Case("mcap-zstd", "none", seeds["mcap-zstd"], index=k)
        for argv in fz.commands_for(case, folder, full=True):
            fz.run_cli(argv)
    fz.check_repaired(folder / "mcap-zstd" / "repaired.mcap")


def _tally(case: fz.Case, got: dict, counts: collections.Counter, failures: list[str]) -> None:
    label = f"{case.fmt} [{case.mutation}] {case.path}"
    if got.get("hang"):
        counts["hangs"] += 1
        failures.append(f"HANG {label}")
        return
    if got.get("crash"):
        counts["tracebacks"] += 1
        failures.append(f"CRASH {label}: {got['crash']}")
        return
    for r in got["results"]:
        counts[f"runs of {r['command']}"] += 1
        counts[f"{r['command']} exit {r['code']}"] += 1
        for p in r["problems"]:
            kind = ("tracebacks" if p.startswith("exit") else
                    "long or multi-line messages" if p.startswith("message") else
                    "python warnings" if p.startswith("warnings") else "invalid JSON")
            counts[kind] += 1
            failures.append(f"{kind.upper()} {label} {r['command']}: {p[-1500:]}")
        if r["unreadable"]:
            counts["unreadable repaired files"] += 1
            failures.append(f"UNREADABLE {label}: {r['unreadable']}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-format", type=int, default=200, help="mutants per format")
    ap.add_argument("--seed", type=int, default=1, help="mutation seed")
    ap.add_argument("--timeout", type=float, default=60.0, help="seconds per case")
    ap.add_argument("--memory-mb", type=int, default=3072, help="address space per case")
    ap.add_argument("--jobs", type=int, default=2, help="cases run at once")
    ap.add_argument("--formats", default=",".join(fz.FORMATS))
    ap.add_argument("--log", help="where failures are written (default: in the temp folder)",
                    default=str(Path(tempfile.gettempdir()) / "imunoise-fuzz-failures.txt"))
    args = ap.parse_args()
    formats = tuple(f for f in args.formats.split(",") if f)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from imunoise.daq.readers import mcap_decode

    mcap_decode.READ_AHEAD = False  # no second thread in a process that forks
    work = Path(tempfile.mkdtemp(prefix="imunoise-fuzz-"))
    counts = collections.Counter()
    per_format = collections.Counter()
    failures: list[str] = []
    slowest = (0.0, "")
    rss = (0.0, "")
    start = time.perf_counter()
    try:
        _warm_up(work / "warm")
        cases = enumerate(fz.iter_cases(work, args.per_format, args.seed, formats))
        running: list[_Running] = []
        finished = 0
        while True:
            while len(running) < args.jobs:
                item = next(cases, None)
                if item is None:
                    break
                per_format[item[1].fmt] += 1
                running.append(_Running(item[1], args.memory_mb))
            if not running:
                break
            for r in list(running):
                got = r.poll(args.timeout)
                if got is None:
                    continue
                running.remove(r)
                before = len(failures)
                _tally(r.case, got, counts, failures)
                label = f"{r.case.fmt} [{r.case.mutation}]"
                slowest = max(slowest, (got["seconds"], label))
                rss = max(rss, (got["rss_mb"], label))
                if r.case.folder is not None and len(failures) == before:
                    shutil.rmtree(r.case.folder, ignore_errors=True)
                finished += 1
                if finished % 100 == 0:
                    print(f"  {finished} mutants, {time.perf_counter() - start:.0f} s",
                          flush=True)
            time.sleep(0.005)
    finally:
        if not failures:
            shutil.rmtree(work, ignore_errors=True)
    wall = time.perf_counter() - start
    total = sum(per_format.values())
    print(f"\n{total} mutants in {wall:.0f} s wall ({wall / max(total, 1):.2f} s each)")
    print("per format: " + ", ".join(f"{f} {n}" for f, n in per_format.items()))
    for key in ("tracebacks", "hangs", "unreadable repaired files",
                "long or multi-line messages", "python warnings", "invalid JSON"):
        print(f"{key:28s} {counts[key]}")
    runs = sorted(k for k in counts if k.startswith("runs of") or " exit " in k)
    print("command exits: " + ", ".join(f"{k} {counts[k]}" for k in runs))
    print(f"slowest case {slowest[0]:.2f} s: {slowest[1]}")
    print(f"largest memory {rss[0]:.0f} MB (peak RSS of a case's process): {rss[1]}")
    if failures:
        Path(args.log).write_text("\n\n".join(failures[:200]) + "\n")
        print(f"{len(failures)} failure(s); the first 200 in {args.log}; mutants kept in {work}")
    bad = sum(counts[k] for k in ("tracebacks", "hangs", "unreadable repaired files",
                                  "long or multi-line messages", "python warnings",
                                  "invalid JSON"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
