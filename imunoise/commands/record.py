"""``imunoise record``: record a device into crash-safe ROS 2 MCAP files."""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from imunoise import SOFTWARE
from imunoise.commands.common import positive_rate
from imunoise.errors import RuntimeFailure, UsageError
from imunoise.options import parse_duration


def _default_rates() -> str:
    from imunoise.daq.devices import DEFAULT_RATES_HZ

    return ", ".join(f"{name} {hz:g} Hz" for name, hz in DEFAULT_RATES_HZ.items())


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("record", help="record a device to MCAP", description=__doc__ + """

Files are ROS 2 bags (sensor_msgs/msg/Imu on /DEVICE/imu, sensor_msgs/msg/Temperature on
/DEVICE/temperature, gap and status events on /diagnostics), flushed and fsync'ed every second
and rotated hourly, named DEVICE_YYYYmmddTHHMMSSZ.mcap (UTC start time). Ctrl-C stops cleanly.

Several devices (--device A --device B) are recorded at once into one file, a topic per device
(/NAME/imu; a repeated name gets _2, _3); the k-th --port goes to the k-th real adis16350, the
k-th --bus to the k-th real itg3200, adxl345 or razor (docs/devices.md).""",
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--device", required=True, metavar="DEV", action="append",
                   help="adis16350, itg3200, adxl345, razor (ITG-3200 + ADXL345 on one bus), "
                        "or the register-level simulators sim:adis16350, sim:razor; repeat "
                        "it to record several devices at once into one file")
    p.add_argument("--port", metavar="P", action="append",
                   help="serial port of the SPI bridge (adis16350), e.g. /dev/ttyUSB0; no "
                        "default; with several devices one per real adis16350, in order")
    p.add_argument("--bus", type=int, metavar="N", action="append",
                   help="I2C bus number (itg3200, adxl345, razor), e.g. 1 for /dev/i2c-1; "
                        "no default; with several devices one per real I2C device, in order")
    p.add_argument("--rate", type=positive_rate, metavar="HZ",
                   help="sampling rate in Hz; the nearest rate the chip supports is used "
                        f"(default {_default_rates()})")
    p.add_argument("--duration", metavar="D",
                   help="stop after D seconds, or with a unit (90s, 30m, 8h); default: until "
                        "Ctrl-C")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (created if missing)")
    p.add_argument("--rotate", default="1h", metavar="D",
                   help="start a new file after D seconds or 90s, 30m, 8h "
                        "(default 1h; 0 = never)")
    p.add_argument("--seed", type=int, help="random seed of a simulated device (default 0)")
    p.add_argument("--bench", metavar="NAME",
                   help="put the simulated devices on one simulated bench whose motion they "
                        "all see: lab (0.56 Hz sway, floor tilt and vibration, 24.3 Hz hum) "
                        "or sway (a strong sway and hum); default: none (they sit still)")
    p.set_defaults(func=run)


# Driver configuration keys holding SI scale factors per count, and the channels they apply to.
_SCALE_KEYS = {
    "scale_gyro_rad_s_per_lsb": ("gyro_x", "gyro_y", "gyro_z"),
    "scale_accel_m_s2_per_lsb": ("accel_x", "accel_y", "accel_z"),
}


def scales_from_config(config: dict[str, str]) -> dict[str, tuple[float, float]]:
    """Per-channel (scale, offset) from a driver configuration, where it states them."""
    scales: dict[str, tuple[float, float]] = {}
    for key, channels in _SCALE_KEYS.items():
        try:
            scale = float(config[key])
        except (KeyError, ValueError):
            continue
        for ch in channels:
            scales[ch] = (scale, 0.0)
    return scales


def _status_line(rec, acq, t_start: float) -> str:
    stats = getattr(acq, "stats", None)
    dropped = getattr(stats, "dropped", 0) if stats is not None else 0
    state = getattr(stats, "state", "") if stats is not None else ""
    samples = getattr(stats, "samples", rec.stats.samples)
    elapsed = max(time.monotonic() - t_start, 1e-9)
    rate = samples / elapsed
    size = rec.stats.bytes_written / 1e6
    name = Path(rec.stats.file).name if rec.stats.file else "-"
    hms = time.strftime("%H:%M:%S", time.gmtime(elapsed))
    return (f"{hms}  {rate:8.1f} Hz  {samples:>10,d} samples  {dropped} dropped  "
            f"{state}  {name}  {size:.2f} MB")


