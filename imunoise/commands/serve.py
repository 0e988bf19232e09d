"""``imunoise serve``: acquire (or replay), record and analyse live; API and dashboard over HTTP.

A device is read in a process of its own at the highest priority granted and recorded by a
child of that process (``--acquisition thread``: a thread of this one); neither waits on the
analysis or on HTTP, and refits run at a bounded cadence in a worker process. Ctrl-C stops
acquisition, finishes the file being written and exits.
"""

from __future__ import annotations

import argparse
import ipaddress
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from imunoise import SOFTWARE
from imunoise.errors import RuntimeFailure, UsageError
from imunoise.live.recorder_sink import RecorderSink

TOKEN_ENV = "IMUNOISE_TOKEN"
DEVICES = ("adis16350", "itg3200", "adxl345", "razor", "sim:adis16350", "sim:razor")
SERIAL_DEVICES = ("adis16350",)
I2C_DEVICES = ("itg3200", "adxl345", "razor")
_LOOPBACK_NAMES = {"localhost"}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="live analyzer + API + dashboard", description=__doc__)
    src = p.add_mutually_exclusive_group()
    src.add_argument("--device", metavar="DEV", action="append",
                     help=f"device to acquire ({', '.join(DEVICES)}); default sim:adis16350; "
                          "repeat it to acquire several at once (one file, a topic per device, "
                          "channels named TOPIC:gyro_x)")
    src.add_argument("--replay", metavar="FILE", help="feed a recording instead of a device")
    p.add_argument("--serial", dest="serial_port", metavar="P", action="append",
                   help="serial port of the SPI bridge (ADIS16350), e.g. /dev/ttyUSB0; with "
                        "several devices one per real adis16350, in order")
    p.add_argument("--bus", type=int, metavar="N", action="append",
                   help="I2C bus number (ITG-3200, ADXL345), e.g. 1 for /dev/i2c-1; with "
                        "several devices one per real I2C device, in order")
    p.add_argument("--bench", metavar="NAME",
                   help="put the simulated devices on one simulated bench whose motion they "
                        "all see: lab or sway (docs/devices.md); default: none")
    p.add_argument("--rate", type=float, metavar="HZ",
                   help="sampling rate in Hz (default: the device's, 102.4 Hz for the "
                        "ADIS16350, 100 Hz for the others)")
    p.add_argument("--seed", type=int, help="simulator random seed (default 0)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind (default 127.0.0.1; any other needs a token)")
    p.add_argument("--port", type=int, default=8000, help="HTTP port (default 8000)")
    p.add_argument("--out", metavar="DIR", help="record MCAP files here (default: no recording)")
    p.add_argument("--catalog", metavar="DIR",
                   help="fleet catalogue (imunoise fleet --catalog DIR) shown at /fleet")
    p.add_argument("--token", help=f"token required by changing requests (or ${TOKEN_ENV})")
    p.add_argument("--target", metavar="P=X%",
                   help="wanted 95 %% half-widths, e.g. K=20%%,B=10%%: /coefficients and the "
                        "dashboard then show how much longer to record for each")
    p.add_argument("--model", default="white,bias_instability,random_walk", metavar="TERMS",
                   help="initial model, comma-separated terms; TERM:P=VALUE holds a "
                        "parameter (SI units), e.g. white,gauss_markov:T=100 "
                        "(default white,bias_instability,random_walk)")
    p.add_argument("--refit-interval", type=float, default=2.0, metavar="S",
                   help="least time between refits, s (default 2)")
    p.add_argument("--acquisition", choices=("process", "thread"), default="process",
                   help="where a device is read and recorded: 'process' (default), a process of "
                        "its own at the highest priority the system grants, handing blocks to "
                        "the analysis through shared memory; 'thread', inside this process")
    p.add_argument("--priority", choices=("realtime", "nice", "normal"), default="realtime",
                   help="scheduling of the acquisition process: 'realtime' (default: "
                        "SCHED_FIFO where permitted, else nice -10 where permitted; /health "
                        "says what was granted), 'nice' or 'normal'")
    p.add_argument("--realtime-kernel-workers", action=argparse.BooleanOptionalAction,
                   default=None,
                   help="while serving, also run the kernel's unbound worker threads, which "
                        "carry a serial adapter's bytes to the acquisition process, at "
                        "SCHED_FIFO 1, and give them back when serve ends (needs the right to "
                        "set real-time priority; /health says what was granted). Default: on "
                        "for the ADIS16350 with --priority realtime and --acquisition process, "
                        "off otherwise; see docs/service.md")
    p.add_argument("--analysis-cpu", type=float, default=0.3, metavar="F",
                   help="fraction of one core the fits and diagnoses may use on average; "
                        "their cadence adapts to it (default 0.3)")
    p.set_defaults(func=run)


