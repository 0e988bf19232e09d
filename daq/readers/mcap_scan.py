"""Opening a ROS 2 MCAP file for the bulk reader: its layout (:mod:`imunoise.daq.mcap_layout`) and
the
Imu and Temperature topics, chosen by schema name, with their fixed CDR layouts."""

from __future__ import annotations

import mmap
from dataclasses import dataclass, field
from pathlib import Path

from imunoise.daq import mcap_layout as ml
from imunoise.daq import ros2_msgs as msgs


class UnsupportedLayout(Exception):
    """The bulk reader cannot decode this file; a per-message reader can."""


@dataclass
class _Topic:
    cid: int
    topic: str
    kind: str  # "imu" or "temperature"
    payload_len: int = 0
    body: int = 0
    frame_len: int = -1
    has_gyro: bool = True
    has_accel: bool = True
    count: int = 0


@dataclass
class McapSource:
    """An opened MCAP file: layout, chosen topics and metadata."""

    path: Path
    layout: ml.McapLayout
    topics: dict[int, _Topic]
    metadata: dict[str, str]
    warnings: list[str] = field(default_factory=list)


def open_mcap(path: str | Path) -> McapSource:
    """Scan ``path`` and choose its Imu and Temperature channels by schema name."""
    path = Path(path)
    size = path.stat().st_size
    if size == 0:
        raise ml.McapFormatError("empty file")
    with open(path, "rb") as f:
        buf = mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)
        try:
            layout = ml.scan(buf, size)
        except (ml.McapFormatError, ValueError, OverflowError) as exc:
            raise ml.McapFormatError(str(exc)) from exc
        except Exception as exc:  # struct.error and friends on a damaged file
            raise ml.McapFormatError(f"damaged MCAP records ({exc})") from exc
        finally:
            buf.close()
    topics: dict[int, _Topic] = {}
    for cid, ch in sorted(layout.channels.items()):
        schema = layout.schemas.get(ch.schema_id)
        if schema is None or ch.message_encoding != msgs.MESSAGE_ENCODING:
            continue
        if schema.name == msgs.IMU:
            topics[cid] = _Topic(cid, ch.topic, "imu")
        elif schema.name == msgs.TEMPERATURE:
            topics[cid] = _Topic(cid, ch.topic, "temperature")
    metadata: dict[str, str] = {"profile": layout.profile, "library": layout.library}
    for md in layout.metadata:
        for key, value in md.data.items():
            metadata[key if md.name.startswith("imunoise") else f"{md.name}.{key}"] = value
    src = McapSource(path, layout, topics, metadata, list(layout.warnings))
    if layout.unchunked_messages:
        raise UnsupportedLayout("messages outside chunks")
    for c in layout.chunks:
        for cid, (_pos, n) in c.mi.items():
            if cid in topics:
                topics[cid].count += n
    return src


