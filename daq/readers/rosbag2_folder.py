"""A rosbag2 folder's ``metadata.yaml`` checked against the folder and its storage files.

The metadata is a description, the storage files are the data: where they disagree the storage
wins and a warning says so.

- File names must stay inside the bag folder: an absolute path or one that climbs out of it
  (``../``) is a :class:`ReadError`; the metadata is never used to open anything outside.
- A listed file that does not exist is a warning (the others are read); none at all is an error.
- Message counts and the duration that differ from what the storage holds are warnings.
- A ``metadata.yaml`` that is not YAML, or not a rosbag2 description, is a :class:`ReadError`
  with one line saying where.
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from imunoise.daq.errors import ReadError, quoted

METADATA = "metadata.yaml"
_MAX_METADATA_BYTES = 16 << 20
_KEY = "rosbag2_bagfile_information"
_DURATION_TOLERANCE_NS = 1_000_000


@dataclass
class BagFolder:
    """What the metadata of a bag folder says, checked: the storage files that exist (inside
    the folder), the storage kind (``"mcap"`` or ``"sqlite3"``), and the disagreements."""

    path: Path
    files: list[Path]
    storage: str
    info: dict[str, Any]
    warnings: list[str] = field(default_factory=list)
    listed_missing: bool = False


def _load(path: Path) -> dict[str, Any]:
    import yaml

    meta = path / METADATA
    try:
        if meta.stat().st_size > _MAX_METADATA_BYTES:
            raise ReadError(f"{path.name}/{METADATA}: larger than 16 MB, not a bag description")
        text = meta.read_bytes().decode("utf-8", "replace")
    except OSError as exc:
        raise ReadError(f"{path.name}/{METADATA}: cannot read ({exc.strerror or exc})") from None
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "unreadable"
        raise ReadError(f"{path.name}/{METADATA}: not valid YAML ({quoted(str(problem), 60)}"
                        f"{where})") from None
    info = doc.get(_KEY) if isinstance(doc, dict) else None
    if not isinstance(info, dict):
        raise ReadError(f"{path.name}/{METADATA}: not a rosbag2 description (no {_KEY} "
                        "mapping)")
    return info


def _inside(folder: Path, name: object) -> Path:
    """The storage file ``name`` of the metadata, which must lie inside ``folder``."""
    if not isinstance(name, str) or not name or "\x00" in name:
        raise ReadError(f"{folder.name}/{METADATA}: a file name is not text: "
                        f"{quoted(str(name), 40)}")
    if os.path.isabs(name):
        raise ReadError(f"{folder.name}/{METADATA}: file {quoted(name, 60)} is an absolute "
                        "path; a bag's files must lie inside its folder")
    root = folder.resolve()
    target = (root / name).resolve()
    if target != root and root not in target.parents:
        raise ReadError(f"{folder.name}/{METADATA}: file {quoted(name, 60)} points outside "
                        "the bag folder")
    return target


def check_folder(path: str | Path) -> BagFolder:
    """Read and check a bag folder's metadata (see the module docstring)."""
    folder = Path(path)
    info = _load(folder)
    names = info.get("relative_file_paths")
    if not isinstance(names, list) or not names:
        raise ReadError(f"{folder.name}/{METADATA}: relative_file_paths is not a list of "
                        "file names")
    files = [_inside(folder, n) for n in names[:10_000]]
    warnings: list[str] = []
    present = [f for f in files if f.is_file()]
    missing = [f for f in files if not f.is_file()]
    if missing:
        warnings.append(f"{folder.name}/{METADATA} lists {len(missing)} file(s) that do not "
                        f"exist (first {quoted(missing[0].name, 40)}); read the others")
    if not present:
        raise ReadError(f"{folder.name}: none of the files {METADATA} lists exists "
                        f"(first {quoted(str(names[0]), 40)})")
    ident = info.get("storage_identifier")
    storage = ident if ident in ("mcap", "sqlite3") else (
        "mcap" if present[0].suffix == ".mcap" else "sqlite3")
    if any((f.suffix == ".mcap") != (storage == "mcap") for f in present):
        warnings.append(f"{folder.name}/{METADATA}: storage identifier {quoted(str(ident), 20)}"
                        " does not match the file names; the files' own format is used")
        storage = "mcap" if all(f.suffix == ".mcap" for f in present) else "sqlite3"
    bag = BagFolder(folder, present, storage, info, warnings, bool(missing))
    _compare_with_storage(bag)
    return bag