def is_loopback(host: str) -> bool:
    """True for 127.0.0.0/8, ::1 and ``localhost``."""
    if host in _LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_security(host: str, token: str | None) -> None:
    """Binding beyond loopback requires a token (changes then require it)."""
    if not is_loopback(host) and not token:
        raise UsageError(f"serve: binding {host} exposes the API beyond this machine; give "
                         f"--token T or set {TOKEN_ENV}")


def open_source(args: argparse.Namespace) -> tuple[Any, dict[str, Any], bool]:
    """The block source, its description for /health, and whether it is a live device."""
    if args.replay and getattr(args, "realtime_kernel_workers", None):
        raise UsageError("serve: --realtime-kernel-workers applies to a device, not to --replay")
    if args.replay:
        return _open_replay(args)
    specs = _device_list(args)
    for spec in specs:
        if spec not in DEVICES:
            raise UsageError(f"serve: unknown device {spec!r}; valid: {', '.join(DEVICES)}")
    bench = _bench_of(args)
    if len(specs) > 1:
        return _open_group(args, specs, bench)
    spec = specs[0]
    from imunoise.daq.devices import open_device
    from imunoise.daq.errors import DeviceError

    kwargs = _single_kwargs(args, spec, bench)
    if getattr(args, "acquisition", "thread") == "process":
        return _open_process(args, spec, kwargs)
    if getattr(args, "realtime_kernel_workers", None):
        raise UsageError("serve: --realtime-kernel-workers needs --acquisition process")
    from imunoise.analysis.noise_stream import stream_factory

    try:  # noise: the simulators' seed-paper models, not white noise alone
        acq = open_device(spec, noise=stream_factory, **kwargs)
    except ValueError as exc:
        raise UsageError(f"serve: {str(exc).replace('--port', '--serial')}") from None
    try:
        acq.open()  # fail now, with the reason, rather than in the acquisition thread
    except (DeviceError, OSError) as exc:
        acq.close()
        raise RuntimeFailure(f"serve: cannot open {spec}: {exc}") from None
    info: dict[str, Any] = {"spec": spec, **{k: v for k, v in kwargs.items()
                                             if k not in ("seed", "noise", "bench")}}
    if "bench" in kwargs:
        info["bench"] = kwargs["bench"].bench.name
    info["config"] = {str(k): str(v) for k, v in (getattr(acq, "config", {}) or {}).items()}
    return acq, info, True


def raise_kernel_workers(args: argparse.Namespace, spec: str | list[str] | None) -> bool:
    """Whether serve holds the kernel's unbound workers at real-time priority: as asked, else
    for a serial device read at real-time priority, whose bytes those workers carry (serve
    then already changes the machine's scheduling for its acquisition process). ``spec``: the
    device, or the devices read at once (any serial one counts)."""
    asked = getattr(args, "realtime_kernel_workers", None)
    if asked is not None:
        return bool(asked)
    specs = [spec] if isinstance(spec, str) else list(spec or ["sim:adis16350"])
    return (any(s.removeprefix("sim:") in SERIAL_DEVICES for s in specs)
            and getattr(args, "priority", "realtime") == "realtime")


