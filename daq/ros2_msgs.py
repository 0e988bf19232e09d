"""ROS 2 message definitions and a vectorised CDR encoder for the recorded message types.

The recorder writes ``sensor_msgs/msg/Imu``, ``sensor_msgs/msg/Temperature`` and
``diagnostic_msgs/msg/DiagnosticArray`` (gap and device-status events) as XCDR1 little-endian
payloads. Imu and Temperature have a fixed layout once ``header.frame_id`` is fixed, so a whole
block of samples is encoded into one numpy structured array; each row is one message payload.

Layout rules (OMG CDR, as used by rmw for ROS 2 types): a 4-byte encapsulation header
``00 01 00 00``; alignment is counted from the end of that header; every primitive aligns to its
own size; a string is a uint32 length that includes the NUL, then the bytes and the NUL; fixed
arrays have no length prefix.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence

import numpy as np

SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
PROFILE = "ros2"
CDR_LE_HEADER = b"\x00\x01\x00\x00"

IMU = "sensor_msgs/msg/Imu"
TEMPERATURE = "sensor_msgs/msg/Temperature"
DIAGNOSTIC_ARRAY = "diagnostic_msgs/msg/DiagnosticArray"

# Field lists of the .msg files involved (comments stripped; semantics and type hashes are
# unaffected by comments).
_MSG_TEXT: dict[str, str] = {
    "sensor_msgs/Imu": (
        "std_msgs/Header header\n"
        "geometry_msgs/Quaternion orientation\n"
        "float64[9] orientation_covariance\n"
        "geometry_msgs/Vector3 angular_velocity\n"
        "float64[9] angular_velocity_covariance\n"
        "geometry_msgs/Vector3 linear_acceleration\n"
        "float64[9] linear_acceleration_covariance\n"
    ),
    "sensor_msgs/Temperature": (
        "std_msgs/Header header\n"
        "float64 temperature\n"
        "float64 variance\n"
    ),
    "diagnostic_msgs/DiagnosticArray": (
        "std_msgs/Header header\n"
        "diagnostic_msgs/DiagnosticStatus[] status\n"
    ),
    "diagnostic_msgs/DiagnosticStatus": (
        "byte OK=0\n"
        "byte WARN=1\n"
        "byte ERROR=2\n"
        "byte STALE=3\n"
        "byte level\n"
        "string name\n"
        "string message\n"
        "string hardware_id\n"
        "diagnostic_msgs/KeyValue[] values\n"
    ),
    "diagnostic_msgs/KeyValue": "string key\nstring value\n",
    "geometry_msgs/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec\n",
}

_SEPARATOR = "\n" + "=" * 80 + "\n"


def _dependencies(name: str) -> list[str]:
    """Message types a .msg text refers to, in sorted order."""
    deps = set()
    for line in _MSG_TEXT[name].splitlines():
        field_type = line.split()[0].split("[")[0] if line.strip() else ""
        if "/" in field_type:
            deps.add(field_type)
    return sorted(deps)


def _full_text(name: str) -> str:
    """Schema text composed as rosbag2 does: the message, then each dependency depth-first
    (sorted per message), each preceded by a line of 80 ``=`` and ``MSG: pkg/Type``."""
    order: list[str] = []

    def visit(dep: str) -> None:
        for d in _dependencies(dep):
            if d not in order:
                order.append(d)
                visit(d)

    visit(name)
    text = _MSG_TEXT[name].rstrip("\n")
    for dep in order:
        text += _SEPARATOR + f"MSG: {dep}\n" + _MSG_TEXT[dep].rstrip("\n")
    return text + "\n"


SCHEMA_TEXT: dict[str, str] = {
    IMU: _full_text("sensor_msgs/Imu"),
    TEMPERATURE: _full_text("sensor_msgs/Temperature"),
    DIAGNOSTIC_ARRAY: _full_text("diagnostic_msgs/DiagnosticArray"),
}

# RIHS01 type hashes as published by ROS 2 (Jazzy and later write them as channel metadata).
TYPE_HASH: dict[str, str] = {
    IMU: "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
    TEMPERATURE: "RIHS01_72514a14126ab9f8a9abec974c78e5610a367b59db5da355ff1fb982d5bad4b8",
    DIAGNOSTIC_ARRAY: "RIHS01_5a8a36efb05fb25070fa0fb3810290c0e6cd4862b54a8fb975a1ee8dc55a333e",
}

# rosbag2's offered_qos_profiles in integer form (readable by Humble and later): history
# unknown (3), depth 0, reliable (1), volatile (2), automatic liveliness (1), infinite durations.
_INFINITE = "    sec: 9223372036\n    nsec: 854775807\n"
QOS_PROFILES_YAML = (
    "- history: 3\n  depth: 0\n  reliability: 1\n  durability: 2\n"
    f"  deadline:\n{_INFINITE}  lifespan:\n{_INFINITE}  liveliness: 1\n"
    f"  liveliness_lease_duration:\n{_INFINITE}  avoid_ros_namespace_conventions: false"
)


def channel_metadata(msgtype: str) -> dict[str, str]:
    """Channel metadata as rosbag2 (Jazzy and later) writes it."""
    return {"offered_qos_profiles": QOS_PROFILES_YAML, "topic_type_hash": TYPE_HASH[msgtype]}


def _align8(n: int) -> int:
    return (n + 7) & ~7


def body_offset(frame_len: int) -> int:
    """Payload offset of the first float64 after the header, for ``frame_len`` string bytes
    including the NUL: 4 (encapsulation) + align8(8 stamp + 4 length + frame_len)."""
    return 4 + _align8(12 + frame_len)


def _header_fields(frame_len: int) -> list[tuple]:
    pad = body_offset(frame_len) - 16 - frame_len
    fields: list[tuple] = [("encap", "V4"), ("sec", "<i4"), ("nanosec", "<u4"),
                           ("frame_len", "<u4"), ("frame_id", f"V{frame_len}")]
    if pad:
        fields.append(("_pad", f"V{pad}"))
    return fields


def imu_dtype(frame_len: int) -> np.dtype:
    """Structured dtype of one ``sensor_msgs/msg/Imu`` payload (frame_len includes the NUL)."""
    return np.dtype(_header_fields(frame_len) + [
        ("orientation", "<f8", (4,)), ("orientation_covariance", "<f8", (9,)),
        ("angular_velocity", "<f8", (3,)), ("angular_velocity_covariance", "<f8", (9,)),
        ("linear_acceleration", "<f8", (3,)), ("linear_acceleration_covariance", "<f8", (9,))])


def temperature_dtype(frame_len: int) -> np.dtype:
    """Structured dtype of one ``sensor_msgs/msg/Temperature`` payload."""
    return np.dtype(_header_fields(frame_len) + [("temperature", "<f8"), ("variance", "<f8")])


# Offsets (bytes after body_offset) of the Imu fields the readers need.
IMU_GYRO_OFFSET = 104
IMU_GYRO_COV_OFFSET = 128
IMU_ACCEL_OFFSET = 200
IMU_ACCEL_COV_OFFSET = 224
IMU_TAIL = 296  # payload length = body_offset + IMU_TAIL
TEMPERATURE_TAIL = 16


def stamps_from_seconds(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split times in seconds into ``builtin_interfaces/Time`` (sec int32, nanosec uint32)."""
    ns = np.rint(np.asarray(t, dtype=np.float64) * 1e9).astype(np.int64)
    return (ns // 1_000_000_000).astype(np.int32), (ns % 1_000_000_000).astype(np.uint32)


def _frame_bytes(frame_id: str) -> bytes:
    data = frame_id.encode("utf-8") + b"\x00"
    if b"\x00" in data[:-1]:
        raise ValueError("frame_id must not contain NUL characters")
    return data


def _fill_header(rec: np.ndarray, t: np.ndarray, frame: bytes) -> None:
    rec["encap"] = np.frombuffer(CDR_LE_HEADER, dtype="V4")[0]
    rec["sec"], rec["nanosec"] = stamps_from_seconds(t)
    rec["frame_len"] = len(frame)
    rec["frame_id"] = np.frombuffer(frame, dtype=f"V{len(frame)}")[0]


def encode_imu(t: np.ndarray, gyro: np.ndarray | None, accel: np.ndarray | None,
               frame_id: str = "imu_link") -> np.ndarray:
    """Encode a block of Imu messages.

    Args:
        t: sample times in seconds (``header.stamp``), shape (n,).
        gyro: angular velocity in rad/s, shape (n, 3), or None for an accelerometer-only device
            (its covariance[0] is then -1, the ROS mark for "not provided").
        accel: linear acceleration in m/s^2, shape (n, 3), or None for a gyro-only device.
        frame_id: ``header.frame_id``.

    Returns:
        Structured array of ``imu_dtype``; ``rec[i].tobytes()`` (or a row of
        ``rec.view(np.uint8).reshape(n, -1)``) is the CDR payload of message i. Orientation is
        not estimated: identity quaternion with orientation_covariance[0] = -1.
    """
    frame = _frame_bytes(frame_id)
    n = len(t)
    rec = np.zeros(n, dtype=imu_dtype(len(frame)))
    _fill_header(rec, t, frame)
    rec["orientation"][:, 3] = 1.0
    rec["orientation_covariance"][:, 0] = -1.0
    if gyro is None:
        rec["angular_velocity_covariance"][:, 0] = -1.0
    else:
        rec["angular_velocity"] = gyro
    if accel is None:
        rec["linear_acceleration_covariance"][:, 0] = -1.0
    else:
        rec["linear_acceleration"] = accel
    return rec


def encode_temperature(t: np.ndarray, temp_c: np.ndarray, variance: float = 0.0,
                       frame_id: str = "imu_link") -> np.ndarray:
    """Encode a block of Temperature messages (degC; variance 0 means unknown)."""
    frame = _frame_bytes(frame_id)
    rec = np.zeros(len(t), dtype=temperature_dtype(len(frame)))
    _fill_header(rec, t, frame)
    rec["temperature"] = temp_c
    rec["variance"] = variance
    return rec


class _CdrWriter:
    """Minimal XCDR1 little-endian serializer for the rare, variable-length event messages."""

    def __init__(self) -> None:
        self.buf = bytearray(CDR_LE_HEADER)

    def _align(self, n: int) -> None:
        self.buf += b"\x00" * ((-(len(self.buf) - 4)) % n)

    def u8(self, v: int) -> None:
        self.buf += struct.pack("<B", v)

    def i32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<i", v)

    def u32(self, v: int) -> None:
        self._align(4)
        self.buf += struct.pack("<I", v)

    def string(self, s: str) -> None:
        data = _frame_bytes(s)
        self.u32(len(data))
        self.buf += data


# diagnostic_msgs/DiagnosticStatus levels
OK, WARN, ERROR, STALE = 0, 1, 2, 3


def encode_diagnostic_array(t: float, statuses: Iterable[tuple[int, str, str, str,
                                                                Sequence[tuple[str, str]]]],
                            frame_id: str = "") -> bytes:
    """Encode one DiagnosticArray: ``statuses`` of (level, name, message, hardware_id,
    [(key, value), ...]); ``t`` in seconds."""
    sec, nanosec = stamps_from_seconds(np.array([t]))
    w = _CdrWriter()
    w.i32(int(sec[0]))
    w.u32(int(nanosec[0]))
    w.string(frame_id)
    statuses = list(statuses)
    w.u32(len(statuses))
    for level, name, message, hardware_id, values in statuses:
        w.u8(level)
        w.string(name)
        w.string(message)
        w.string(hardware_id)
        w.u32(len(values))
        for key, value in values:
            w.string(key)
            w.string(value)
    return bytes(w.buf)
