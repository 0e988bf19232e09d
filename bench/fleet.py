"""Fleet benchmark: ``imunoise fleet`` over many 3 h, 100 Hz recordings on Dask.

    python bench/fleet.py [--files 100] [--hours 3] [--no-diagnose]

Generates the recordings once (simulated units, written by the recorder; cached in
``bench/out/fleet``), starts a Dask scheduler and workers as separate processes, and measures
in the same run:
  (a) files per second with 1 and with 2 workers, and the parallel efficiency
      (rate with 2 / (2 x rate with 1); target >= 0.8);
  (b) the peak memory of a worker (target < 500 MB) and of the client process, the latter
      with a fifth of the files and with all of them (flat: the client keeps a bounded window
      of tasks and of rows);
  (c) Dask's overhead per task (empty tasks through the same cluster);
and projects the wall time for 100,000 recordings on a 100-worker cluster from (a)-(c).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imunoise.daq.sim.fleet_units import SimUnit, write_recording  # noqa: E402

OUT = ROOT / "bench" / "out" / "fleet"
DASK = Path(sys.executable).parent / "dask"


def recordings(n_files: int, hours: float) -> list[Path]:
    """``n_files`` recordings of ten units (cached)."""
    stamp = OUT / "made.json"
    want = {"files": n_files, "hours": hours}
    if stamp.exists() and json.loads(stamp.read_text()) == want:
        return sorted(OUT.glob("*.mcap"))
    shutil.rmtree(OUT, ignore_errors=True)
    OUT.mkdir(parents=True)
    units = [SimUnit(f"B{i:02d}", n_gyro=3e-4 * (1 + 0.03 * i)) for i in range(10)]
    t = time.perf_counter()
    for k in range(n_files):
        unit = units[k % len(units)]
        write_recording(OUT, unit, 1.7e9 + k * 86400.0, hours * 3600.0, seed=k)
        print(f"\rwriting recordings {k + 1}/{n_files}", end="", file=sys.stderr, flush=True)
    print(f"\rwrote {n_files} recordings in {time.perf_counter() - t:.0f} s", file=sys.stderr)
    stamp.write_text(json.dumps(want))
    return sorted(OUT.glob("*.mcap"))


class Cluster:
    """A Dask scheduler and ``n`` single-threaded workers, each its own process."""

    def __init__(self, n: int, tmp: Path) -> None:
        sched = tmp / f"scheduler-{n}.json"
        self.procs = [subprocess.Popen([str(DASK), "scheduler", "--scheduler-file", str(sched),
                                        "--host", "127.0.0.1", "--port", "0",
                                        "--no-dashboard"], stdout=subprocess.DEVNULL,
                                       stderr=subprocess.DEVNULL, cwd=ROOT)]
        deadline = time.monotonic() + 60
        while not (sched.exists() and "address" in (sched.read_text() or "")):
            if time.monotonic() > deadline:
                raise RuntimeError("scheduler did not start")
            time.sleep(0.1)
        self.address = json.loads(sched.read_text())["address"]
        # as imunoise fleet's own local cluster: no statistical profiler (it grows per task)
        env = dict(os.environ, DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED="False")
        for i in range(n):
            self.procs.append(subprocess.Popen(
                [str(DASK), "worker", self.address, "--nthreads", "1", "--no-dashboard",
                 "--host", "127.0.0.1", "--name", f"w{i}"],
                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT, env=env))
        from distributed import Client

        with Client(self.address, timeout="60s") as c:
            c.wait_for_workers(n, timeout=120)

    def close(self) -> None:
        for p in self.procs:
            p.terminate()
        for p in self.procs:
            try:
                p.wait(20)
            except subprocess.TimeoutExpired:
                p.kill()


def run_fleet(files: list[Path], address: str, catalog: Path, diagnose: bool
              ) -> tuple[float, float, str]:
    """Wall time (s), client peak RSS (MB) and the summary line of one fleet run."""
    shutil.rmtree(catalog, ignore_errors=True)
    argv = [sys.executable, "-m", "imunoise", "fleet", *map(str, files), "--catalog",
            str(catalog), "--scheduler", address] + ([] if diagnose else ["--no-diagnose"])
    t = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, cwd=ROOT)
    _pid, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    err = proc.stderr.read().decode().strip().splitlines() if proc.stderr else []
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError("fleet failed: " + "\n".join(err[-5:]))
    return wall, usage.ru_maxrss / 1024.0, err[-1] if err else ""


def task_overhead(address: str, n: int = 2000) -> float:
    """Seconds per empty task through the scheduler (submit to result)."""
    from distributed import Client

    with Client(address) as c:
        c.gather(c.map(abs, range(50), pure=False))  # warm up
        t = time.perf_counter()
        c.gather(c.map(abs, range(n), pure=False))
        return (time.perf_counter() - t) / n


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--files", type=int, default=100)
    ap.add_argument("--hours", type=float, default=3.0)
    ap.add_argument("--no-diagnose", action="store_true",
                    help="skip the per-channel diagnosis (as imunoise fleet --no-diagnose)")
    args = ap.parse_args()
    files = recordings(args.files, args.hours)
    diagnose = not args.no_diagnose
    print(f"{len(files)} recordings of {args.hours:g} h at 100 Hz, 6 channels; diagnosis "
          f"{'on' if diagnose else 'off'}; load average {os.getloadavg()[0]:.1f} on "
          f"{os.cpu_count()} cores")
    rates, client_mb = {}, {}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        for n in (1, 2):
            cluster = Cluster(n, tmp)
            try:
                wall, rss, line = run_fleet(files, cluster.address, tmp / f"cat{n}", diagnose)
                rates[n] = len(files) / wall
                client_mb[len(files)] = rss
                print(f"(a) {n} worker(s): {wall:.0f} s, {rates[n]:.3f} files/s; {line}")
                if n == 2:
                    few = files[: max(2, len(files) // 5)]
                    _w, rss_few, _ = run_fleet(few, cluster.address, tmp / "few", diagnose)
                    client_mb[len(few)] = rss_few
                    overhead = task_overhead(cluster.address)
            finally:
                cluster.close()
    eff = rates[2] / (2 * rates[1])
    print(f"    parallel efficiency with 2 workers: {eff:.2f} (target >= 0.8)")
    peak = line.rsplit("worker peak memory", 1)[-1].strip() if "peak" in line else "?"
    print(f"(b) worker peak memory: {peak} (target < 500 MB)")
    print("    client peak memory: " + ", ".join(f"{mb:.0f} MB with {k} files"
                                              for k, mb in sorted(client_mb.items())))
    print(f"(c) Dask overhead per task: {overhead * 1e3:.2f} ms")
    per_file = 1.0 / rates[1]
    projected = 100_000 * per_file / (100 * min(1.0, eff)) + 100_000 * overhead
    print(f"projection, 100,000 recordings on 100 workers: {per_file:.1f} s per file per "
          f"worker / (100 x {min(1.0, eff):.2f}) + scheduler {overhead * 1e3:.2f} ms per task "
          f"-> {projected / 3600:.1f} h")
    return 0


if __name__ == "__main__":
    sys.exit(main())
