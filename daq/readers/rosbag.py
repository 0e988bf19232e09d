"""Per-message reader through rosbags, for what the bulk MCAP reader does not take.

Handles rosbag2 folders (``metadata.yaml`` with one or several split files), un-chunked MCAP
files, ``frame_id`` changing from message to message, and any CDR variant rosbags decodes.
It is about a hundred times slower than :mod:`imunoise.daq.readers.mcap` and needs a complete (not
crashed) file.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from imunoise.core.record import Record
from imunoise.daq import ros2_msgs as msgs
from imunoise.daq.errors import ReadError
from imunoise.daq.readers.mcap import ACCEL, GYRO, make_series, topic_timing


class RosbagReadError(ReadError):
    """rosbags could not read the input."""


def _first_line(exc: BaseException, limit: int = 100) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else "")[:limit]


def _collect(reader, conns, kinds: dict[str, str], per_topic: dict[str, dict[str, list]],
             undecoded: dict[str, int]) -> None:
    """Stamps and fields of every message of ``conns``; a message that does not deserialize
    is counted in ``undecoded`` (lost) and the rest are read."""
    for conn, _log_ns, raw in reader.messages(connections=conns):
        try:
            m = reader.deserialize(raw, conn.msgtype)
        except Exception:  # noqa: BLE001 - a damaged message is a lost one
            undecoded[conn.topic] = undecoded.get(conn.topic, 0) + 1
            continue
        d = per_topic.setdefault(conn.topic, {"t": [], "a": [], "b": [], "cov": []})
        d["t"].append(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)
        if kinds[conn.topic] == "imu":
            g, a = m.angular_velocity, m.linear_acceleration
            d["a"].append((g.x, g.y, g.z))
            d["b"].append((a.x, a.y, a.z))
            if not d["cov"]:
                d["cov"] = [m.angular_velocity_covariance[0],
                            m.linear_acceleration_covariance[0]]
        else:
            d["a"].append(m.temperature)


def read_rosbag(path: str | Path, rate_hz: float | None = None) -> Record:
    """Read the Imu and Temperature topics of a rosbag2 folder or a complete MCAP file."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    per_topic: dict[str, dict[str, list]] = {}
    kinds: dict[str, str] = {}
    undecoded: dict[str, int] = {}
    try:
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
            conns = [c for c in reader.connections
                     if c.msgtype in (msgs.IMU, msgs.TEMPERATURE)]
            if not conns:
                raise RosbagReadError(
                    f"{path.name}: no sensor_msgs/msg/Imu or Temperature topic")
            for conn in conns:
                kinds[conn.topic] = "imu" if conn.msgtype == msgs.IMU else "temperature"
            _collect(reader, conns, kinds, per_topic, undecoded)
    except RosbagReadError:
        raise
    except Exception as exc:  # rosbags raises several unrelated types on bad input
        raise RosbagReadError(f"{path.name}: not a readable ROS 2 bag "
                              f"({type(exc).__name__}: {_first_line(exc)})") from exc
    warnings: list[str] = [f"{topic}: {n} message(s) could not be decoded; lost (a gap)"
                           for topic, n in undecoded.items()]
    channels = {}
    temperature = None
    imu_topics = [t for t in per_topic if kinds[t] == "imu"]
    for topic in imu_topics:
        d = per_topic[topic]
        t = np.asarray(d["t"], dtype=np.int64)
        timing = topic_timing(t, topic, rate_hz=rate_hz)
        warnings.extend(timing.notes)
        label = topic if len(imu_topics) > 1 else ""
        blocks = []
        if d["cov"][0] != -1.0:
            blocks.append((GYRO, np.asarray(d["a"], dtype=np.float64), "rad/s"))
        if d["cov"][1] != -1.0:
            blocks.append((ACCEL, np.asarray(d["b"], dtype=np.float64), "m/s^2"))
        for names, arr, units in blocks:
            for i, name in enumerate(names):
                key = f"{label}:{name}" if label else name
                channels[key] = make_series(key, t, arr[:, i], timing, warnings, units)
    temp_topics = [t for t in per_topic if kinds[t] == "temperature"]
    if temp_topics:
        d = per_topic[temp_topics[0]]
        t = np.asarray(d["t"], dtype=np.int64)
        timing = topic_timing(t, temp_topics[0], {"rate_hz": "1.0"})
        temperature = make_series("temp", t, np.asarray(d["a"], dtype=np.float64), timing,
                                  warnings, "degC")
    if not channels and temperature is None:
        raise RosbagReadError(f"{path.name}: the Imu/Temperature topics hold no messages")
    meta = {"format": "rosbag2" if path.is_dir() else "mcap", "reader": "rosbags",
            "topics": ",".join(per_topic)}
    return Record(source=str(path), channels=channels, temperature=temperature, metadata=meta,
                  warnings=warnings)
