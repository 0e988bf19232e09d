"""``imunoise fleet``: analyse many recordings on Dask into a Parquet catalogue.

Every recording (MCAP, rosbag2 folder, ROS 1 bag, CSV; paths, globs, folders or fsspec URLs)
is analysed as ``imunoise analyze`` would, plus the diagnosis of each channel, on a Dask
distributed cluster: a local one (one process per core) by default, or an existing one with
``--scheduler tcp://HOST:PORT``. Workers open each file where it lies: paths must be valid on
the workers. Results go to the catalogue folder as Parquet parts, one row per file and
channel; a file that fails is a row with its error. Files already in the catalogue (same
content hash, or the same path, size and modification time) are skipped, so an interrupted run
is resumed by running it again.
"""

from __future__ import annotations

import argparse
import glob
import itertools
import logging
import os
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from imunoise.errors import UsageError

RECORDING_SUFFIXES = (".mcap", ".bag", ".csv")
IN_FLIGHT_PER_WORKER = 4
"""Futures kept submitted per worker: enough to keep workers busy, few enough that the client's
memory does not grow with the number of files."""
WORKER_CONFIG = {"distributed.worker.profile.enabled": False}
"""Dask settings of the local cluster's workers. Dask's statistical profiler keeps the stack
samples of every task; with tasks of ten seconds it held about 3 MB more per file analysed
(a worker at 630 MB after 100 files, 357 MB without it). Workers of an existing cluster should
be started with ``DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False`` for the same reason."""
FLUSH_ROWS = 2000
FLUSH_SECONDS = 30.0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fleet", help="many recordings on Dask into a Parquet catalogue",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="+", metavar="FILES-OR-GLOBS",
                   help="recordings, folders searched for recordings, globs ('**' recurses) "
                        "or fsspec URLs (s3://... needs s3fs)")
    p.add_argument("--catalog", required=True, metavar="DIR",
                   help="catalogue folder (Parquet parts; created when missing)")
    p.add_argument("--scheduler", metavar="ADDR",
                   help="address of a running Dask scheduler, e.g. tcp://10.0.0.5:8786 "
                        "(default: a local cluster)")
    p.add_argument("--connect-timeout", type=float, default=20.0, metavar="S",
                   help="seconds to wait for the scheduler (default 20)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local cluster size in processes (default: one per core)")
    p.add_argument("--unit", metavar="REGEX",
                   help="unit identity from the file path: the first group of REGEX (or the "
                        "whole match), e.g. 'imu-(\\w+)/'; default: the recording's metadata "
                        "(unit, unit_id, serial), else the file name")
    p.add_argument("--static", choices=("auto", "all"), default="auto",
                   help="auto: analyse the still stretches only (default); all: every sample")
    p.add_argument("--no-diagnose", action="store_true",
                   help="skip the per-channel diagnosis (faster; no significant_suggestions)")
    p.add_argument("--retry-failed", action="store_true",
                   help="analyse again the files whose earlier analysis failed")
    p.set_defaults(func=run)


def _has_magic(text: str) -> bool:
    return any(c in text for c in "*?[")


def _recordings_in(folder: Path) -> Iterator[Path]:
    """Recordings under a folder: rosbag2 folders (with metadata.yaml) as wholes, and files
    with a recording suffix outside them."""
    if (folder / "metadata.yaml").is_file():
        yield folder
        return
    for entry in sorted(folder.iterdir()):
        if entry.is_dir():
            yield from _recordings_in(entry)
        elif entry.suffix.lower() in RECORDING_SUFFIXES:
            yield entry


def _expand_url(text: str) -> list[str]:
    import fsspec

    fs, path = fsspec.core.url_to_fs(text)
    paths = fs.glob(path) if _has_magic(path) else [path]
    out = []
    for p in paths:
        if fs.isdir(p) and not fs.exists(f"{p.rstrip('/')}/metadata.yaml"):
            out += [q for q in fs.find(p) if q.lower().endswith(RECORDING_SUFFIXES)]
        else:
            out.append(p)
    return [fs.unstrip_protocol(p) for p in out]


def expand_inputs(inputs: Iterable[str]) -> list[str]:
    """Locations to analyse, in order, without repeats: absolute local paths or URLs.

    Raises UsageError when nothing matches at all."""
    from imunoise.fleet_task import is_url

    found: list[str] = []
    for text in inputs:
        if is_url(text):
            found += _expand_url(text)
            continue
        text = text.removeprefix("file://")
        matches = [Path(m) for m in sorted(glob.glob(text, recursive=True))] \
            if _has_magic(text) else [Path(text)]
        for m in matches:
            if m.is_dir():
                found += [str(p.resolve()) for p in _recordings_in(m)]
            elif m.exists() or not _has_magic(text):
                found.append(str(m.resolve()))  # a missing file becomes a failed row
    unique = list(dict.fromkeys(found))
    if not unique:
        raise UsageError("fleet: no recording matches " + " ".join(map(repr, inputs)))
    return unique


def _client(args: argparse.Namespace):
    """A Dask client on the given scheduler or on a new local cluster."""
    from distributed import Client, LocalCluster

    if args.scheduler:
        try:
            return Client(args.scheduler, timeout=f"{args.connect_timeout}s")
        except (OSError, TimeoutError) as exc:
            raise UsageError(f"fleet: cannot reach the Dask scheduler {args.scheduler}: "
                             f"{exc}") from None
    import dask

    n = args.workers or os.cpu_count() or 1
    with dask.config.set(WORKER_CONFIG):
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               silence_logs=logging.ERROR, dashboard_address=":0")
    return Client(cluster)