def _storage_facts(bag: BagFolder) -> tuple[int, int, int] | None:
    """(messages, first, last log time in ns) the storage files hold, or None when they
    cannot be counted cheaply (the reader then reports their damage)."""
    total, first, last = 0, None, None
    for f in bag.files:
        facts = _sqlite_facts(f) if f.suffix == ".db3" else _mcap_facts(f)
        if facts is None:
            return None
        n, a, b = facts
        total += n
        if n:
            first = a if first is None else min(first, a)
            last = b if last is None else max(last, b)
    return total, first or 0, last or 0


def _sqlite_facts(path: Path) -> tuple[int, int, int] | None:
    try:
        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            n, a, b = con.execute(
                "SELECT COUNT(*), MIN(timestamp), MAX(timestamp) FROM messages").fetchone()
        finally:
            con.close()
    except (sqlite3.Error, TypeError, ValueError):
        return None
    return int(n), int(a or 0), int(b or 0)


def _mcap_facts(path: Path) -> tuple[int, int, int] | None:
    import mmap

    from imunoise.daq import mcap_layout as ml

    try:
        with open(path, "rb") as fh:
            buf = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
            try:
                layout = ml.scan(buf)
            finally:
                buf.close()
    except (OSError, ValueError, ml.McapFormatError):
        return None
    if layout.damaged or layout.unchunked_messages or any(not c.mi for c in layout.chunks):
        return None
    n = sum(k for c in layout.chunks for _p, k in c.mi.values())
    times = [(c.message_start_time, c.message_end_time) for c in layout.chunks if c.mi]
    return n, min((a for a, _ in times), default=0), max((b for _, b in times), default=0)


def _number(value: object) -> int | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        return int(value)
    except (OverflowError, ValueError):
        return None


def _compare_with_storage(bag: BagFolder) -> None:
    """Warnings where the metadata's message count or duration differ from the storage's."""
    info = bag.info
    stated = _number(info.get("message_count"))
    duration = info.get("duration")
    stated_ns = _number(duration.get("nanoseconds")) if isinstance(duration, dict) else None
    if "message_count" in info and (stated is None or stated < 0):
        bag.warnings.append(f"{bag.path.name}/{METADATA}: message_count "
                            f"{quoted(str(info.get('message_count')), 24)} is not a count; "
                            "ignored")
    facts = _storage_facts(bag) if not bag.listed_missing else None
    if facts is None:
        return
    n, first, last = facts
    if stated is not None and stated >= 0 and stated != n:
        bag.warnings.append(f"{bag.path.name}/{METADATA} says {stated:.6g} messages, the "
                            f"storage holds {n}: the storage's are read")
    if stated_ns is not None and n and abs(stated_ns - (last - first)) > _DURATION_TOLERANCE_NS:
        bag.warnings.append(f"{bag.path.name}/{METADATA} says the bag lasts {stated_ns * 1e-9:.6g}"
                            f" s, its messages span {(last - first) * 1e-9:.6g} s: the storage's "
                            "times are used")


@contextlib.contextmanager
def readable_copy(bag: BagFolder) -> Iterator[Path]:
    """A folder rosbags can open: the bag itself when its metadata lists only files that exist,
    else a temporary folder with links to the files that exist and metadata listing them."""
    if not bag.listed_missing:
        yield bag.path
        return
    import yaml

    with tempfile.TemporaryDirectory(prefix="imunoise-bag-") as tmp:
        out = Path(tmp) / bag.path.name
        out.mkdir()
        names = []
        for f in bag.files:
            (out / f.name).symlink_to(f)
            names.append(f.name)
        info = dict(bag.info)
        info["relative_file_paths"] = names
        if isinstance(info.get("files"), list):
            info["files"] = [e for e in info["files"]
                             if isinstance(e, dict) and Path(str(e.get("path", ""))).name in names]
        (out / METADATA).write_text(yaml.safe_dump({_KEY: info}))
        yield out
