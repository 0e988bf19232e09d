"""Serve benchmark: does ``imunoise serve`` lose samples under dashboard and API load?

    python bench/serve.py [--minutes 10] [--runs adis204,razor100,razor1000] [--load idle,busy]
                          [--[no-]realtime-kernel-workers]

For each simulated device configuration and each load, starts ``imunoise serve --device ...
--out DIR`` (acquisition in its own process, the default), and while it runs keeps
  * a dashboard open: the event stream ``/events``, and on each update (at most once a second)
    the requests the page makes: ``/allan``, ``/psd``, ``/model``, ``/diagnosis`` of a channel
    and ``/coefficients``;
  * 50 API clients, each fetching ``/coefficients``, ``/allan`` or ``/psd`` every 0.2 s;
  * with ``busy``, two CPU-bound processes beside it (on a 2-core machine: both cores).
Beside serve runs the platform's floor: a bare loop at the acquisition process's priority
that wakes once per device period and does nothing else (``floor_main``); the samples a
polled part would lose to its late wake-ups alone are what no acquisition code on this
machine, at that moment, can avoid. Then stops serve with SIGTERM and reads the recording
back. Prints per run: samples expected (from the recording's first and last stamps at the
device rate), recorded, lost at each stage (missing in the file: lost at the device, or by the
recorder's ring, which ``/health`` counts under ``recording``; hand-over and analysis: from
``/health``; for the ADIS16350 also the simulator process's own count of samples it made that
were never read, the truth against which the driver's estimate from the host clock is
checked), and the CPU used by each process (serve's HTTP/analysis side, the acquisition
process, the recorder process, the ADIS16350's simulator process, the fit worker, the
clients, the hogs) as a percentage of one core, and on a virtual machine the CPU time the
host took from it during the run (steal), which no priority inside the machine can prevent.
Serve holds the kernel's tty workers, which the ADIS16350's bytes pass through, at real-time
priority by default for that device where it may (``live/kernel_workers.py``);
``--no-realtime-kernel-workers`` runs it without, ``--realtime-kernel-workers`` with them for
every device.

Configurations: ``adis204`` is the ADIS16350 at 204.8 Hz (the highest rate a Bus Pirate link
carries, docs/devices.md); ``razorN`` the ITG-3200 + ADXL345 on one simulated 400 kHz bus with
the gyro at N Hz and the accelerometer at its nearest rate. ``razor1000`` is the highest gyro
rate the shared bus carries (1 kHz gyro + 800 Hz accelerometer fill about 60 % of it; the next
gyro rate, 1142.9 Hz, brings the accelerometer to 1600 Hz and fills it; see
tests/daq/test_acquisition.py).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imunoise.daq.readers.mcap import read_mcap  # noqa: E402

CONFIGS = {
    "adis204": ("sim:adis16350", 204.8),
    "adis102": ("sim:adis16350", 102.4),
}
CLIENTS = 50
CLIENT_PERIOD_S = 0.2
_HOG = ("import os\nparent = os.getppid()\nwhile os.getppid() == parent:\n"
        "    for _ in range(1_000_000):\n        pass\n")
"""A CPU-bound process that ends once the benchmark is gone, however it ended."""


def config_of(name: str) -> tuple[str, float]:
    if name in CONFIGS:
        return CONFIGS[name]
    if name.startswith("razor"):
        return "sim:razor", float(name.removeprefix("razor"))
    raise SystemExit(f"unknown run {name!r}: adis204, adis102 or razorN (N in Hz)")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get(url: str, timeout: float = 10.0) -> bytes | None:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as r:
            return r.read()
    except OSError:
        return None


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (s), 0 when it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def stolen_seconds() -> float | None:
    """CPU time the hypervisor gave to others while this machine's CPUs wanted to run (s,
    summed over CPUs; the ``steal`` column of /proc/stat), None where there is none.

    A virtual CPU taken away for a few milliseconds stalls whatever runs on it, real-time
    priority or not: a sample a polled part makes in that time is lost to any software.
    """
    try:
        fields = Path("/proc/stat").read_text().split("\n", 1)[0].split()
        return int(fields[8]) / os.sysconf("SC_CLK_TCK")
    except (OSError, IndexError, ValueError):
        return None


def children(pid: int) -> list[int]:
    out = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        try:
            out += [int(x) for x in (task / "children").read_text().split()]
        except OSError:
            pass
    return out


def floor_main(rate_hz: float, seconds: float) -> None:
    """The platform's own floor, measured beside serve: a bare loop at the acquisition
    process's priority that wakes once per device period and does nothing else. Prints (JSON)
    how often it woke later than a data-ready poll may be (``1 - RETRY_FRACTION`` of a
    period: the polls sit up to a tenth of a period after each appearance), and how many
    samples a part without FIFO would have lost to those late wake-ups alone."""
    from imunoise.daq.poll_schedule import RETRY_FRACTION
    from imunoise.live.acquisition_process import raise_priority

    policy = raise_priority("realtime")["policy"]
    period = 1.0 / rate_hz
    slack = (1.0 - RETRY_FRACTION) * period
    t0 = time.monotonic()
    n = int(seconds * rate_hz)
    late_wakes = lost = 0
    worst = 0.0
    k = 0
    while k < n:
        k += 1
        due = t0 + k * period
        wait = due - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        late = time.monotonic() - due
        worst = max(worst, late)
        if late > slack:
            late_wakes += 1
            missed = int((late - slack) // period) + 1
            lost += missed
            k += missed  # the periods slept through are gone, as a polled part's samples are
    print(json.dumps({"policy": policy, "periods": n, "late_wakes": late_wakes,
                      "lost": lost, "worst_late_s": worst}))


def client_main(base: str, channel: str, n: int, period: float, stop_after: float) -> None:
    """The load: ``n`` API client threads and one dashboard, until ``stop_after`` seconds."""
    end = time.monotonic() + stop_after
    paths = ["/coefficients", f"/allan?channel={channel}", f"/psd?channel={channel}"]

    def api(i: int) -> None:
        k = i
        while time.monotonic() < end:
            get(base + paths[k % len(paths)])
            k += 1
            time.sleep(period)

    def dashboard() -> None:
        q = f"?channel={channel}"
        last = 0.0
        while time.monotonic() < end:
            try:
                with urllib.request.urlopen(base + "/events", timeout=30) as stream:
                    for line in stream:
                        if time.monotonic() >= end:
                            return
                        if line.startswith(b"event:") or line.startswith(b"data:"):
                            if time.monotonic() - last >= 1.0:
                                last = time.monotonic()
                                for p in (f"/allan{q}", f"/psd{q}", "/coefficients",
                                          f"/model{q}", f"/diagnosis{q}"):
                                    get(base + p)
            except OSError:
                time.sleep(0.5)

    threads = [threading.Thread(target=api, args=(i,), daemon=True) for i in range(n)]
    threads.append(threading.Thread(target=dashboard, daemon=True))
    for t in threads:
        t.start()
    while time.monotonic() < end:
        time.sleep(0.5)


def recorded(out: Path) -> dict[str, dict[str, float]]:
    """Per IMU stream of the recording: samples, missing samples, expected samples."""
    rows: dict[str, dict[str, float]] = {}
    for path in sorted(out.glob("*.mcap")):
        rec = read_mcap(path)
        for topic, facts in rec.facts.get("timing", {}).items():
            key = next((k for k in rec.channels if k.startswith(topic + ":")),
                       None) or next(iter(rec.channels))
            n = rec.channels[key].n_samples
            row = rows.setdefault(topic, {"recorded": 0, "missing": 0, "fs_hz": facts["fs_hz"]})
            row["recorded"] += n
            row["missing"] += facts["missing_samples"]
    for row in rows.values():
        row["expected"] = row["recorded"] + row["missing"]
    return rows


def run_one(name: str, load: str, seconds: float, serve_args: tuple[str, ...] = ()) -> dict:
    spec, rate = config_of(name)
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    out = Path(tempfile.mkdtemp(prefix=f"bench_serve_{name}_"))
    hogs = [subprocess.Popen([sys.executable, "-c", _HOG]) for _ in range(2 if load == "busy"
                                                                          else 0)]
    serve = subprocess.Popen([sys.executable, "-m", "imunoise", "serve", "--device", spec,
                              "--rate", f"{rate:g}", "--port", str(port), "--out", str(out),
                              *serve_args],
                             cwd=ROOT, stderr=subprocess.PIPE, text=True,
                             env=dict(os.environ, PYTHONPATH=str(ROOT)))
    client = floor = None
    try:
        health = None
        for _ in range(240):
            raw = get(base + "/health", timeout=5)
            if raw:
                health = json.loads(raw)
                if health.get("channels"):
                    break
            time.sleep(0.5)
        if not health or not health.get("channels"):
            raise SystemExit(f"{name}: serve did not come up: {serve.stderr.read()[-2000:]}")
        acq_pid = (health.get("acquisition_process") or {}).get("pid")
        channel = health["channels"][0]
        code = (f"import sys; sys.path.insert(0, {str(ROOT)!r}); import bench.serve as b; "
                f"b.client_main({base!r}, {channel!r}, {CLIENTS}, {CLIENT_PERIOD_S!r}, "
                f"{seconds!r})")
        client = subprocess.Popen([sys.executable, "-c", code], cwd=ROOT)
        floor = subprocess.Popen(
            [sys.executable, "-c", f"import sys; sys.path.insert(0, {str(ROOT)!r}); "
             f"import bench.serve as b; b.floor_main({rate!r}, {seconds!r})"],
            cwd=ROOT, stdout=subprocess.PIPE, text=True)
        rec_pid = (health.get("recording") or {}).get("pid")
        sim_pid = ((health.get("acquisition_process") or {}).get("simulator") or {}).get("pid")
        procs = {"serve": serve.pid, "acquisition": acq_pid, "recorder": rec_pid,
                 "simulator": sim_pid, "clients": client.pid}
        workers = [p for p in children(serve.pid) if p != acq_pid]
        cpu0 = {k: cpu_seconds(p) for k, p in procs.items() if p}
        steal0 = stolen_seconds()
        hog0 = [cpu_seconds(h.pid) for h in hogs]
        t0 = time.monotonic()
        time.sleep(seconds)
        wall = time.monotonic() - t0
        workers = [p for p in children(serve.pid) if p != acq_pid] or workers
        cpu = {k: (cpu_seconds(p) - cpu0.get(k, 0.0)) / wall for k, p in procs.items() if p}
        cpu["fit_worker"] = sum(cpu_seconds(p) for p in workers) / wall
        cpu["hogs"] = sum(cpu_seconds(h.pid) - c for h, c in zip(hogs, hog0, strict=True)) / wall
        steal1 = stolen_seconds()
        stolen = None if steal0 is None or steal1 is None else steal1 - steal0
        health = json.loads(get(base + "/health") or b"{}")
        client.wait(60)
        try:
            platform = json.loads(floor.communicate(timeout=60)[0] or "{}")
        except (subprocess.TimeoutExpired, ValueError):
            floor.kill()
            platform = {}
        serve.send_signal(signal.SIGTERM)
        serve.wait(120)
    finally:
        for p in [*hogs, client, floor]:
            if p is not None and p.poll() is None:
                p.kill()
        if serve.poll() is None:  # stopped early: serve closes its file and gives back
            serve.send_signal(signal.SIGTERM)  # the kernel workers it raised
            try:
                serve.wait(60)
            except subprocess.TimeoutExpired:
                serve.kill()
    streams = recorded(out)
    return {"run": name, "load": load, "seconds": wall, "streams": streams,
            "losses": health.get("losses", {}), "process": health.get("acquisition_process"),
            "cpu": cpu, "serve_exit": serve.returncode, "out": str(out), "rate_hz": rate,
            "platform": platform, "stolen_s": stolen}


def report(r: dict) -> None:
    pr = r["process"] or {}
    prio = (pr.get("priority") or {})
    print(f"{r['run']:>10} {r['load']:>5}  {r['seconds']:5.0f} s  exit {r['serve_exit']}  "
          f"acquisition priority {prio.get('policy')}"
          + (f" (refused: {prio['refused']})" if prio.get("refused") else ""))
    kw = pr.get("kernel_workers")
    if kw:
        print(f"{'':17}kernel's unbound workers: {kw.get('policy')} for {kw.get('threads')} "
              "threads" + (f" (refused: {kw['refused']})" if kw.get("refused") else ""))
    for topic, s in r["streams"].items():
        print(f"{'':17}{topic:24} expected {s['expected']:9.0f}  recorded {s['recorded']:9.0f}"
              f"  missing in the file {s['missing']:6.0f}")
    lo = r["losses"]
    print(f"{'':17}losses from /health: device {lo.get('device')}, hand-over "
          f"{lo.get('handover')}, analysis {lo.get('analysis')}, recording "
          f"{lo.get('recording')}; restarts {pr.get('restarts')}")
    sim = pr.get("simulator") or {}
    if sim.get("samples_never_read") is not None:
        print(f"{'':17}the simulator's own count at the same /health read: "
              f"{sim['samples_never_read']} samples made and never read")
    pf = r.get("platform") or {}
    if pf:
        print(f"{'':17}platform floor at {r['rate_hz']:g} Hz ({pf['policy']}, same run): a "
              f"bare loop woke too late for a polled part {pf['late_wakes']} times, "
              f"{pf['lost']} samples of {pf['periods']} "
              f"({100 * pf['lost'] / max(pf['periods'], 1):.4f} %), worst "
              f"{1e3 * pf['worst_late_s']:.1f} ms late")
    if r.get("stolen_s") is not None:
        print(f"{'':17}CPU time the host took from this machine's CPUs during the run "
              f"(/proc/stat steal): {r['stolen_s']:.2f} s")
    cpu = r["cpu"]
    print(f"{'':17}CPU (% of a core): " + ", ".join(f"{k} {100 * v:.0f}"
                                                     for k, v in cpu.items()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0,
                    help="length of each run in minutes (default: %(default)s)")
    ap.add_argument("--runs", default="adis204,razor100,razor1000",
                    help="comma-separated devices and rates: adis204 (ADIS16350 at 204.8 Hz), "
                         "razor100, razor1000 (ITG-3200 gyro at 100 or 1000 Hz beside the "
                         "ADXL345) (default: %(default)s)")
    ap.add_argument("--load", default="idle,busy",
                    help="idle (the benchmark's clients only) and/or busy (two CPU-bound "
                         "processes beside) (default: %(default)s)")
    ap.add_argument("--realtime-kernel-workers", action=argparse.BooleanOptionalAction,
                    default=None,
                    help="pass serve --realtime-kernel-workers or --no-realtime-kernel-workers "
                         "(the kernel's unbound workers, which carry the ADIS16350 simulator's "
                         "bytes, at SCHED_FIFO 1; see live/kernel_workers.py); default: "
                         "serve's own default (on for the ADIS16350 where permitted)")
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args()
    # SIGTERM ends the benchmark through its cleanup, as Ctrl-C does
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    serve_args = {None: (), True: ("--realtime-kernel-workers",),
                  False: ("--no-realtime-kernel-workers",)}[args.realtime_kernel_workers]
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    print(f"load average before: {load:.1f} on {os.cpu_count()} cores; {args.minutes:g} min "
          f"per run, {CLIENTS} API clients + a dashboard"
          + (f"; serve {serve_args[0]}" if serve_args else ""))
    results = []
    for load_kind in args.load.split(","):
        for name in args.runs.split(","):
            r = run_one(name, load_kind, 60.0 * args.minutes, serve_args)
            report(r)
            results.append(r)
            sys.stdout.flush()
    lost = sum(s["missing"] for r in results if r["load"] == "idle"
               for s in r["streams"].values())
    # A sample the recorder's ring could not take is missing in the file too (a marked gap).
    lost += sum(int(r["losses"].get("handover", 0) or 0) + int(r["losses"].get("analysis", 0)
                                                               or 0)
                for r in results if r["load"] == "idle")
    if any(r["load"] == "idle" for r in results):
        floor = sum(int((r.get("platform") or {}).get("lost", 0)) for r in results
                    if r["load"] == "idle")
        print(f"idle runs: {lost} samples lost anywhere (target 0); the platform's floor in "
              f"the same runs: {floor}")
    for r in results:
        if r["load"] == "busy":
            exp = sum(s["expected"] for s in r["streams"].values())
            miss = sum(s["missing"] for s in r["streams"].values())
            pf = r.get("platform") or {}
            print(f"busy {r['run']}: recording lost {miss} of {exp:.0f} samples "
                  f"({100 * miss / max(exp, 1):.4f} %, target <= 0.01 %); the platform's "
                  f"floor {pf.get('lost', '?')} of {pf.get('periods', '?')}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))


if __name__ == "__main__":
    main()
