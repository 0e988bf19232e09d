"""Several devices at once: does recording them together lose what recording each alone does not?

    python bench/multi.py [--minutes 3] [--devices sim:adis16350,sim:razor] [--rate HZ]
                          [--command serve|record] [--bench lab] [--repeats 1] [--json FILE]

For each repeat, runs the command (``imunoise serve --out DIR``, the acquisition in its own
process, or ``imunoise record``, in-process) on each device alone, then on all of them at once
(``--device A --device B``, one file), for ``--minutes`` each, and reads every recording back.
Prints per run and device topic: samples expected (from the topic's first and last stamps at
its rate), recorded, and missing in the file (the gaps the acquisition marked: samples the
device made that were not read); for ``serve`` also the losses /health counted for the device
by stage just before the stop (device, hand-over, analysis, recording) and, for the simulated
ADIS16350, the simulator process's own count of samples it made and nobody read. Ends with
each device's missing samples alone and together, summed over the repeats.

The machine is shared: a run's losses depend on what else runs; interleaving alone and
together runs (``--repeats``) keeps that from favouring one of them.
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
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from imunoise.daq.device_group import topic_names  # noqa: E402
from imunoise.daq.readers.mcap import read_mcap  # noqa: E402


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get_json(url: str) -> dict | None:
    try:
        with urllib.request.urlopen(url, timeout=10) as r:
            return json.loads(r.read())
    except (OSError, ValueError):
        return None


def recorded(out: Path) -> dict[str, dict[str, float]]:
    """Per IMU topic of the recordings in ``out``: recorded, missing and expected samples."""
    rows: dict[str, dict[str, float]] = {}
    for path in sorted(out.glob("*.mcap")):
        rec = read_mcap(path)
        for topic, facts in rec.facts.get("timing", {}).items():
            key = next((k for k in rec.channels if k.startswith(topic + ":")),
                       None) or next(iter(rec.channels))
            row = rows.setdefault(topic, {"recorded": 0, "missing": 0,
                                          "fs_hz": facts["fs_hz"]})
            row["recorded"] += rec.channels[key].n_samples
            row["missing"] += facts["missing_samples"]
    for row in rows.values():
        row["expected"] = row["recorded"] + row["missing"]
    return rows


def run(command: str, specs: list[str], seconds: float, rate: float | None,
        bench: str | None, seed: int) -> dict:
    out = Path(tempfile.mkdtemp(prefix="bench_multi_"))
    args = [sys.executable, "-m", "imunoise", command]
    for spec in specs:
        args += ["--device", spec]
    args += ["--out", str(out), "--seed", str(seed)]
    if rate is not None:
        args += ["--rate", f"{rate:g}"]
    if bench:
        args += ["--bench", bench]
    health = None
    if command == "record":
        args += ["--duration", f"{seconds:g}"]
        proc = subprocess.run(args, cwd=ROOT, capture_output=True, text=True,
                              env=dict(os.environ, PYTHONPATH=str(ROOT)))
        code, err = proc.returncode, proc.stderr
    else:
        port = free_port()
        args += ["--port", str(port)]
        proc = subprocess.Popen(args, cwd=ROOT, stderr=subprocess.PIPE, text=True,
                                env=dict(os.environ, PYTHONPATH=str(ROOT)))
        base = f"http://127.0.0.1:{port}"
        try:
            for _ in range(240):
                h = get_json(base + "/health")
                if h and h.get("samples", {}).get("received"):
                    break
                time.sleep(0.5)
            time.sleep(seconds)
            health = get_json(base + "/health")
        finally:
            proc.send_signal(signal.SIGTERM)
            try:
                _, err = proc.communicate(timeout=120)
            except subprocess.TimeoutExpired:
                proc.kill()
                _, err = proc.communicate()
        code = proc.returncode
    return {"devices": specs, "command": command, "exit": code, "stderr": err[-1500:],
            "streams": recorded(out), "health": health, "out": str(out)}


def per_device(r: dict) -> dict[str, dict]:
    """The run's figures by device (the spec), its topics under its topic name."""
    names = topic_names(r["devices"])
    health = r.get("health") or {}
    by_name = {d["name"]: d for d in health.get("devices") or []}
    out = {}
    for spec, name in zip(r["devices"], names, strict=True):
        topics = {t: s for t, s in r["streams"].items() if t.startswith(f"/{name}/")}
        row: dict = {"name": name, "topics": topics,
                     "missing": sum(s["missing"] for s in topics.values()),
                     "expected": sum(s["expected"] for s in topics.values())}
        if len(r["devices"]) == 1:
            row["losses"] = health.get("losses")
            sim = (health.get("acquisition_process") or {}).get("simulator") or {}
        else:
            row["losses"] = (by_name.get(name) or {}).get("losses")
            sim = ((health.get("acquisition_process") or {}).get("simulator") or {}).get(name) \
                or {}
        row["never_read"] = sim.get("samples_never_read") if sim else None
        out[spec] = row
    return out


def report(r: dict) -> None:
    label = " + ".join(r["devices"])
    print(f"{r['command']} {label}: exit {r['exit']}")
    if r["exit"] not in (0, None):
        print("   " + r["stderr"].strip().replace("\n", "\n   "))
    for spec, d in per_device(r).items():
        for topic, s in d["topics"].items():
            print(f"   {spec:15} {topic:26} expected {s['expected']:8.0f}  recorded "
                  f"{s['recorded']:8.0f}  missing in the file {s['missing']:5.0f}")
        if d.get("losses"):
            lo = d["losses"]
            print(f"   {spec:15} /health losses: device {lo.get('device')}, hand-over "
                  f"{lo.get('handover')}, analysis {lo.get('analysis')}, recording "
                  f"{lo.get('recording')}"
                  + (f"; the simulator's own count: {d['never_read']} never read"
                     if d.get("never_read") is not None else ""))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--minutes", type=float, default=3.0,
                    help="length of each run in minutes (default: %(default)s)")
    ap.add_argument("--devices", default="sim:adis16350,sim:razor",
                    help="comma-separated devices (default: %(default)s)")
    ap.add_argument("--rate", type=float, help="--rate passed to every run")
    ap.add_argument("--command", choices=("serve", "record"), default="serve")
    ap.add_argument("--bench", default="lab", help="simulated bench (default: %(default)s; "
                    "'none' for none)")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    args = ap.parse_args()
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    specs = args.devices.split(",")
    bench = None if args.bench == "none" else args.bench
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    print(f"load average before: {load:.1f} on {os.cpu_count()} cores; {args.command}, "
          f"{args.minutes:g} min per run, {args.repeats} repeat(s)")
    results = []
    for _ in range(args.repeats):
        for group in [[s] for s in specs] + [specs]:
            r = run(args.command, group, 60.0 * args.minutes, args.rate, bench, args.seed)
            report(r)
            results.append(r)
            sys.stdout.flush()
    print("missing samples per device (sum over repeats): alone vs together")
    for spec in specs:
        alone = [per_device(r)[spec] for r in results if r["devices"] == [spec]]
        together = [per_device(r)[spec] for r in results if len(r["devices"]) > 1]
        print(f"   {spec:15} alone {sum(d['missing'] for d in alone):5.0f} of "
              f"{sum(d['expected'] for d in alone):9.0f}   together "
              f"{sum(d['missing'] for d in together):5.0f} of "
              f"{sum(d['expected'] for d in together):9.0f}")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1, default=str))


if __name__ == "__main__":
    main()
