"""One recording of a fleet, analysed where it lies: the catalogue rows of a file.

This runs on a Dask worker. The worker opens the path or URL itself (a URL that is not a local
file is copied by fsspec into the worker's temporary folder first, since the readers need
random access), hashes the content, and, unless the hash is already catalogued, runs exactly
what ``imunoise analyze`` runs (still stretches, overlapping Allan deviation, the default
model fit with 95 % intervals) plus, by default, the diagnosis of each channel. Whatever goes
wrong with one file becomes one failed row with a one-line error; it never stops the fleet.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
import resource
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from imunoise.core.units import channel_kind, conventional, si_unit

HASH_CHUNK = 1 << 20
UNIT_KEYS = ("unit", "unit_id", "serial", "serial_number", "device_serial")
"""Metadata keys (also with the recorder's ``config.`` prefix) naming the unit of a file."""
MODEL_KEYS = ("sensor_model", "model", "device")
"""Metadata keys naming the sensor model, first found wins."""


@dataclass
class FileOutcome:
    """What one file gave: ``status`` is ``ok``, ``failed`` or ``skipped`` (hash known)."""

    location: str
    status: str
    file_hash: str | None = None
    rows: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    error: str | None = None
    worker_peak_mb: float = 0.0
    """Peak resident memory of the worker process so far (MB)."""


def is_url(location: str) -> bool:
    """True for ``protocol://...`` locations other than ``file://``."""
    return "://" in location and not location.startswith("file://")


def local_path(location: str) -> str:
    return location.removeprefix("file://")


def content_hash(path: str | Path) -> str:
    """BLAKE2b-128 of a file's bytes, or of a folder's (rosbag2) files' names and bytes in
    sorted order, as hex."""
    path = Path(path)
    h = hashlib.blake2b(digest_size=16)
    files = sorted(p for p in path.rglob("*") if p.is_file()) if path.is_dir() else [path]
    for p in files:
        if path.is_dir():
            h.update(str(p.relative_to(path)).encode() + b"\0")
        with open(p, "rb") as f:
            while chunk := f.read(HASH_CHUNK):
                h.update(chunk)
    return h.hexdigest()


@contextlib.contextmanager
def opened_locally(location: str) -> Iterator[str]:
    """A local path for ``location``: the path itself, or a temporary copy of a URL (fsspec;
    ``s3://`` needs s3fs), removed afterwards."""
    if not is_url(location):
        yield local_path(location)
        return
    import fsspec

    fs, path = fsspec.core.url_to_fs(location)
    with tempfile.TemporaryDirectory(prefix="imunoise-fleet-") as tmp:
        target = os.path.join(tmp, os.path.basename(path.rstrip("/")) or "recording")
        fs.get(path, target, recursive=fs.isdir(path))
        yield target


def unit_of(location: str, metadata: dict[str, str], pattern: str | None) -> tuple[str, str]:
    """The unit a file belongs to and where that came from: the ``--unit`` regular expression
    applied to the location (its first group, or the whole match), else the recording's
    metadata, else the file's name without extension."""
    if pattern:
        m = re.search(pattern, location)
        if m:
            return (m.group(1) if m.groups() else m.group(0)), "pattern"
    for key in UNIT_KEYS:
        for k in (key, f"config.{key}"):
            if metadata.get(k):
                return str(metadata[k]), f"metadata {k}"
    name = os.path.basename(location.rstrip("/"))
    return name.split(".")[0] or name, "file name"


def sensor_model_of(metadata: dict[str, str]) -> str:
    for key in MODEL_KEYS:
        for k in (key, f"config.{key}"):
            if metadata.get(k):
                return str(metadata[k])
    return "unknown"


def _stat(location: str) -> tuple[int | None, int | None]:
    if is_url(location):
        return None, None
    try:
        st = os.stat(local_path(location))
    except OSError:
        return None, None
    return int(st.st_size), int(st.st_mtime_ns)


def _coefficient_columns(model: list[dict], kind: str) -> dict[str, Any]:
    """``N``, ``N_lo95``, ... of the default model's terms (SI and conventional units)."""
    out: dict[str, Any] = {}
    for term in model:
        for p, v in (term.get("params") or {}).items():
            if p not in ("N", "B", "K"):
                continue
            lo, hi = (term.get("ci95") or {}).get(p, [None, None])
            resolved = v is not None and lo is not None and lo > 0.0
            unit, factor = conventional(p, kind)
            out[f"{p}_si_unit"] = si_unit(p, kind)
            out[f"{p}_conv_unit"] = unit
            out[f"{p}_resolved"] = bool(resolved)
            out[f"{p}_hi95"] = hi
            out[f"{p}_conv_hi95"] = hi * factor if hi is not None else None
            # an interval reaching zero is no measurement: no value, only the upper bound
            out[p] = v if resolved else None
            out[f"{p}_lo95"] = lo if resolved else None
            out[f"{p}_conv"] = v * factor if resolved else None
            out[f"{p}_conv_lo95"] = lo * factor if resolved else None
    return out


def _base_row(location: str, digest: str | None, version: str) -> dict[str, Any]:
    size, mtime = _stat(location)
    return {"file": location, "file_hash": digest, "file_size": size, "file_mtime_ns": mtime,
            "imunoise_version": version, "analysed_at": datetime.now(UTC)}


def failed_row(location: str, digest: str | None, error: str, version: str) -> dict[str, Any]:
    row = _base_row(location, digest, version)
    row.update(status="failed", error=error.splitlines()[0] if error else "failed")
    return row


def _significant(record: Any, key: str) -> list[str]:
    from imunoise.pipeline.channel_extras import suggestions

    return [s["term"] for s in suggestions(record, key) if s.get("significant")]


def channel_rows(location: str, path: str, digest: str, version: str,
                 unit_pattern: str | None, static: str, diagnose: bool) -> list[dict[str, Any]]:
    """The catalogue rows of every IMU channel of one local recording (numbers as
    ``imunoise analyze --json`` gives them)."""
    from imunoise.analysis.default_model import DEFAULT_MODEL_TEXT
    from imunoise.analysis.evidence.outliers import outlier_indices
    from imunoise.pipeline.channel_analysis import analyze_record
    from imunoise.pipeline.documents import analysis_json
    from imunoise.pipeline.reading import read_record, select

    record = read_record(path, None, static)
    keys = [k for k in select(record, []) if k != "temp"]
    if not keys:
        raise ValueError("no IMU channel in the recording")
    results = analyze_record(record, keys, show_progress=False)
    doc = analysis_json(path, record, results)
    unit, unit_source = unit_of(location, record.metadata, unit_pattern)
    base = _base_row(location, digest, version)
    base.update(status="ok", unit=unit, unit_source=unit_source,
                sensor_model=sensor_model_of(record.metadata))
    rows = []
    for r in results:
        ch = doc["channels"][r.key]
        kind = channel_kind(r.key)
        s = r.series
        row = dict(base)
        topic, _, name = r.key.rpartition(":")
        row.update(topic=topic or None, channel=name, kind=kind,
                   start_time=datetime.fromtimestamp(float(s.t0_s), UTC),
                   duration_s=float(s.duration_s), fs_hz=float(s.fs_hz),
                   n_samples=int(s.n_samples), gaps=int(len(s.segment_starts) - 1),
                   outliers=int(outlier_indices(s.segments()).size),
                   chi2_per_dof=(ch.get("error") or {}).get("chi2_per_dof"),
                   model=DEFAULT_MODEL_TEXT, diagnosed=False, significant_suggestions=[])
        row.update(_coefficient_columns(ch.get("model") or [], kind))
        if r.fit is None:
            row["error"] = "; ".join(r.warnings) or "no model fit"
        elif diagnose:
            row["significant_suggestions"] = _significant(record, r.key)
            row["diagnosed"] = True
        rows.append(row)
    return rows


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def analyse_file(location: str, *, version: str, unit_pattern: str | None = None,
                 static: str = "auto", diagnose: bool = True,
                 known_hashes: frozenset[str] = frozenset()) -> FileOutcome:
    """Analyse one recording into catalogue rows; never raises for a bad file."""
    out = _analyse(location, version, unit_pattern, static, diagnose, known_hashes)
    out.worker_peak_mb = _peak_mb()
    return out


def _analyse(location: str, version: str, unit_pattern: str | None, static: str,
             diagnose: bool, known_hashes: frozenset[str]) -> FileOutcome:
    t = time.perf_counter()
    digest = None
    try:
        with opened_locally(location) as path:
            digest = content_hash(path)
            if digest in known_hashes:
                return FileOutcome(location, "skipped", digest,
                                   seconds=time.perf_counter() - t)
            with np.errstate(all="ignore"):
                rows = channel_rows(location, path, digest, version, unit_pattern, static,
                                    diagnose)
        return FileOutcome(location, "ok", digest, rows, time.perf_counter() - t)
    except Exception as exc:  # noqa: BLE001 - one bad file is one failed row, never the fleet
        message = str(exc).strip() or type(exc).__name__
        error = f"{type(exc).__name__}: {message}" if not _is_usage(exc) else message
        return FileOutcome(location, "failed", digest,
                           [failed_row(location, digest, error, version)],
                           time.perf_counter() - t, error.splitlines()[0])


def _is_usage(exc: BaseException) -> bool:
    from imunoise.errors import UsageError

    return isinstance(exc, UsageError)