def _start_acquisition(args: argparse.Namespace, config: Any) -> Any:
    """The recording folder made and an acquisition process (``AcquisitionConfig``) opened,
    or the one-line ``RuntimeFailure`` that says why not."""
    from imunoise.daq.errors import DeviceError
    from imunoise.live.acquisition_process import AcquisitionProcess

    if args.out:
        try:
            Path(args.out).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RuntimeFailure(f"serve: cannot record to {args.out}: {exc}") from None
    source = AcquisitionProcess(config)
    try:
        source.open()
    except DeviceError as exc:
        raise RuntimeFailure(f"serve: {exc}") from None
    return source


def _open_process(args: argparse.Namespace, spec: str, kwargs: dict[str, Any]
                  ) -> tuple[Any, dict[str, Any], bool]:
    """The device read and recorded by an acquisition process
    (``imunoise.live.acquisition_process``)."""
    from imunoise.live.acquisition_process import AcquisitionConfig

    config = AcquisitionConfig(spec, dict(kwargs), out=args.out, record_rate_hz=args.rate,
                               software=SOFTWARE, priority=getattr(args, "priority", "realtime"),
                               realtime_kernel_workers=raise_kernel_workers(args, spec))
    source = _start_acquisition(args, config)
    workers = source.kernel_workers
    if workers and workers.get("threads"):
        print(f"imunoise: {workers['threads']} kernel worker threads at {workers['policy']} "
              f"while serving (they carry the serial port's bytes; "
              f"--no-realtime-kernel-workers leaves them as they are)", file=sys.stderr)
    info: dict[str, Any] = {"spec": spec, "acquisition": "process",
                            **{k: v for k, v in kwargs.items() if k not in ("seed", "bench")}}
    if "bench" in kwargs:
        info["bench"] = kwargs["bench"].bench.name
    info["config"] = source.config_reported
    return source, info, True


def _open_replay(args: argparse.Namespace) -> tuple[Any, dict[str, Any], bool]:
    """A recording fed as if live."""
    path = Path(args.replay)
    if not path.exists():
        raise UsageError(f"serve: no such file: {path}")
    from imunoise.daq.readers import ReadError
    from imunoise.daq.replay import open_blocks

    try:
        blocks, total = open_blocks(path)
    except ReadError as exc:
        raise UsageError(f"serve: {exc}") from None
    speed = getattr(args, "speed", None)  # set by ``imunoise replay --serve``
    if speed is not None:
        from imunoise.daq.replay import paced

        blocks = paced(blocks, speed)
    return blocks, {"spec": f"replay:{path.name}", "samples_in_file": total}, False


def _single_kwargs(args: argparse.Namespace, spec: str, bench: Any) -> dict[str, Any]:
    """``open_device`` keyword arguments of a single device (the last --serial or --bus
    given, as before several devices were possible)."""
    kwargs: dict[str, Any] = {}
    base = spec.removeprefix("sim:")
    serial = args.serial_port[-1] if args.serial_port else None
    bus = args.bus[-1] if args.bus else None
    wanted = (("port", serial if base in SERIAL_DEVICES else None),
              ("bus", bus if base in I2C_DEVICES else None),
              ("rate_hz", args.rate), ("seed", args.seed))
    for key, value in wanted:
        if value is not None:
            kwargs[key] = value
    if bench is not None and spec.startswith("sim:"):
        import time

        from imunoise.daq.sim.bench import BenchPlacement

        kwargs["bench"] = BenchPlacement(bench, 0, seed=args.seed or 0, epoch=time.monotonic())
    return kwargs


def _device_list(args: argparse.Namespace) -> list[str]:
    devices = args.device
    if isinstance(devices, str):  # a namespace made by another command (replay --serve)
        devices = [devices]
    return list(devices or ["sim:adis16350"])


def _bench_of(args: argparse.Namespace) -> Any:
    name = getattr(args, "bench", None)
    if not name:
        return None
    from imunoise.daq.sim.bench import bench_named

    try:
        return bench_named(name)
    except ValueError as exc:
        raise UsageError(f"serve: --bench: {exc}") from None


