"""Replay benchmark: an 8 h, 100 Hz, 6-axis recording (2.88 M Imu messages) read three ways.

    python bench/replay.py [--hours 8] [--rate 100] [--reuse] [--memory-hours 2,8,32]

Writes the file once with the recorder (1 s chunks, as a live recording has), then times in the
same run:
  (a) ``imunoise analyze FILE --json`` from file to JSON (a separate process; its peak RSS),
  (b) the ``mcap`` library's own reader merely iterating the messages (a separate process),
  (c) the bulk reader alone (``imunoise.daq.readers.open_record``) in this process: messages per
  second.
Targets: (a) <= half of (b), peak memory of (a) under 400 MB, (c) >= 3 million messages/s.
With ``--memory-hours``, (a)'s peak memory is also measured for recordings of those lengths
(written once each, kept in ``bench/out/memory``), as users run it and with ``--stream
always`` / ``never``, to show how it grows with the length (target: flat).
If ``analyze`` is not available, (a) is reported as missing and the bulk load in a separate
process (``open_record`` to arrays) is timed in its place.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imunoise.core.blocks import SampleBlock  # noqa: E402
from imunoise.daq.readers import open_record  # noqa: E402
from imunoise.daq.recorder import McapRecorder  # noqa: E402

OUT = ROOT / "bench" / "out"
GYRO_LSB = 0.07326 * np.pi / 180
ACCEL_LSB = 2.522e-3 * 9.80665


def write_recording(hours: float, rate: float, out: Path = OUT) -> Path:
    """Quantized white noise plus a slow random walk, written as a live recorder would."""
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("bench_*.mcap"):
        old.unlink()
    rng = np.random.default_rng(42)
    n_total = int(round(hours * 3600 * rate))
    block = int(rate)  # one second per block, as a live acquisition hands them over
    t0 = 1.7e9
    rec = McapRecorder(out, "bench", threaded=False, fsync=False, rotate_s=None,
                       rate_hz=rate, reserve_bytes=0)
    walk = np.zeros(6)
    names = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
    for k in range(0, n_total, block):
        n = min(block, n_total - k)
        t = t0 + (k + np.arange(n)) / rate
        ch, raw = {}, {}
        for i, name in enumerate(names):
            lsb = GYRO_LSB if i < 3 else ACCEL_LSB
            drift = walk[i] + np.cumsum(rng.normal(0, 0.02, n))
            walk[i] = drift[-1]
            counts = np.rint(rng.normal(0, 8, n) + drift).astype(np.int64)
            raw[name] = counts
            ch[name] = counts * lsb
        rec.write(SampleBlock("/bench/imu", t, ch, rate, raw=raw))
        ts = t[:: int(rate)]
        rec.write(SampleBlock("/bench/temperature", ts,
                              {"temp": 25.0 + 0.001 * np.arange(len(ts))}, 1.0))
    rec.close()
    (path,) = out.glob("bench_*.mcap")
    return path


def memory_by_length(hours_list: list[float], rate: float) -> None:
    """Peak memory of ``imunoise analyze FILE --json`` for recordings of each length: as users
    run it (``--stream auto``: loaded below about 9 h, streamed above), always streamed, and
    always loaded (what it was before streaming existed)."""
    modes = ("auto", "always", "never")
    rows = []
    print(f"    {'hours':>5}  " + "  ".join(f"{'--stream ' + m:>22}" for m in modes))
    for hours in hours_list:
        folder = OUT / "memory" / f"{hours:g}h_{rate:g}hz"
        existing = sorted(folder.glob("bench_*.mcap"))
        path = existing[0] if existing else write_recording(hours, rate, folder)
        cells, peaks = [], []
        for mode in modes:
            wall, rss, code, _cpu = run_child([sys.executable, "-m", "imunoise", "analyze",
                                               str(path), "--json", "--stream", mode])
            peaks.append(rss)
            cells.append(f"{rss:6.0f} MB {wall:6.1f} s" + ("" if code == 0 else f" (exit {code})"))
        rows.append((hours, peaks))
        print(f"    {hours:5g}  " + "  ".join(f"{c:>22}" for c in cells))
    if len(rows) >= 2:
        (h0, m0), (h1, m1) = rows[0], rows[-1]
        growth = "  ".join(f"{m:>9}: {(b - a) / (h1 - h0):5.1f} MB/h"
                           for m, a, b in zip(modes, m0, m1, strict=True))
        print(f"    growth per hour of {rate:g} Hz, six channels: {growth}")


def run_child(argv: list[str], stdout_path: Path | None = None
              ) -> tuple[float, float, int, float]:
    """Wall time (s), peak RSS (MB), exit code and CPU time (user + system, s) of a child
    process. On a shared, loaded machine the CPU time is the steadier figure."""
    out = open(stdout_path, "wb") if stdout_path else subprocess.DEVNULL
    t = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.PIPE, cwd=ROOT,
                            env=dict(os.environ, PYTHONPATH=str(ROOT)))
    _pid, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    err = proc.stderr.read().decode(errors="replace").strip()
    if stdout_path:
        out.close()
    if proc.returncode != 0 and err:
        print(f"  ({' '.join(argv[-3:])}: exit {proc.returncode}: {err.splitlines()[-1]})")
    return wall, usage.ru_maxrss / 1024.0, proc.returncode, usage.ru_utime + usage.ru_stime


MCAP_ITERATE = """
import sys
from mcap.reader import make_reader
n = 0
with open(sys.argv[1], "rb") as f:
    for _ in make_reader(f).iter_messages(log_time_order=False):
        n += 1
