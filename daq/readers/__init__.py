"""Input files to :class:`daq.record.Record`: one entry point, dispatching on the path.

Readers are registered in ``FILE_READERS`` (by suffix) and ``FOLDER_READERS`` (by a marker file in
a folder) as ``"module:function"``; each function takes ``(path, rate_hz)`` and returns a
``Record`` or raises :class:`ReadError`. A reader whose module is not installed yet makes the
input type report itself as unsupported.
"""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path

from daq.record import Record


class ReadError(ValueError):
    """The input cannot be read: missing, unsupported, empty or malformed. One-line message."""


FILE_READERS: dict[str, str] = {
    ".csv": "daq.readers.csv:read_csv",
    ".mcap": "daq.readers.mcap:read_mcap",
}

# A folder is read by the first entry whose marker file it contains.
FOLDER_READERS: dict[str, str] = {
    "metadata.yaml": "daq.readers.rosbag2:read_rosbag2",
}


def _call(target: str, path: Path, rate_hz: float | None, what: str) -> Record:
    module_name, func_name = target.split(":")
    if importlib.util.find_spec(module_name) is None:
        raise ReadError(f"{path}: {what} input is not supported yet")
    func = getattr(importlib.import_module(module_name), func_name)
    return func(path, rate_hz=rate_hz)


def open_record(path: str | Path, rate_hz: float | None = None) -> Record:
    """Read a recording (CSV now; MCAP and rosbag2 folders through their readers).

    Args:
        path: file or rosbag2 folder.
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
        for marker, target in FOLDER_READERS.items():
            if (p / marker).is_file():
                return _call(target, p, rate_hz, "rosbag2 folder")
        raise ReadError(f"{p}: is a folder but not a rosbag2 bag (no metadata.yaml)")
    suffix = p.suffix.lower()
    if suffix not in FILE_READERS:
        known = ", ".join(sorted(FILE_READERS))
        raise ReadError(f"{p}: unsupported file type {suffix or '(none)'!r}: expected {known} "
                        "or a rosbag2 folder")
    return _call(FILE_READERS[suffix], p, rate_hz, suffix.lstrip(".").upper())
