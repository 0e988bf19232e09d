"""Input files to :class:`imunoise.core.record.Record`: one entry point, dispatching on the path.

- ``.csv``: :mod:`imunoise.daq.readers.csv_file` (the column layout of docs/robot-logs.md).
- ``.mcap``: the bulk numpy reader (:mod:`imunoise.daq.readers.mcap`), falling back to per-message
  decoding through rosbags (:mod:`imunoise.daq.readers.rosbag`) for layouts the bulk reader does
  not take.
- ``.bag``: ROS 1 (:mod:`imunoise.daq.readers.rosbag1`).
- a rosbag2 folder (``metadata.yaml``): rosbags; a folder holding exactly one ``.mcap`` file is
  read as that file.

CSV, MCAP and ROS 1 bag files are parsed once per state of the file
(:mod:`imunoise.daq.readers.record_cache`).
"""

from __future__ import annotations

from pathlib import Path

from imunoise.core.record import Record
from imunoise.daq.errors import ReadError
from imunoise.daq.readers.record_cache import cached

__all__ = ["ReadError", "open_record"]


def open_record(path: str | Path, rate_hz: float | None = None) -> Record:
    """Read a recording into memory.

    Args:
        path: a ``.csv`` (also EuRoC/ASL ``imu0/data.csv``), ``.mcap`` or ``.bag`` (ROS 1)
            file, or a rosbag2 folder.
        rate_hz: nominal sampling rate in Hz; needed for a CSV without a time column ``t``,
            otherwise it overrides the rate inferred from the time stamps.

    Raises:
        ReadError: missing, unsupported, empty or malformed input.
    """
    p = Path(path)
    if rate_hz is not None and not rate_hz > 0:
        raise ReadError(f"bad rate {rate_hz}: must be a positive number of Hz")
    if not p.exists():
        raise ReadError(f"{p}: no such file or directory")
    if p.is_dir():
        if (p / "metadata.yaml").is_file():
            return _read_bag(p, rate_hz)
        mcaps = sorted(p.glob("*.mcap"))
        if len(mcaps) == 1:
            return _read_mcap_file(mcaps[0], rate_hz)
        raise ReadError(f"{p}: is a folder but not a rosbag2 bag (no metadata.yaml)")
    suffix = p.suffix.lower()
    if suffix == ".csv":
        from imunoise.daq.readers.csv_file import read_csv

        return cached(p, rate_hz, lambda: read_csv(p, rate_hz=rate_hz))
    if suffix == ".mcap":
        return cached(p, rate_hz, lambda: _read_mcap_file(p, rate_hz))
    if suffix == ".bag":
        return cached(p, rate_hz, lambda: _read_rosbag1(p, rate_hz))
    raise ReadError(f"{p}: unsupported file type {suffix or '(none)'!r}: expected .csv, .mcap, "
                    ".bag (ROS 1) or a rosbag2 folder")


def _read_rosbag1(path: Path, rate_hz: float | None) -> Record:
    from imunoise.daq.readers.rosbag1 import Rosbag1Error, read_rosbag1

    try:
        return read_rosbag1(path, rate_hz)
    except Rosbag1Error as exc:
        raise ReadError(str(exc)) from exc
    except OSError as exc:
        raise ReadError(f"{path}: cannot read ({exc.strerror or exc})") from None


def _read_bag(path: Path, rate_hz: float | None = None) -> Record:
    """A rosbag2 folder: its metadata checked against the folder
    (:mod:`imunoise.daq.readers.rosbag2_folder`); a single MCAP storage file is read by the
    MCAP reader (damaged chunks left out), anything else through rosbags."""
    from imunoise.daq.readers.rosbag import RosbagReadError, read_rosbag
    from imunoise.daq.readers.rosbag2_folder import check_folder, readable_copy

    bag = check_folder(path)
    if bag.storage == "mcap" and len(bag.files) == 1:
        record = _read_mcap_file(bag.files[0], rate_hz)
    else:
        try:
            with readable_copy(bag) as folder:
                record = read_rosbag(folder, rate_hz)
        except RosbagReadError as exc:
            raise ReadError(str(exc)) from exc
        except OSError as exc:
            raise ReadError(f"{path.name}: cannot read ({exc.strerror or exc})") from None
    record.source = str(path)
    record.metadata["format"] = "rosbag2"
    record.warnings[:0] = bag.warnings
    return record


def _read_mcap_file(path: Path, rate_hz: float | None = None) -> Record:
    from imunoise.daq.mcap_layout import McapFormatError
    from imunoise.daq.readers.mcap import UnsupportedLayout, read_mcap
    from imunoise.daq.readers.rosbag import RosbagReadError, read_rosbag

    try:
        return read_mcap(path, rate_hz)
    except UnsupportedLayout as exc:
        reason = str(exc)
    except (McapFormatError, OSError) as exc:
        raise ReadError(f"{path.name}: {exc}") from exc
    except ReadError as exc:
        raise ReadError(f"{path.name}: {exc}") from exc
    try:
        record = read_rosbag(path, rate_hz)
    except RosbagReadError as exc:
        raise ReadError(f"{path.name}: {reason}; per-message reading failed too ({exc})") from exc
    record.warnings.insert(0, f"read message by message ({reason})")
    return record