def _open_group(args: argparse.Namespace, specs: list[str], bench: Any
                ) -> tuple[Any, dict[str, Any], bool]:
    """Several devices at once: in the acquisition process (a DeviceGroup there, one file), or
    with ``--acquisition thread`` a DeviceGroup in this process."""
    import time

    from imunoise.daq.device_group import member_seed, pair_devices
    from imunoise.daq.errors import DeviceError
    from imunoise.daq.sim.bench import BenchPlacement

    try:
        members = pair_devices(specs, args.serial_port or (), args.bus or (),
                               port_option="--serial")
    except ValueError as exc:
        raise UsageError(f"serve: {exc}") from None
    described = [{"name": m.name, "spec": m.spec,
                  **({"port": m.port} if m.port else {}),
                  **({"bus": m.bus} if m.bus is not None else {})} for m in members]
    info: dict[str, Any] = {"spec": "+".join(specs), "devices": described}
    if bench is not None:
        info["bench"] = bench.name
    if getattr(args, "acquisition", "thread") != "process":
        if getattr(args, "realtime_kernel_workers", None):
            raise UsageError("serve: --realtime-kernel-workers needs --acquisition process")
        from imunoise.analysis.noise_stream import stream_factory
        from imunoise.daq.devices import open_devices

        group = open_devices(specs, ports=args.serial_port or (), buses=args.bus or (),
                             rate_hz=args.rate, seed=args.seed, bench=bench,
                             noise=stream_factory, port_option="--serial")
        try:
            group.open()
        except (DeviceError, OSError) as exc:
            group.close()
            raise RuntimeFailure(f"serve: cannot open {info['spec']}: {exc}") from None
        info["config"] = group.config
        return group, info, True
    from imunoise.live.acquisition_process import AcquisitionConfig

    epoch = time.monotonic()
    config_members = []
    for m in members:
        kw: dict[str, Any] = {"seed": member_seed(args.seed, m.position)}
        for key, value in (("port", m.port), ("bus", m.bus), ("rate_hz", args.rate)):
            if value is not None:
                kw[key] = value
        if bench is not None and m.simulated:
            kw["bench"] = BenchPlacement(bench, m.position, seed=args.seed or 0, epoch=epoch)
        config_members.append((m.spec, m.name, kw))
    config = AcquisitionConfig(
        info["spec"], {}, out=args.out, record_rate_hz=None, software=SOFTWARE,
        priority=getattr(args, "priority", "realtime"),
        realtime_kernel_workers=raise_kernel_workers(args, specs),
        members=config_members)
    source = _start_acquisition(args, config)
    info["acquisition"] = "process"
    info["config"] = source.config_reported
    return source, info, True


def open_recorder(out: str, device: str, config: dict[str, str] | None,
                  rate_hz: float | None) -> Any:
    from imunoise.daq.recorder import McapRecorder

    try:
        return McapRecorder(out, device, config=config, rate_hz=rate_hz, software=SOFTWARE)
    except OSError as exc:
        raise RuntimeFailure(f"serve: cannot record to {out}: {exc}") from None


def open_group_recorder(out: str, group: Any) -> Any:
    """One recorder for every device of a group (``--acquisition thread``)."""
    from imunoise.daq.recorder import McapRecorder

    devices = {name: {"spec": spec, "config": group.member_config(name),
                      "rate_hz": acq.rate_hz}
               for (name, acq), spec in zip(group.members, group.specs, strict=True)}
    try:
        return McapRecorder(out, "+".join(group.names), software=SOFTWARE, devices=devices)
    except OSError as exc:
        raise RuntimeFailure(f"serve: cannot record to {out}: {exc}") from None