def _pending(locations: list[str], seen: Any, retry_failed: bool) -> tuple[list[str], int]:
    """Locations not yet catalogued (by path, size and mtime) and the count skipped."""
    from imunoise.fleet_task import _stat

    todo, skipped = [], 0
    for loc in locations:
        size, mtime = _stat(loc)
        if size is not None and mtime is not None and seen.has_stamp(loc, size, mtime):
            if not (retry_failed and loc in seen.failed_files):
                skipped += 1
                continue
        todo.append(loc)
    return todo, skipped


class _Sink:
    """Rows waiting to be written as one catalogue part (bounded: flushed by count and age)."""

    def __init__(self, folder: str) -> None:
        self.folder = folder
        self.rows: list[dict] = []
        self.parts = 0
        self.last = time.monotonic()

    def add(self, rows: list[dict]) -> None:
        self.rows += rows
        if len(self.rows) >= FLUSH_ROWS or time.monotonic() - self.last > FLUSH_SECONDS:
            self.flush()

    def flush(self) -> None:
        from imunoise.fleet.catalog import write_part

        if write_part(self.folder, self.rows) is not None:
            self.parts += 1
        self.rows = []
        self.last = time.monotonic()


def _run_on(client: Any, todo: list[str], args: argparse.Namespace, known: frozenset[str],
            sink: _Sink) -> dict[str, int]:
    """Submit the files with a bounded window of futures; write rows as they come back."""
    from distributed import as_completed

    from imunoise import __version__
    from imunoise.fleet_task import analyse_file, failed_row
    from imunoise.progress import progress_bar

    workers = max(1, len(client.scheduler_info().get("workers", {})))
    window = IN_FLIGHT_PER_WORKER * workers
    known_f = client.scatter([known], broadcast=True)[0]  # one object, not its items
    counts = {"ok": 0, "failed": 0, "skipped": 0, "worker_peak_mb": 0}
    queue = iter(todo)

    where: dict[str, str] = {}  # future key -> location, for a task that is lost
    resubmitted: set[str] = set()  # locations whose task the cluster cancelled once

    def submit(loc: str):
        fut = client.submit(analyse_file, loc, version=__version__, unit_pattern=args.unit,
                            static=args.static, diagnose=not args.no_diagnose,
                            known_hashes=known_f, pure=False, retries=1)
        where[fut.key] = loc
        return fut

    first = [submit(loc) for loc in itertools.islice(queue, window)]
    running = as_completed(first, with_results=False)
    with progress_bar(sys.stderr.isatty() or bool(os.environ.get("IMUNOISE_PROGRESS"))) as bar:
        task = bar.add_task("analysing", total=len(todo))
        for fut in running:
            try:
                out = fut.result()
                rows, status = out.rows, out.status
                counts["worker_peak_mb"] = max(counts["worker_peak_mb"],
                                               int(out.worker_peak_mb))
            except Exception as exc:  # noqa: BLE001 - a lost task (killed worker) is a row
                loc = where.get(fut.key, "unknown file (task lost)")
                if "Cancelled" in type(exc).__name__ and loc in where.values() \
                        and loc not in resubmitted:
                    # the cluster cancelled it (a worker holding its inputs died): that is
                    # no verdict on the file, which gets one more run
                    resubmitted.add(loc)
                    where.pop(fut.key, None)
                    fut.release()
                    running.add(submit(loc))
                    continue
                rows = [failed_row(loc, None, f"{type(exc).__name__}: {exc}", __version__)]
                status = "failed"
            counts[status] += 1
            where.pop(fut.key, None)
            sink.add(rows)
            fut.release()
            bar.update(task, description=f"analysing ({counts['failed']} failed)")
            bar.advance(task)
            nxt = next(queue, None)
            if nxt is not None:
                running.add(submit(nxt))
    return counts


def run(args: argparse.Namespace) -> int:
    from imunoise.extras import require

    require("fleet", "imunoise fleet")
    from imunoise.fleet.catalog import CatalogError, seen

    if args.workers is not None and args.workers < 1:
        raise UsageError("fleet: --workers must be at least 1")
    locations = expand_inputs(args.inputs)
    try:
        already = seen(args.catalog)
    except CatalogError as exc:
        raise UsageError(f"fleet: {exc}") from None
    todo, skipped = _pending(locations, already, args.retry_failed)
    known = already.hashes - (already.failed_hashes if args.retry_failed else frozenset())
    sink = _Sink(args.catalog)
    counts = {"ok": 0, "failed": 0, "skipped": 0}
    if todo:
        client = _client(args)
        try:
            if not args.scheduler and client.dashboard_link:
                print(f"Dask dashboard: {client.dashboard_link}", file=sys.stderr)
            counts = _run_on(client, todo, args, known, sink)
        finally:
            sink.flush()
            cluster = getattr(client, "cluster", None)
            client.close()
            if cluster is not None and not args.scheduler:
                cluster.close()
    counts["skipped"] += skipped
    peak = f"; worker peak memory {counts['worker_peak_mb']} MB" \
        if counts.get("worker_peak_mb") else ""
    print(f"{len(locations)} recording(s): {counts['ok']} analysed, {counts['failed']} failed, "
          f"{counts['skipped']} already in the catalogue -> {args.catalog}{peak}",
          file=sys.stderr)
    return 0
