"""Run the live service on a paced synthetic IMU in its own process (for the load test).

Usage: ``python tests/serve_synthetic.py PORT RATE_HZ``. Prints ``ready`` when listening; on
SIGTERM or SIGINT stops, then prints one JSON line with the final counts.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from pathlib import Path

import uvicorn

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from imunoise.live.scheduler import RollingAnalyzer
from imunoise.live.service import LiveService
from imunoise.web.app import create_app
from tests.live_helpers import CountingSink, SyntheticImu


def main() -> None:
    port, rate = int(sys.argv[1]), float(sys.argv[2])
    source = SyntheticImu(fs_hz=rate, block=max(1, int(rate / 20)), pace=True, seed=11)
    sink = CountingSink()
    # as ``imunoise serve``: fits and diagnoses in a worker process
    service = LiveService(source, RollingAnalyzer(workers="process"), sinks=[sink],
                          realtime=True).start()
    server = uvicorn.Server(uvicorn.Config(create_app(service), host="127.0.0.1", port=port,
                                           log_level="warning", timeout_graceful_shutdown=1))

    def announce() -> None:
        while not server.started:
            time.sleep(0.02)
        print("ready", flush=True)

    threading.Thread(target=announce, daemon=True).start()
    # uvicorn re-raises the stop signal after its shutdown: handle it so the counts get printed.
    signal.signal(signal.SIGTERM, lambda *_: None)
    signal.signal(signal.SIGINT, lambda *_: None)
    server.run()
    service.stop()
    print(json.dumps({"source_samples": source.stats.samples, "sink_samples": sink.samples,
                      "sink_closed": sink.closed, "received": service.samples_received,
                      "analysed": service.samples_analysed,
                      "not_analysed": service.samples_not_analysed,
                      "max_late_s": source.stats.max_late_s}), flush=True)


if __name__ == "__main__":
    main()
