"""Readers: every supported input becomes a :class:`daq.record.Record`.

``open_record`` dispatches on the path: ``.mcap`` files go to the bulk numpy reader
(:mod:`daq.readers.mcap`) with a per-message fallback through rosbags
(:mod:`daq.readers.rosbag`); a rosbag2 folder (``metadata.yaml``) goes to rosbags.
"""

from __future__ import annotations

from pathlib import Path

from daq.record import Record


class InputError(ValueError):
    """The input cannot be read; the message is one line naming the problem."""


def open_record(path: str | Path, rate_hz: float | None = None) -> Record:
    """Load a recording. Raises InputError with a one-line reason on bad input."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{path}: no such file or directory")
    if path.is_dir():
        if not (path / "metadata.yaml").is_file():
            mcaps = sorted(path.glob("*.mcap"))
            if len(mcaps) == 1:
                return _read_mcap_file(mcaps[0])
            raise InputError(f"{path}: a directory that is not a rosbag2 bag (no metadata.yaml)")
        return _read_bag(path)
    if path.suffix.lower() == ".mcap":
        return _read_mcap_file(path)
    raise InputError(f"{path}: unsupported input (expected .csv, .mcap or a rosbag2 folder)")


def _read_bag(path: Path) -> Record:
    from daq.readers.rosbag import RosbagReadError, read_rosbag

    try:
        return read_rosbag(path)
    except RosbagReadError as exc:
        raise InputError(str(exc)) from exc


def _read_mcap_file(path: Path) -> Record:
    from daq.mcap_layout import McapFormatError
    from daq.readers.mcap import UnsupportedLayout, read_mcap
    from daq.readers.rosbag import RosbagReadError, read_rosbag

    try:
        return read_mcap(path)
    except UnsupportedLayout as exc:
        reason = str(exc)
    except (McapFormatError, OSError) as exc:
        raise InputError(f"{path.name}: {exc}") from exc
    try:
        record = read_rosbag(path)
    except RosbagReadError as exc:
        raise InputError(f"{path.name}: {reason}; per-message reading failed too ({exc})"
                         ) from exc
    record.warnings.insert(0, f"read message by message ({reason})")
    return record
