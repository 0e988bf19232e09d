"""Several devices recorded at once, on one time base: naming, port pairing and the loop.

Topic naming: a device's streams keep their topics under ``/<name>/``, where ``name`` is the
device's name without ``sim:`` (``adis16350``, ``razor``); the second device of the same name
is ``<name>_2``, the third ``<name>_3`` (``/adis16350_2/imu``; the razor's ``/razor_2/itg3200/
imu`` and ``/razor_2/adxl345/imu``). The first of each name keeps the topics it has alone.

Port pairing: the k-th ``--port`` (``serve``: ``--serial``) goes to the k-th real device on a
serial bridge (``adis16350``) and the k-th ``--bus`` to the k-th real I2C device (``itg3200``,
``adxl345``, ``razor``), in the order the devices are given; simulated devices take neither.
There must be exactly one of each per real device that needs it.

Seeds: the k-th device (from 0) draws its own noise with seed ``seed + SEED_STRIDE * k``, so
the first one draws what it draws alone; a simulated bench they share draws from ``seed``.

:class:`DeviceGroup` runs each device's :class:`imunoise.daq.acquisition.Acquisition` loop on a
thread of its own (each paced by its own part, as alone) and hands their batches out in the
order they come, streams renamed to the device's topic name. A device that fails for good
stops alone; the others go on, and the group ends with the last of them.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

from imunoise.core.blocks import SampleBlock
from imunoise.daq.errors import AcquisitionFailed, DeviceError

SEED_STRIDE = 100_003
SERIAL_BASES = ("adis16350",)
I2C_BASES = ("itg3200", "adxl345", "razor")


@dataclass(frozen=True)
class Member:
    """One device of a group: its spec, topic name, place in the group and connection."""

    spec: str
    name: str
    position: int
    port: str | None = None
    bus: int | None = None

    @property
    def simulated(self) -> bool:
        return self.spec.startswith("sim:")

    @property
    def base(self) -> str:
        return self.spec.removeprefix("sim:")


def topic_names(specs: Sequence[str]) -> list[str]:
    """Topic name of each device (see the module docstring)."""
    seen: dict[str, int] = {}
    names = []
    for spec in specs:
        base = spec.removeprefix("sim:")
        seen[base] = seen.get(base, 0) + 1
        names.append(base if seen[base] == 1 else f"{base}_{seen[base]}")
    return names


def pair_devices(specs: Sequence[str], ports: Sequence[str] = (),
                 buses: Sequence[int] = (), port_option: str = "--port") -> list[Member]:
    """The members for ``specs`` with their ports and buses paired as the module docstring
    says; ``ValueError`` naming the rule when the counts do not match."""
    names = topic_names(specs)
    serial = [k for k, s in enumerate(specs) if s in SERIAL_BASES]
    i2c = [k for k, s in enumerate(specs) if s in I2C_BASES]
    if len(ports) != len(serial):
        raise ValueError(f"{len(serial)} device(s) on a serial bridge "
                         f"({', '.join(specs[k] for k in serial) or 'none'}) but "
                         f"{len(ports)} {port_option}: give one {port_option} per real "
                         f"adis16350, in the order of the devices")
    if len(buses) != len(i2c):
        raise ValueError(f"{len(i2c)} I2C device(s) "
                         f"({', '.join(specs[k] for k in i2c) or 'none'}) but {len(buses)} "
                         f"--bus: give one --bus per real itg3200, adxl345 or razor, in the "
                         f"order of the devices")
    port_of = dict(zip(serial, ports, strict=True))
    bus_of = dict(zip(i2c, buses, strict=True))
    return [Member(spec, name, k, port_of.get(k), bus_of.get(k))
            for k, (spec, name) in enumerate(zip(specs, names, strict=True))]


def member_seed(seed: int | None, position: int) -> int:
    """The noise seed of the ``position``-th device of a group run with ``seed``."""
    return (0 if seed is None else int(seed)) + SEED_STRIDE * position


def renamed(stream: str, name: str) -> str:
    """``stream`` with its first path component replaced by ``name``."""
    parts = stream.split("/")
    if len(parts) < 3 or parts[0] != "":
        return f"/{name}/{stream.lstrip('/')}"
    parts[1] = name
    return "/".join(parts)


def device_of_stream(stream: str) -> str:
    """The topic name of the device a stream belongs to (its first path component)."""
    return stream.lstrip("/").split("/", 1)[0]


@dataclass
class GroupStats:
    """Counters of a group: sums over its devices, and each device's own (``devices``)."""

    members: list[tuple[str, Any]] = field(default_factory=list)
    failures: dict[str, str] = field(default_factory=dict)

    def _each(self) -> dict[str, dict[str, Any]]:
        return {name: acq.stats.as_dict() for name, acq in self.members}

    def _sum(self, key: str) -> int:
        return sum(int(getattr(acq.stats, key, 0) or 0) for _, acq in self.members)

    @property
    def samples(self) -> int:
        return self._sum("samples")

    @property
    def dropped(self) -> int:
        return self._sum("dropped")

    @property
    def gaps(self) -> int:
        return self._sum("gaps")

    @property
    def reconnects(self) -> int:
        return self._sum("reconnects")

    @property
    def state(self) -> str:
        states = {name: str(acq.stats.state) for name, acq in self.members}
        if len(set(states.values())) == 1:
            return next(iter(states.values()))
        if any(s == "running" for s in states.values()):
            odd = [f"{n} {s}" for n, s in states.items() if s != "running"]
            return "running (" + ", ".join(odd) + ")"
        return ", ".join(f"{n} {s}" for n, s in states.items())

    @property
    def last_error(self) -> str:
        errors = [f"{name}: {acq.stats.last_error}" for name, acq in self.members
                  if acq.stats.last_error]
        return errors[-1] if errors else ""

    def as_dict(self) -> dict[str, Any]:
        each = self._each()
        faults: dict[str, int] = {}
        for name, st in each.items():
            for k, v in (st.get("faults") or {}).items():
                faults[f"{name}: {k}"] = v
        return {
            "samples": self.samples, "dropped": self.dropped, "gaps": self.gaps,
            "reconnects": self.reconnects,
            "jitter_s": max((float(s.get("jitter_s") or 0) for s in each.values()), default=0),
            "max_late_s": max((float(s.get("max_late_s") or 0) for s in each.values()),
                              default=0),
            "state": self.state, "last_error": self.last_error, "faults": faults,
            "devices": each,
        }