print(n)
"""

BULK_LOAD = """
import sys
from imunoise.daq.readers import open_record
r = open_record(sys.argv[1])
print(sum(s.n_samples for s in r.channels.values()))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--hours", type=float, default=8.0)
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--reuse", action="store_true", help="reuse bench/out/bench_*.mcap")
    ap.add_argument("--memory-hours", default="", metavar="H1,H2,...",
                    help="also measure analyze's peak memory at these lengths, e.g. 2,8,32")
    args = ap.parse_args()
    existing = sorted(OUT.glob("bench_*.mcap"))
    if args.reuse and existing:
        path = existing[0]
    else:
        t = time.perf_counter()
        path = write_recording(args.hours, args.rate)
        print(f"wrote {path.name}: {path.stat().st_size / 1e6:.1f} MB in "
              f"{time.perf_counter() - t:.1f} s")
    n_imu = int(round(args.hours * 3600 * args.rate))

    print(f"load average before: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores")
    reads, cpus = [], []
    for _ in range(5):
        t, c = time.perf_counter(), time.process_time()
        r = open_record(path)
        reads.append(time.perf_counter() - t)
        cpus.append(time.process_time() - c)
        assert r.channels["gyro_x"].n_samples == n_imu, r.channels["gyro_x"].n_samples
        del r
    t_read, t_cpu = float(np.median(reads)), float(np.median(cpus))
    rate_read = n_imu / t_read
    print(f"(c) bulk reader, in process: {t_read:.2f} s wall ({t_cpu:.2f} s CPU), median of 5 "
          f"-> {rate_read / 1e6:.2f} M Imu messages/s wall, {n_imu / t_cpu / 1e6:.2f} M/s "
          "per CPU second (target >= 3.0)")
    print(f"    best of 5: {n_imu / min(reads) / 1e6:.2f} M/s wall, "
          f"{n_imu / min(cpus) / 1e6:.2f} M/s per CPU second")

    t_mcap, rss_mcap, _, cpu_mcap = run_child([sys.executable, "-c", MCAP_ITERATE, str(path)])
    print(f"(b) mcap make_reader().iter_messages(), no decoding: {t_mcap:.2f} s wall "
          f"({cpu_mcap:.2f} s CPU, peak {rss_mcap:.0f} MB)")

    json_out = OUT / "analyze.json"
    t_an, rss_an, code, cpu_an = run_child([sys.executable, "-m", "imunoise", "analyze",
                                            str(path), "--json"], json_out)
    if code == 0:
        label = "(a) imunoise analyze FILE --json"
    else:
        label = "(a') analyze unavailable; bulk load to arrays in a separate process"
        t_an, rss_an, code, cpu_an = run_child([sys.executable, "-c", BULK_LOAD, str(path)])
    ratio = t_an / t_mcap
    print(f"{label}: {t_an:.2f} s wall ({cpu_an:.2f} s CPU), peak {rss_an:.0f} MB "
          f"-> {ratio:.3f} of (b) wall, {cpu_an / cpu_mcap:.3f} in CPU (target <= 0.5), "
          "memory target < 400 MB")
    if args.memory_hours:
        print("analyze peak memory by record length:")
        memory_by_length([float(h) for h in args.memory_hours.split(",")], args.rate)
    print(f"load average after: {os.getloadavg()[0]:.1f}")
    ok = ratio <= 0.5 and rss_an < 400 and rate_read >= 3e6
    print("all targets met" if ok else "TARGET MISSED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
