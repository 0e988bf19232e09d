"""Parsed recordings remembered between commands, so that a log is parsed once.

A CSV of 1e6 rows takes about 0.7 s to parse, an MCAP file about 0.35 s per 1e6 messages and a
ROS 1 bag longer, while every command
(``fit``, ``diagnose``, ``analyze`` ...) reads its input afresh: a user who fits, diagnoses and
refits one log pays that each time. The parsed :class:`~imunoise.core.record.Record` is
therefore kept as an uncompressed ``.npz`` (arrays, plus the scalars, metadata, warnings and
facts as JSON; read back without pickle), and the next read of the same file loads it in a
few hundredths of a second.

An entry belongs to one state of one file: its key hashes the resolved path, size,
modification time (ns), inode and device, the requested rate and :data:`FORMAT`. A file that
changes gets a new key; a file modified within the last :data:`SETTLE_S` seconds (still being
written, or on a file system with coarse time stamps) is not cached. Entries are written to a
temporary name and renamed, so a reader never sees half of one; an entry that cannot be read
is removed and the file parsed again. A cache that cannot be written (read-only, disk full)
only costs the parse: the record is returned all the same.

Where: ``$IMUNOISE_CACHE_DIR``, else ``$XDG_CACHE_HOME/imunoise/records``, else
``~/.cache/imunoise/records``. Size: at most ``$IMUNOISE_CACHE_MB`` MiB (default
:data:`DEFAULT_MB`), the least recently used entries removed first; a record larger than half
of that is not kept; ``IMUNOISE_CACHE_MB=0`` turns the cache off.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import time
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from imunoise.core.record import Record
from imunoise.core.series import ChannelSeries

FORMAT = 1
"""Bumped whenever a reader's output or this file's layout changes: older entries are then
never matched (and age out)."""

DEFAULT_MB = 2048
SETTLE_S = 2.0
_SUFFIX = ".npz"


def cache_dir() -> Path | None:
    """The cache folder, or None when the cache is turned off."""
    try:
        if float(os.environ.get("IMUNOISE_CACHE_MB", DEFAULT_MB)) <= 0:
            return None
    except ValueError:
        return None
    given = os.environ.get("IMUNOISE_CACHE_DIR")
    if given:
        return Path(given)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "imunoise" / "records"


def _limit_bytes() -> int:
    try:
        return int(float(os.environ.get("IMUNOISE_CACHE_MB", DEFAULT_MB)) * 2**20)
    except ValueError:
        return 0


def _key(path: Path, rate_hz: float | None) -> str | None:
    """The entry name of ``path`` as it is now, or None when it should not be cached."""
    try:
        st = path.stat()
        real = str(path.resolve())
    except OSError:
        return None
    if time.time() - st.st_mtime < SETTLE_S:
        return None
    ident = json.dumps([FORMAT, real, st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev,
                        None if rate_hz is None else float(rate_hz)])
    return hashlib.sha256(ident.encode()).hexdigest()[:32]


def _series_meta(s: ChannelSeries) -> dict[str, Any]:
    return {"name": s.name, "units": s.units, "fs_hz": float(s.fs_hz), "t0_s": float(s.t0_s),
            "segment_t0": s.segment_t0_s is not None}


def _pack(record: Record) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    arrays: dict[str, np.ndarray] = {}
    series: list[tuple[str, ChannelSeries]] = list(record.channels.items())
    if record.temperature is not None:
        series.append(("", record.temperature))
    metas = []
    for i, (key, s) in enumerate(series):
        arrays[f"v{i}"] = np.asarray(s.values)
        arrays[f"s{i}"] = np.asarray(s.segment_starts)
        if s.segment_t0_s is not None:
            arrays[f"t{i}"] = np.asarray(s.segment_t0_s)
        metas.append({"key": key, **_series_meta(s)})
    meta = {"series": metas, "temperature": record.temperature is not None,
            "metadata": record.metadata, "warnings": record.warnings, "facts": record.facts}
    return arrays, meta


def _unpack(npz: Any, source: str) -> Record:
    meta = json.loads(str(npz["meta"][()]))
    series = []
    for i, m in enumerate(meta["series"]):
        series.append((m["key"], ChannelSeries(
            name=m["name"], units=m["units"], fs_hz=float(m["fs_hz"]), values=npz[f"v{i}"],
            segment_starts=npz[f"s{i}"], t0_s=float(m["t0_s"]),
            segment_t0_s=npz[f"t{i}"] if m["segment_t0"] else None)))
    temperature = series.pop()[1] if meta["temperature"] else None
    return Record(source=source, channels=dict(series), temperature=temperature,
                  metadata=dict(meta["metadata"]), warnings=list(meta["warnings"]),
                  facts=dict(meta["facts"]))


def load(path: Path, rate_hz: float | None) -> Record | None:
    """The cached record of ``path`` as it is now, or None."""
    folder, key = cache_dir(), _key(path, rate_hz)
    if folder is None or key is None:
        return None
    entry = folder / (key + _SUFFIX)
    try:
        with np.load(entry, allow_pickle=False) as npz:
            record = _unpack(npz, str(path))
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile):
        with contextlib.suppress(OSError):
            entry.unlink()  # damaged: parse again and write it anew
        return None
    with contextlib.suppress(OSError):
        os.utime(entry)  # recently used: evicted last
    return record


def store(path: Path, rate_hz: float | None, record: Record, key: str | None) -> None:
    """Keep ``record`` as the entry ``key`` of ``path`` (taken before it was read), unless the
    file changed while it was read; failures to write are ignored."""
    folder = cache_dir()
    if folder is None or key is None or _key(path, rate_hz) != key:
        return
    try:
        arrays, meta = _pack(record)
        payload = json.dumps(meta)
    except (TypeError, ValueError):
        return  # facts that JSON cannot hold: not cached
    if 2 * sum(a.nbytes for a in arrays.values()) > _limit_bytes():
        return  # it would push out everything else, itself next
    tmp = None
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix=".tmp-", suffix=_SUFFIX)
        with os.fdopen(fd, "wb") as fh:
            members: dict[str, Any] = {"meta": np.array(payload), **arrays}
            np.savez(fh, **members)
        os.replace(tmp, folder / (key + _SUFFIX))
        tmp = None
        _evict(folder, _limit_bytes())
    except OSError:
        pass
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)


def _evict(folder: Path, limit: int) -> None:
    """Remove the least recently used entries until the folder holds at most ``limit`` bytes."""
    entries = []
    for p in folder.glob("*" + _SUFFIX):
        with contextlib.suppress(OSError):
            st = p.stat()
            entries.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in entries)
    for _, size, p in sorted(entries, key=lambda e: e[0]):
        if total <= limit:
            break
        with contextlib.suppress(OSError):
            p.unlink()
            total -= size


def cached(path: Path, rate_hz: float | None, read: Callable[[], Record]) -> Record:
    """``read()``'s record of ``path``, from the cache when this state of the file was read
    before."""
    hit = load(path, rate_hz)
    if hit is not None:
        return hit
    key = _key(path, rate_hz) if cache_dir() is not None else None
    record = read()
    store(path, rate_hz, record, key)
    return record
