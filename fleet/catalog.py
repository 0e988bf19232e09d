"""The fleet catalogue: a Parquet dataset with one row per recording and channel.

Layout: a folder of ``part-*.parquet`` files, all with :data:`SCHEMA`. Each run appends parts
and never rewrites one: a part is written under a hidden name (``.part-*.tmp``, which Parquet
readers skip) and renamed into place, so concurrent runs and a crash mid-write leave only
whole parts. Read it with ``pyarrow.dataset.dataset(DIR)``, ``pandas.read_parquet(DIR)`` or
DuckDB (``SELECT * FROM 'DIR/*.parquet'``).

Coefficients (the default model's ``N``, ``B``, ``K``) appear twice: in the channel's SI unit
(``N``, ``N_lo95``, ``N_hi95``, unit in ``N_si_unit``) and in the conventional unit
(``N_conv``..., unit in ``N_conv_unit``; deg/sqrt(h), deg/h, ... for gyros). A coefficient
whose 95 % interval reaches zero is not a measurement: its value is null, ``N_resolved`` is
false and ``N_hi95`` keeps the upper bound. A file that could not be analysed is one row with
``status = "failed"`` and its one-line ``error``.
"""

from __future__ import annotations

import os
import time
import uuid
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

COEFFICIENTS: tuple[str, ...] = ("N", "B", "K")
"""Coefficients of the default model (white, bias_instability, random_walk) kept per row."""


def _coefficient_fields(p: str) -> list[pa.Field]:
    return [pa.field(p, pa.float64()), pa.field(f"{p}_lo95", pa.float64()),
            pa.field(f"{p}_hi95", pa.float64()), pa.field(f"{p}_si_unit", pa.string()),
            pa.field(f"{p}_conv", pa.float64()), pa.field(f"{p}_conv_lo95", pa.float64()),
            pa.field(f"{p}_conv_hi95", pa.float64()), pa.field(f"{p}_conv_unit", pa.string()),
            pa.field(f"{p}_resolved", pa.bool_())]


SCHEMA = pa.schema(
    [pa.field("file", pa.string()), pa.field("file_hash", pa.string()),
     pa.field("file_size", pa.int64()), pa.field("file_mtime_ns", pa.int64()),
     pa.field("status", pa.string()), pa.field("error", pa.string()),
     pa.field("unit", pa.string()), pa.field("unit_source", pa.string()),
     pa.field("sensor_model", pa.string()), pa.field("topic", pa.string()),
     pa.field("channel", pa.string()), pa.field("kind", pa.string()),
     pa.field("start_time", pa.timestamp("us", tz="UTC")),
     pa.field("duration_s", pa.float64()), pa.field("fs_hz", pa.float64()),
     pa.field("n_samples", pa.int64()), pa.field("gaps", pa.int64()),
     pa.field("outliers", pa.int64()), pa.field("chi2_per_dof", pa.float64()),
     pa.field("model", pa.string())]
    + [f for p in COEFFICIENTS for f in _coefficient_fields(p)]
    + [pa.field("significant_suggestions", pa.list_(pa.string())),
       pa.field("diagnosed", pa.bool_()),
       pa.field("imunoise_version", pa.string()),
       pa.field("analysed_at", pa.timestamp("us", tz="UTC"))])
"""Columns of every part of the catalogue."""


class CatalogError(Exception):
    """The catalogue folder cannot be used (not a folder, unreadable parts)."""


def part_paths(folder: str | Path) -> list[Path]:
    """The catalogue's complete parts (hidden temporary files excluded), oldest name first."""
    return sorted(Path(folder).glob("part-*.parquet"))


def table_of(rows: Iterable[Mapping[str, Any]]) -> pa.Table:
    """Rows (dicts keyed by column; missing keys are nulls) as a table with :data:`SCHEMA`."""
    rows = list(rows)
    columns = {f.name: [r.get(f.name) for r in rows] for f in SCHEMA}
    return pa.Table.from_pydict(columns, schema=SCHEMA)


def write_part(folder: str | Path, rows: Iterable[Mapping[str, Any]]) -> Path | None:
    """Append rows to the catalogue as one new part, atomically; None when there are none."""
    table = table_of(rows)
    if table.num_rows == 0:
        return None
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    name = f"part-{time.strftime('%Y%m%dT%H%M%S', time.gmtime())}-{uuid.uuid4().hex[:12]}"
    tmp = folder / f".{name}.tmp"
    final = folder / f"{name}.parquet"
    try:
        pq.write_table(table, tmp, compression="zstd")
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, final)
    finally:
        tmp.unlink(missing_ok=True)
    return final


def read_catalog(folder: str | Path, columns: list[str] | None = None) -> pa.Table:
    """The whole catalogue (or some columns) as one table; an empty table with the schema when
    the folder has no parts. Raises CatalogError for a path that is not a folder."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise CatalogError(f"{folder}: the catalogue must be a folder")
    parts = part_paths(folder) if folder.is_dir() else []
    if not parts:
        return SCHEMA.empty_table().select(columns) if columns else SCHEMA.empty_table()
    try:
        return ds.dataset([str(p) for p in parts], schema=SCHEMA, format="parquet"
                          ).to_table(columns=columns)
    except (pa.ArrowInvalid, OSError) as exc:
        raise CatalogError(f"{folder}: unreadable catalogue part: {exc}") from None


@dataclass(frozen=True)
class Seen:
    """What the catalogue already holds, to skip files analysed before."""

    hashes: frozenset[str]
    """Content hashes of every file in the catalogue."""
    stamps: frozenset[tuple[str, int, int]]
    """(file, size, mtime_ns) of every file in the catalogue."""
    failed_hashes: frozenset[str]
    """Content hashes whose analysis failed (and never succeeded)."""
    failed_files: frozenset[str]
    """Files whose analysis failed (and never succeeded)."""

    def has_stamp(self, file: str, size: int, mtime_ns: int) -> bool:
        return (file, size, mtime_ns) in self.stamps


def seen(folder: str | Path) -> Seen:
    """Hashes and (file, size, mtime) stamps already in the catalogue."""
    t = read_catalog(folder, ["file", "file_hash", "file_size", "file_mtime_ns", "status"])
    cols = t.to_pydict()
    hashes = frozenset(h for h in cols["file_hash"] if h)
    stamps = frozenset((f, s, m) for f, s, m in zip(cols["file"], cols["file_size"],
                                                     cols["file_mtime_ns"], strict=True)
                       if f is not None and s is not None and m is not None)
    by_status: dict[str, dict[str, set[str]]] = {"ok": {"h": set(), "f": set()},
                                                   "failed": {"h": set(), "f": set()}}
    for f, h, st in zip(cols["file"], cols["file_hash"], cols["status"], strict=True):
        if st in by_status:
            if h:
                by_status[st]["h"].add(h)
            if f:
                by_status[st]["f"].add(f)
    ok, failed = by_status["ok"], by_status["failed"]
    return Seen(hashes=hashes, stamps=stamps, failed_hashes=frozenset(failed["h"] - ok["h"]),
                failed_files=frozenset(failed["f"] - ok["f"]))