def _open(args: argparse.Namespace, out: Path, rotate_s: float | None) -> tuple[Any, Any]:
    """The opened device and its recorder; usage errors exit 2, device or disk failures 1."""
    try:
        from imunoise.daq.devices import open_device
    except ImportError as exc:
        raise RuntimeFailure(f"device drivers are not available ({exc})") from exc
    from imunoise.analysis.noise_stream import stream_factory
    from imunoise.daq.errors import DeviceError
    from imunoise.daq.recorder import McapRecorder

    extra: dict[str, Any] = {}
    if getattr(args, "bench_table", None) is not None and args.device.startswith("sim:"):
        from imunoise.daq.sim.bench import BenchPlacement

        extra["bench"] = BenchPlacement(args.bench_table, 0, seed=args.seed or 0,
                                        epoch=time.monotonic())
    try:  # noise: the simulators' seed-paper models, not white noise alone
        acq = open_device(args.device, port=args.port, bus=args.bus, rate_hz=args.rate,
                          seed=args.seed, noise=stream_factory, **extra)
    except (ValueError, KeyError) as exc:
        raise UsageError(f"record: {exc}") from exc
    except (OSError, DeviceError) as exc:
        raise RuntimeFailure(f"record: cannot open {args.device}: {exc}") from exc
    try:
        acq.open()  # the configuration (scales, rate) is known once the device is set up
    except (OSError, DeviceError) as exc:
        acq.close()
        raise RuntimeFailure(f"record: cannot open {args.device}: {exc}") from exc
    config = dict(getattr(acq, "config", {}) or {})
    try:
        rec = McapRecorder(args.out, args.device, config=config, software=SOFTWARE,
                           scales=scales_from_config(config),
                           rate_hz=getattr(acq, "rate_hz", None) or args.rate, rotate_s=rotate_s)
    except OSError as exc:
        acq.close()
        raise RuntimeFailure(f"record: cannot write to {out}: {exc.strerror or exc}") from exc
    return acq, rec


def _copy_blocks(source: Any, rec: Any, write: Callable[[Any], None],
                 duration: float | None, after_block: Callable[[Any], None] | None = None,
                 at_end: Callable[[], None] | None = None) -> tuple[bool, str | None]:
    """Copy ``source``'s blocks through ``write`` until the duration, Ctrl-C, a device failure
    or a recorder error, with a status line on stderr; ``after_block`` sees each block once
    written, ``at_end`` runs once the source is closed and before the recorder closes.
    Returns (interrupted, failure)."""
    from imunoise.daq.errors import DeviceError
    from imunoise.live.acquisition_process import settle_heap

    settle_heap()  # no long garbage-collector pause between two polls
    tty = sys.stderr.isatty()
    t_start = time.monotonic()
    last_print = 0.0
    try:
        for block in source.blocks(duration):
            write(block)
            if after_block is not None:
                after_block(block)
            if rec.error:
                break
            now = time.monotonic()
            if now - last_print >= (0.5 if tty else 60.0):
                line = _status_line(rec, source, t_start)
                print(("\r" + line) if tty else line, end="" if tty else "\n", file=sys.stderr,
                      flush=True)
                last_print = now
    except KeyboardInterrupt:
        return True, None
    except DeviceError as exc:
        return False, str(exc)
    finally:
        try:
            source.stop()
        finally:
            source.close()
            if at_end is not None:
                at_end()
            rec.close()
            if tty:
                print(file=sys.stderr)
    return False, None


def _record(acq: Any, rec: Any, duration: float | None) -> tuple[bool, str | None]:
    """One device: device state changes become events in the file."""
    from imunoise.daq import ros2_msgs

    last_state: list[Any] = [None]

    def note_state(block: Any) -> None:
        state = getattr(getattr(acq, "stats", None), "state", None)
        if state != last_state[0] and last_state[0] is not None:
            rec.event(ros2_msgs.WARN if state not in ("running", "ok") else ros2_msgs.OK,
                      f"device state: {state}", {"event": "state", "state": str(state)},
                      t=float(block.t[-1]) if len(block) else None)
        last_state[0] = state

    return _copy_blocks(acq, rec, rec.write, duration, after_block=note_state)