class DeviceGroup:
    """Several acquisitions as one source of batches (``Acquisition``'s interface).

    Args:
        members: ``(topic name, acquisition)`` of each device, in the group's order.
        specs: the device names, for :attr:`config` and descriptions.
    """

    def __init__(self, members: Sequence[tuple[str, Any]], specs: Sequence[str] = ()) -> None:
        if not members:
            raise ValueError("a device group needs at least one device")
        self.members = list(members)
        self.specs = list(specs) or [name for name, _ in members]
        self.stats = GroupStats(self.members)
        self.simulator: dict[str, Any] = {name: getattr(acq, "simulator", None)
                                          for name, acq in self.members}
        self._stop = threading.Event()

    @property
    def names(self) -> list[str]:
        return [name for name, _ in self.members]

    @property
    def config(self) -> dict[str, str]:
        """Every device's configuration, keys prefixed with its topic name."""
        out = {}
        for (name, acq), spec in zip(self.members, self.specs, strict=True):
            out[f"{name}.device"] = spec
            for k, v in dict(getattr(acq, "config", {}) or {}).items():
                out[f"{name}.{k}"] = str(v)
        return out

    def member_config(self, name: str) -> dict[str, str]:
        return dict(getattr(dict(self.members)[name], "config", {}) or {})

    @property
    def rate_hz(self) -> float:
        return float(self.members[0][1].rate_hz)

    def open(self) -> None:
        for _, acq in self.members:
            acq.open()

    def stop(self) -> None:
        self._stop.set()
        for _, acq in self.members:
            acq.stop()

    def close(self) -> None:
        self._stop.set()
        for _, acq in self.members:
            try:
                acq.close()
            except Exception:  # noqa: BLE001 - close every device whatever one says
                pass

    def __enter__(self) -> DeviceGroup:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def blocks(self, duration_s: float | None = None) -> Iterator[SampleBlock]:
        for batch in self.batches(duration_s):
            yield from batch

    def batches(self, duration_s: float | None = None) -> Iterator[list[SampleBlock]]:
        """Each device's batches as they come, streams renamed to its topic name, until every
        device has ended (``duration_s`` of its time, :meth:`stop`, or a failure). Raises
        :class:`AcquisitionFailed` when every device failed."""
        self.open()
        handed: queue.SimpleQueue = queue.SimpleQueue()
        running = len(self.members)

        def run(name: str, acq: Any) -> None:
            try:
                for batch in acq.batches(duration_s):
                    for block in batch:
                        block.stream = renamed(block.stream, name)
                    handed.put(batch)
                    if self._stop.is_set():
                        break
            except DeviceError as exc:
                self.stats.failures[name] = str(exc)
            except Exception as exc:  # noqa: BLE001 - one device's fault ends that device
                self.stats.failures[name] = f"{type(exc).__name__}: {exc}"
            finally:
                handed.put(None)

        threads = [threading.Thread(target=run, args=(name, acq), daemon=True,
                                    name=f"imunoise-acq-{name}")
                   for name, acq in self.members]
        for t in threads:
            t.start()
        try:
            while running:
                batch = handed.get()
                if batch is None:
                    running -= 1
                    continue
                yield batch
        finally:
            self.stop()
            for t in threads:
                t.join(5.0)
        if len(self.stats.failures) == len(self.members):
            raise AcquisitionFailed("; ".join(f"{n}: {r}" for n, r in
                                              self.stats.failures.items()))