def _make_server(config: Any, stop_streams: threading.Event,
                 stop_acquisition: Any = None) -> Any:
    """A uvicorn server that, as soon as a stop is asked for (Ctrl-C, SIGTERM), ends the
    recording first and the live event streams, so that the file is closed before the HTTP
    side winds down and an open dashboard's connection closes instead of timing out."""
    import uvicorn

    class _Server(uvicorn.Server):
        def handle_exit(self, sig: int, frame: object) -> None:
            if stop_acquisition is not None:
                stop_acquisition()
            stop_streams.set()
            super().handle_exit(sig, frame)

    return _Server(config)


def run(args: argparse.Namespace) -> int:
    import uvicorn

    from imunoise.analysis.channel_state import check_terms
    from imunoise.live.scheduler import RollingAnalyzer
    from imunoise.live.service import LiveService
    from imunoise.web.app import LOOPBACK_HOSTS, create_app

    token = args.token or os.environ.get(TOKEN_ENV) or None
    check_security(args.host, token)
    if not 0 < args.port < 65536:
        raise UsageError(f"serve: bad port {args.port}")
    try:
        from imunoise.analysis.terms import parse_model
        model = [e.text() for e in parse_model(args.model).entries]
        check_terms(model)
    except ValueError as exc:
        raise UsageError(f"serve: {exc}") from None
    if args.refit_interval <= 0:
        raise UsageError("serve: --refit-interval must be positive")
    if not 0 < args.analysis_cpu <= 1:
        raise UsageError(f"serve: --analysis-cpu must be in (0, 1], got {args.analysis_cpu:g}")

    source, info, realtime = open_source(args)
    sinks = []
    recorder = None
    in_process = hasattr(source, "recording")  # an acquisition process records by itself
    if args.out and realtime and not in_process:
        try:
            recorder = (open_group_recorder(args.out, source) if info.get("devices")
                        else open_recorder(args.out, info["spec"], info.get("config"),
                                           args.rate))
        except RuntimeFailure:
            source.close()
            raise
        if info.get("devices"):
            from imunoise.live.recorder_sink import GroupRecorderSink

            sinks.append(GroupRecorderSink(recorder, source))
        else:
            sinks.append(RecorderSink(recorder, source))
    service = LiveService(
        source, RollingAnalyzer(model=model, refit_interval_s=args.refit_interval,
                                cpu_budget=args.analysis_cpu, workers="process",
                                targets=args.target, qualified=bool(info.get("devices"))),
        sinks=sinks,
        device=info, realtime=realtime,
        current_file=((lambda: recorder.stats.file or None) if recorder else
                      (lambda: source.recording().get("file") or None) if in_process and args.out
                      else None))
    app = create_app(service, token=token, catalog=args.catalog,
                     allowed_hosts=LOOPBACK_HOSTS if is_loopback(args.host) else None)
    config = uvicorn.Config(app, host=args.host, port=args.port, log_level="warning",
                            timeout_graceful_shutdown=2, lifespan="on")
    server = _make_server(config, app.state.stop_streams, service.stop_acquisition)
    service.start()
    url_host = f"[{args.host}]" if ":" in args.host else args.host
    print(f"imunoise: serving {info['spec']} on http://{url_host}:{args.port}/ "
          f"(API docs at /docs); Ctrl-C stops", file=sys.stderr, flush=True)
    stopping = threading.Event()

    def _terminate(signum: int, frame: object) -> None:  # SIGTERM from docker stop
        stopping.set()
        service.stop_acquisition()
        server.should_exit = True

    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)
    try:
        server.run()
    except KeyboardInterrupt:
        pass
    finally:
        service.stop()
        if recorder is not None and getattr(recorder, "error", None):
            print(f"imunoise: recording: {recorder.error}", file=sys.stderr)
        files = getattr(getattr(recorder, "stats", None), "files", None) or (
            source.recording().get("files") if in_process else None)
        if files:
            print(f"imunoise: recorded {', '.join(map(str, files))}", file=sys.stderr)
    if not server.started:
        raise RuntimeFailure(f"serve: could not listen on {args.host}:{args.port}")
    return 0