def _open_group(args: argparse.Namespace, out: Path, rotate_s: float | None
                ) -> tuple[Any, Any, Any]:
    """Several devices, opened, with one recorder for all of them and its sink."""
    from imunoise.analysis.noise_stream import stream_factory
    from imunoise.daq.devices import open_devices
    from imunoise.daq.errors import DeviceError
    from imunoise.daq.recorder import McapRecorder
    from imunoise.live.recorder_sink import GroupRecorderSink

    what = " + ".join(args.device)
    try:
        group = open_devices(list(args.device), ports=args.port or (), buses=args.bus or (),
                             rate_hz=args.rate, seed=args.seed, bench=args.bench_table,
                             noise=stream_factory)
    except (ValueError, KeyError) as exc:
        raise UsageError(f"record: {exc}") from exc
    except (OSError, DeviceError) as exc:
        raise RuntimeFailure(f"record: cannot open {what}: {exc}") from exc
    try:
        group.open()
    except (OSError, DeviceError) as exc:
        group.close()
        raise RuntimeFailure(f"record: cannot open {what}: {exc}") from exc
    devices = {name: {"spec": spec, "config": dict(getattr(acq, "config", {}) or {}),
                      "rate_hz": acq.rate_hz}
               for (name, acq), spec in zip(group.members, group.specs, strict=True)}
    try:
        rec = McapRecorder(args.out, "+".join(group.names), software=SOFTWARE,
                           rotate_s=rotate_s, devices=devices)
    except OSError as exc:
        group.close()
        raise RuntimeFailure(f"record: cannot write to {out}: {exc.strerror or exc}") from exc
    return group, rec, GroupRecorderSink(rec, group)


def _record_group(group: Any, rec: Any, sink: Any, duration: float | None
                  ) -> tuple[bool, str | None]:
    """Several devices: every block through the group's sink, which records each device's
    state changes as its own events; each device's losses noted at the end."""

    def note_losses() -> None:
        for name, st in group.stats.as_dict()["devices"].items():
            sink.sinks[name].note("ok", "acquisition ended", {
                "event": "losses", "device_dropped": str(st.get("dropped", 0)),
                "device_gaps": str(st.get("gaps", 0))})

    return _copy_blocks(group, rec, sink.write, duration, at_end=note_losses)


def _run_group(args: argparse.Namespace, out: Path, rotate_s: float | None,
               duration: float | None) -> int:
    group, rec, sink = _open_group(args, out, rotate_s)
    interrupted, failure = _record_group(group, rec, sink, duration)
    if rec.error:
        raise RuntimeFailure(f"record: {rec.error}")
    each = group.stats.as_dict()["devices"]
    failed = {name: reason for name, reason in group.stats.failures.items()}
    for name, st in each.items():
        if str(st.get("state", "")).startswith("failed") and name not in failed:
            failed[name] = str(st["state"])
    if failure or failed:
        kept = ", ".join(rec.stats.files) or "nothing"
        why = failure or "; ".join(f"{n}: {r}" for n, r in failed.items())
        raise RuntimeFailure(f"record: {why}; recorded data kept in {kept}")
    files = ", ".join(rec.stats.files) or "no file (no samples)"
    how = "stopped by Ctrl-C" if interrupted else "done"
    per = ", ".join(f"{name} {int(st.get('samples', 0))}" for name, st in each.items())
    print(f"record: {how}: {rec.stats.samples} samples in {files} ({per})", file=sys.stderr)
    return 0


def _single_device_args(args: argparse.Namespace) -> None:
    """One device: --port and --bus as they were (the last one given, not both)."""
    if args.port and args.bus:
        raise UsageError("record: argument --bus: not allowed with argument --port (one "
                         "device takes one of them)")
    args.device = args.device[0]
    args.port = args.port[-1] if args.port else None
    args.bus = args.bus[-1] if args.bus else None


def run(args: argparse.Namespace) -> int:
    duration = parse_duration(args.duration) if args.duration else None
    rotate_s = None if args.rotate.strip() in ("0", "0s") else parse_duration(args.rotate)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UsageError(f"record: --out {out}: exists and is not a folder")
    args.bench_table = None
    if args.bench:
        from imunoise.daq.sim.bench import bench_named

        try:
            args.bench_table = bench_named(args.bench)
        except ValueError as exc:
            raise UsageError(f"record: --bench: {exc}") from None
    if len(args.device) > 1:
        return _run_group(args, out, rotate_s, duration)
    _single_device_args(args)
    acq, rec = _open(args, out, rotate_s)
    interrupted, failure = _record(acq, rec, duration)
    if rec.error:
        raise RuntimeFailure(f"record: {rec.error}")
    state = str(getattr(getattr(acq, "stats", None), "state", ""))
    if failure or state.startswith("failed"):
        kept = ", ".join(rec.stats.files) or "nothing"
        raise RuntimeFailure(f"record: {args.device}: {failure or state}; recorded data kept "
                             f"in {kept}")
    files = ", ".join(rec.stats.files) or "no file (no samples)"
    how = "stopped by Ctrl-C" if interrupted else "done"
    print(f"record: {how}: {rec.stats.samples} samples in {files}", file=sys.stderr)
    return 0
