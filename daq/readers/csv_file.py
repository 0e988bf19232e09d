"""CSV recordings: one header row, a time column ``t`` in seconds (or a given rate), channel
columns ``gyro_x gyro_y gyro_z`` (rad/s) and ``accel_x accel_y accel_z`` (m/s^2), any subset, and
``temp`` (degC). Other columns are ignored.

How imperfect files are read (each case adds a one-line warning to the record):

- the time stamps go through the shared timing model (:mod:`imunoise.core.timing`): samples really
  missing start a new segment, which the estimators never bridge; jittered stamps are re-timed
  on the sample grid and the jitter is reported;
- time going backwards or repeating also starts a new segment (the samples are kept);
- rows whose ``t`` is not a finite number are dropped (they cannot be placed in time);
- a NaN, an infinite or an empty channel value removes that sample from that channel only and
  splits the channel's segment around it;
- an incomplete last line (a logger killed mid-write) is dropped.

Anything else that is malformed (no known channel columns, text where a number should be, a row
with a different number of fields, binary data) is a :class:`ReadError` naming the line.

The EuRoC/ASL layout of ``imu0/data.csv`` (EuRoC MAV, TUM-VI and most VIO datasets) is recognised
by its header, ``#timestamp [ns],w_RS_S_x [rad s^-1],...,a_RS_S_z [m s^-2]``: time stamps in
nanoseconds, ``w_RS_S_*`` the gyro in rad/s and ``a_RS_S_*`` the accelerometer in m/s^2. The
dataset's ``sensor.yaml`` beside the file, when present, is read into the record's metadata
(``dataset_*`` keys) so that its stated noise figures can be shown next to the measured ones.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import numpy as np

from imunoise.core.record import TEMPERATURE_KEY, Record
from imunoise.core.series import (
    SAMPLE_LIMIT,
    TIME_LIMIT_S,
    ChannelSeries,
    channel_units,
    usable_samples,
    usable_times,
)
from imunoise.core.timing import Timing, analyse_stamps
from imunoise.daq.errors import ReadError, quoted

TIME_COLUMN = "t"
CHANNEL_COLUMNS = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z")
# EuRoC/ASL column names (lower case, units stripped) -> ours; their time stamps are in ns.
ASL_COLUMNS = {"timestamp": TIME_COLUMN,
               "w_rs_s_x": "gyro_x", "w_rs_s_y": "gyro_y", "w_rs_s_z": "gyro_z",
               "a_rs_s_x": "accel_x", "a_rs_s_y": "accel_y", "a_rs_s_z": "accel_z"}
ASL_TIME_SCALE = 1e-9  # ns -> s
# Keys of the dataset's sensor.yaml shown beside the measured values (Kalibr's noise model).
SENSOR_YAML_KEYS = ("rate_hz", "gyroscope_noise_density", "gyroscope_random_walk",
                    "accelerometer_noise_density", "accelerometer_random_walk")
_UNITS_SUFFIX = re.compile(r"\s*\[[^\]]*\]\s*$")
_DELIMITERS = (",", ";", "\t")
FAST_PARSE_MIN_BYTES = 1 << 20
"""Smallest body read by the fast parser (:mod:`imunoise.daq.readers.csv_numbers`): below it,
importing pyarrow costs more than np.loadtxt."""
# Inferred rates outside this range usually mean a time column in ms, us or ns.
_PLAUSIBLE_RATE_HZ = (0.5, 1e5)
_ROW_ERROR = re.compile(r"at row (\d+)")
_NON_SPACE = re.compile(rb"\S")
_EMPTY_FIELD = re.compile(rb"(?<=[,;\t])(?=[,;\t\r\n])|^(?=[,;\t])|(?<=[,;\t])$", re.MULTILINE)


def _header(data: bytes, path: Path) -> tuple[list[str], str, int]:
    """Column names, delimiter and the byte offset where the data rows start."""
    end = data.find(b"\n")
    line = data if end < 0 else data[:end]
    body_start = len(data) if end < 0 else end + 1
    if b"\x00" in data[:4096]:
        raise ReadError(f"{path}: not a CSV file (binary data)")
    try:
        text = line.decode("utf-8-sig").strip()
    except UnicodeDecodeError:
        raise ReadError(f"{path}: not a CSV file (header is not text)") from None
    delim = next((d for d in _DELIMITERS if d in text), ",")
    names = [n.strip().strip('"').strip("'").strip().lower() for n in text.split(delim)]
    return names, delim, body_start


def _asl_names(names: list[str]) -> list[str] | None:
    """Our column names for an EuRoC/ASL header (``#timestamp [ns], w_RS_S_x [rad s^-1], ...``),
    or None when the header is not of that layout."""
    bare = [_UNITS_SUFFIX.sub("", n.lstrip("#").strip()) for n in names]
    if not bare or bare[0] != "timestamp" or not any(b in ASL_COLUMNS for b in bare[1:]):
        return None
    return [ASL_COLUMNS.get(b, b) for b in bare]


def _asl_seconds(data: bytes, delim: str, t_ns: np.ndarray) -> tuple[np.ndarray, float]:
    """EuRoC/ASL nanosecond stamps as seconds after the first one, and that first one (s).

    A float64 holds a stamp near 1.4e18 ns, or 1.4e9 s, only to about 250 ns, which biases the
    rate in the ninth digit; the stamps are read again as integers and differenced before
    scaling. Falls back to the float values when a stamp is not an integer (the reader's other
    checks then apply).
    """
    try:
        ns = np.loadtxt(io.BytesIO(data), delimiter=delim, usecols=[0], dtype=np.int64, ndmin=1,
                        comments=None, skiprows=1)
    except ValueError:
        ns = None
    limit = int(TIME_LIMIT_S / ASL_TIME_SCALE)
    if (ns is not None and ns.size == t_ns.size and ns.size
            and np.all((ns >= -limit) & (ns <= limit))):
        return (ns - ns[0]).astype(np.float64) * ASL_TIME_SCALE, int(ns[0]) * ASL_TIME_SCALE
    t = t_ns * ASL_TIME_SCALE
    good = usable_times(t)  # the others are dropped with their rows
    first = float(t[good][0]) if good.any() else 0.0
    return np.where(good, t - first, np.nan), first


def _sensor_yaml(path: Path, warnings: list[str]) -> dict[str, str]:
    """The stated noise figures of an EuRoC/ASL ``sensor.yaml`` beside ``path`` (``dataset_*``
    metadata keys), or nothing when there is none."""
    yaml_path = path.parent / "sensor.yaml"
    if not yaml_path.is_file():
        return {}
    import yaml

    try:
        doc = yaml.safe_load(yaml_path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        warnings.append(f"{yaml_path}: not read ({str(exc).splitlines()[0]})")
        return {}
    if not isinstance(doc, dict):
        return {}
    out = {"dataset_sensor_yaml": str(yaml_path)}
    for key in SENSOR_YAML_KEYS:
        value = doc.get(key)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            out[f"dataset_{key}"] = f"{float(value):.9g}"
    return out


def _split_channel(values: np.ndarray, seg_flags: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                        int]:
    """Drop samples that are not finite or beyond :data:`imunoise.core.series.SAMPLE_LIMIT`
    (lost samples); a segment starts where ``seg_flags`` says or after a dropped one.

    Returns the kept values, their segment starts and the number dropped.
    """
    bad = ~usable_samples(values)
    n_bad = int(bad.sum())
    if n_bad == 0:
        return values, np.flatnonzero(seg_flags).astype(np.int64), 0
    keep = ~bad
    flags = seg_flags.copy()
    flags[1:] |= bad[:-1]
    new_index = np.cumsum(keep) - 1
    starts = new_index[flags & keep]
    return values[keep], starts.astype(np.int64), n_bad


def _load(text: bytes, usecols: list[int], delim: str, n_fields: int, path: Path
          ) -> np.ndarray:
    """Parse the rows after the header line of ``text`` (the whole file; ``n_fields`` fields
    per row): the fast parser where it reads the rows as np.loadtxt would, else np.loadtxt."""
    end = text.find(b"\n")
    if end >= 0 and len(text) - end > FAST_PARSE_MIN_BYTES:
        from imunoise.daq.readers.csv_numbers import parse_numbers  # imports pyarrow

        fast = parse_numbers(memoryview(text)[end + 1:], n_fields, usecols, delim)
        if fast is not None:
            return fast

    def attempt(buf: bytes) -> np.ndarray:
        return np.loadtxt(io.BytesIO(buf), delimiter=delim, usecols=usecols, dtype=np.float64,
                          ndmin=2, comments=None, encoding="utf-8", skiprows=1)

    try:
        try:
            return attempt(text)
        except ValueError as exc:
            if "string ''" not in str(exc):
                raise
            # empty fields are missing values: read them as NaN
            return attempt(_EMPTY_FIELD.sub(b"nan", text))
    except (ValueError, UnicodeDecodeError) as exc:
        found = _locate_bad_line(text, usecols, delim)
        msg = found if found else quoted(_ROW_ERROR.sub("", str(exc).split(";")[0]).strip(), 80)
        raise ReadError(f"{path}: bad CSV data: {msg}") from None


def _locate_bad_line(text: bytes, usecols: list[int], delim: str) -> str | None:
    """Describe the first data line the fast parser rejected (error path only)."""
    need = max(usecols) + 1
    d = delim.encode()
    for number, line in enumerate(text.split(b"\n")[1:], start=2):
        fields = line.rstrip(b"\r").split(d)
        if len(fields) == 1 and not fields[0].strip():
            continue
        if len(fields) < need:
            return f"line {number} has {len(fields)} field(s), expected at least {need}"
        for c in usecols:
            value = fields[c].strip()
            try:
                float(value or b"nan")
            except ValueError:
                return f"line {number}, column {c + 1}: {quoted(value, 20)} is not a number"
    return None


def _blank(data: bytes, start: int = 0) -> bool:
    return _NON_SPACE.search(data, start) is None


def _drop_incomplete_last_line(data: bytes, body_start: int, delim: str, n_names: int,
                               warnings: list[str]) -> bytes:
    """Drop the last line if it has fewer fields than the line before it (or the header).

    ``data`` is the whole file; the data rows begin at ``body_start``. Copies only when a line
    is dropped.
    """
    end = len(data)
    while end > body_start and data[end - 1] in b"\r\n":
        end -= 1
    cut = data.rfind(b"\n", body_start, end)
    d = delim.encode()
    if cut >= 0:
        prev_start = data.rfind(b"\n", body_start, cut) + 1 or body_start
        expected = data.count(d, max(prev_start, body_start), cut)
        last_start = cut + 1
    else:
        expected = n_names - 1
        last_start = body_start
    if data.count(d, last_start, end) < expected:
        warnings.append("last line is incomplete (file cut off while writing); dropped")
        return data[:last_start]
    return data


def _shown(name: str) -> str:
    """A column name for a message: as is when short and printable, else quoted and cut."""
    return name if len(name) <= 24 and name.isprintable() else quoted(name, 24)


def _columns(names: list[str], path: Path) -> list[str]:
    """The IMU channel columns of a header; duplicates or none at all are a ReadError."""
    if len(set(names)) != len(names):
        dup = sorted({n for n in names if names.count(n) > 1})
        raise ReadError(f"{path}: duplicate column(s) "
                        f"{', '.join(_shown(n) for n in dup[:4])}")
    channels = [c for c in CHANNEL_COLUMNS if c in names]
    if not channels:
        shown = ", ".join(_shown(n) for n in names[:6] if n) or "(none)"
        raise ReadError(f"{path}: no IMU channel columns (expected some of "
                        f"{', '.join(CHANNEL_COLUMNS)}; found {shown})")
    return channels


def _timing(cols: dict[str, np.ndarray], t_offset: float, rate_hz: float | None, path: Path,
            warnings: list[str]) -> tuple[dict[str, np.ndarray], Timing, float]:
    """Rows without a valid time dropped, the timing of the rest (:mod:`imunoise.core.timing`) and
    the
    record's start time (s). ``t_offset`` is added to ``t`` for absolute time."""
    t = cols[TIME_COLUMN]
    good_t = usable_times(t)
    if not good_t.all():
        warnings.append(f"{int((~good_t).sum())} row(s) without a valid time (not finite or "
                        f"beyond {TIME_LIMIT_S:g} s) dropped")
        cols = {k: v[good_t] for k, v in cols.items()}
        t = cols[TIME_COLUMN]
    if len(t) < 2:
        raise ReadError(f"{path}: need at least two rows with valid times")
    try:
        timing = analyse_stamps(t, rate_hz=rate_hz)
    except ValueError as exc:
        raise ReadError(f"{path}: {exc}") from None
    if rate_hz is None and not _PLAUSIBLE_RATE_HZ[0] <= timing.fs_hz <= _PLAUSIBLE_RATE_HZ[1]:
        warnings.append(f"sampling rate from 't' is {timing.fs_hz:.6g} Hz: is 't' in seconds?")
    warnings.extend(timing.notes)
    return cols, timing, float(t[0]) + t_offset


def _series(name: str, values: np.ndarray, seg_flags: np.ndarray, fs: float, t0: float,
            warnings: list[str]) -> ChannelSeries | None:
    """One column as a series (non-finite values removed, segments split around them)."""
    kept, seg_starts, n_bad = _split_channel(values, seg_flags)
    if n_bad:
        huge = bool(np.any(np.isfinite(values) & (np.abs(values) > SAMPLE_LIMIT)))
        what = f" or beyond {SAMPLE_LIMIT:g}" if huge else ""
        warnings.append(f"{name}: {n_bad} missing or non-finite{what} value(s) removed; "
                        "segments split around them")
    if kept.size == 0:
        warnings.append(f"{name}: no valid values; channel left out")
        return None
    return ChannelSeries(name=name, units=channel_units(name), fs_hz=fs, values=kept,
                         segment_starts=seg_starts, t0_s=t0)


def read_csv(path: str | Path, rate_hz: float | None = None) -> Record:
    """Read an IMU CSV file into a :class:`Record` (SI units, gap-free segments).

    Args:
        path: the CSV file.
        rate_hz: nominal sampling rate in Hz. Required when there is no ``t`` column; with one,
            it replaces the rate inferred from the median time step.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ReadError(f"{path}: cannot read ({exc.strerror or exc})") from None
    if _blank(data):
        raise ReadError(f"{path}: empty file")
    names, delim, body_start = _header(data, path)
    asl = _asl_names(names)
    names = asl if asl is not None else names
    channels = _columns(names, path)
    has_t = TIME_COLUMN in names
    if not has_t and rate_hz is None:
        raise ReadError(f"{path}: no time column 't'; give the sampling rate with --rate HZ")
    has_temp = TEMPERATURE_KEY in names

    warnings: list[str] = []
    data = _drop_incomplete_last_line(data, body_start, delim, len(names), warnings)
    if _blank(data, body_start):
        raise ReadError(f"{path}: no data rows after the header")

    wanted = ([TIME_COLUMN] if has_t else []) + channels + ([TEMPERATURE_KEY] if has_temp else [])
    table = _load(data, [names.index(c) for c in wanted], delim, len(names), path)
    cols = dict(zip(wanted, np.ascontiguousarray(table.T), strict=True))

    facts: dict = {}
    if has_t:
        t_offset = 0.0  # seconds to add to t for the absolute time of the record's start
        if asl is not None:
            cols[TIME_COLUMN], t_offset = _asl_seconds(data, delim, cols[TIME_COLUMN])
        cols, timing, t0 = _timing(cols, t_offset, rate_hz, path, warnings)
        fs, starts = timing.fs_hz, timing.segment_starts
        facts = {"timing": {"csv": timing.facts()}}
    else:
        # rate_hz is given on this branch (no time column); mypy cannot see it
        fs, starts, t0 = float(rate_hz), np.zeros(1, dtype=np.int64), 0.0  # type: ignore[arg-type]
    seg_flags = np.zeros(len(next(iter(cols.values()))), dtype=bool)
    seg_flags[starts] = True

    out = {name: s for name in channels
           if (s := _series(name, cols[name], seg_flags, fs, t0, warnings)) is not None}
    if not out:
        raise ReadError(f"{path}: no valid values in any IMU channel")
    temperature = (_series(TEMPERATURE_KEY, cols[TEMPERATURE_KEY], seg_flags, fs, t0, warnings)
                   if has_temp else None)
    metadata = {"format": "euroc-asl csv" if asl is not None else "csv",
                "rows": str(table.shape[0]), "columns": ",".join(wanted), "fs_hz": f"{fs:.9g}"}
    if asl is not None:
        metadata.update(_sensor_yaml(path, warnings))
    ignored = [n for n in names if n not in wanted]
    if ignored:
        metadata["ignored_columns"] = ",".join(ignored)
    return Record(source=str(path), channels=out, temperature=temperature, metadata=metadata,
                  warnings=warnings, facts=facts)
