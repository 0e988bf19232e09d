"""Damaged-file fuzzing: small seed recordings in every format imunoise reads, a seeded mutation
engine, and the checks that every command exits cleanly on what it produces.

Used by ``tests/imunoise/test_damaged_files.py`` (a few hundred cases, in-process) and by
``bench/fuzz.py`` (thousands, each case in a forked process with a time limit).

A seed is a file (or a rosbag2 folder) written by an independent writer where one exists: the
official ``mcap`` writer (zstd, lz4, uncompressed chunks, no chunks), imunoise's own recorder,
rosbags (rosbag2 MCAP and sqlite3, ROS 1 bags with and without compression), and the CSV and
EuRoC/ASL layouts. Content mutants (non-finite and huge values, backward, repeated and
never-increasing times, huge stamps) are written by those writers from altered signals; byte
mutants (flips, truncations, zeroed, duplicated and deleted ranges, huge length fields, broken
``metadata.yaml``) alter the bytes of a seed.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import struct
import time
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

N_SAMPLES = 400
FS_HZ = 100.0
T0_NS = 1_600_000_000 * 10**9
CHUNK_BYTES = 16 * 1024  # several chunks per seed: damage lands in the middle, not the tail
MAX_MESSAGE = 300  # characters of an exit-2 message, "imunoise: " included
MCAP_FORMATS = ("mcap-imunoise", "mcap-zstd", "mcap-lz4", "mcap-none", "mcap-unchunked")
FORMATS = MCAP_FORMATS + ("rosbag2-mcap", "rosbag2-sqlite3", "ros1", "ros1-lz4", "ros1-bz2",
                          "csv", "euroc")


@dataclass
class Signals:
    """What a seed holds: int64 ns stamps, gyro and accel (n, 3) and a temperature per sample.

    ``t_s`` replaces the stamps in the text formats when set (times a binary stamp cannot
    hold, such as 1e308 s)."""

    ns: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    temp: np.ndarray
    t_s: np.ndarray | None = None
    text_values: dict[tuple[int, int], str] | None = None  # (row, column) -> CSV field text

    def copy(self) -> Signals:
        return Signals(self.ns.copy(), self.gyro.copy(), self.accel.copy(), self.temp.copy(),
                       None if self.t_s is None else self.t_s.copy(),
                       dict(self.text_values or {}))


def clean_signals(n: int = N_SAMPLES, seed: int = 0) -> Signals:
    rng = np.random.default_rng(seed)
    ns = T0_NS + np.arange(n, dtype=np.int64) * int(1e9 / FS_HZ)
    gyro = rng.normal(0.0, 1e-3, (n, 3))
    accel = rng.normal(0.0, 1e-2, (n, 3)) + [0.0, 0.0, 9.81]
    return Signals(ns, gyro, accel, 25.0 + rng.normal(0.0, 0.01, n))


# ---- content mutations: altered signals, written by each format's writer -------------------

def _values(sig: Signals, rng: np.random.Generator, value: float) -> None:
    k = int(rng.integers(1, 6))
    rows = rng.integers(0, len(sig.ns), k)
    cols = rng.integers(0, 6, k)
    for r, c in zip(rows, cols, strict=True):
        (sig.gyro if c < 3 else sig.accel)[r, c % 3] = value
        (sig.text_values or {}).pop((int(r), int(c)), None)


def _all_huge(sig: Signals, rng: np.random.Generator) -> None:
    sig.gyro[:, int(rng.integers(0, 3))] = rng.choice([1e308, -1e308, 1.7e308]) * \
        rng.uniform(0.5, 1.0, len(sig.ns))


def _backwards(sig: Signals, rng: np.random.Generator) -> None:
    a = int(rng.integers(0, len(sig.ns) - 20))
    sig.ns[a:a + 20] = sig.ns[a:a + 20][::-1].copy()


def _repeated(sig: Signals, rng: np.random.Generator) -> None:
    a = int(rng.integers(0, len(sig.ns) - 50))
    sig.ns[a:a + 50] = sig.ns[a]


def _never_increasing(sig: Signals, rng: np.random.Generator) -> None:
    if rng.random() < 0.5:
        sig.ns[:] = sig.ns[0]
    else:
        sig.ns[:] = sig.ns[::-1].copy()


def _huge_stamp(sig: Signals, rng: np.random.Generator) -> None:
    i = int(rng.integers(0, len(sig.ns)))
    sig.ns[i] = rng.choice([(2**31 - 1) * 10**9, 0, 10**9 * 4_000_000])


def _text_time(sig: Signals, rng: np.random.Generator) -> None:
    t = sig.ns.astype(np.float64) * 1e-9
    i = int(rng.integers(0, len(t)))
    t[i] = rng.choice([1e308, -1e300, np.inf, np.nan, 1.7976931348623157e308])
    sig.t_s = t


def _text_fields(sig: Signals, rng: np.random.Generator) -> None:
    sig.text_values = sig.text_values or {}
    for _ in range(int(rng.integers(1, 4))):
        r, c = int(rng.integers(0, len(sig.ns))), int(rng.integers(0, 6))
        sig.text_values[(r, c)] = str(rng.choice(["1e999", "-1e999", "inf", "nan", "", "0x1p3",
                                                  "1,5", "\u00e9\u00e9", "1e308e3", "--1"]))


CONTENT_MUTATIONS: dict[str, Callable[[Signals, np.random.Generator], None]] = {
    "nan values": lambda s, r: _values(s, r, float("nan")),
    "infinite values": lambda s, r: _values(s, r, float(r.choice([np.inf, -np.inf]))),
    "huge values": lambda s, r: _values(s, r, float(r.choice([1e308, -1e308, 1.7e308]))),
    "all huge": _all_huge,
    "backward times": _backwards,
    "repeated times": _repeated,
    "never increasing times": _never_increasing,
    "huge stamp": _huge_stamp,
}
TEXT_MUTATIONS = {"huge or non-finite time": _text_time, "bad text fields": _text_fields}


# ---- writers -------------------------------------------------------------------------------

def _imu_records(sig: Signals):
    from imunoise.daq import ros2_msgs as m

    rec = m.encode_imu(np.zeros(len(sig.ns)), sig.gyro, sig.accel, "imu")
    sec = np.clip(sig.ns // 10**9, -2**31, 2**31 - 1)
    rec["sec"] = sec.astype(np.int32)
    rec["nanosec"] = (sig.ns % 10**9).astype(np.uint32)
    return rec


def write_mcap_official(path: Path, sig: Signals, compression: str) -> Path:
    from mcap.writer import CompressionType, Writer

    from imunoise.daq import ros2_msgs as m

    kinds = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4,
             "none": CompressionType.NONE, "unchunked": CompressionType.NONE}
    rec = _imu_records(sig)
    with open(path, "wb") as f:
        w = Writer(f, chunk_size=CHUNK_BYTES, compression=kinds[compression],
                   use_chunking=compression != "unchunked")
        w.start(profile="ros2", library="fuzz seed")
        sid = w.register_schema(m.IMU, m.SCHEMA_ENCODING, m.SCHEMA_TEXT[m.IMU].encode())
        cid = w.register_channel("/imu/data", m.MESSAGE_ENCODING, sid)
        for i in range(len(rec)):
            log = max(int(sig.ns[i]), 0)
            w.add_message(cid, log, rec[i].tobytes(), log, i)
        w.finish()
    return path


def write_mcap_imunoise(folder: Path, sig: Signals) -> Path:
    from imunoise.core.blocks import SampleBlock
    from imunoise.daq.recorder import McapRecorder

    folder.mkdir(parents=True, exist_ok=True)
    t = sig.ns.astype(np.float64) * 1e-9
    chans = {f"gyro_{a}": sig.gyro[:, i] for i, a in enumerate("xyz")}
    chans.update({f"accel_{a}": sig.accel[:, i] for i, a in enumerate("xyz")})
    chans["temp"] = sig.temp
    rec = McapRecorder(folder, "sim:adis16350", config={"model": "ADIS16350"}, threaded=False,
                       fsync=False, rotate_s=None, chunk_size=CHUNK_BYTES,
                       reserve_bytes=0, rate_hz=FS_HZ)
    for a in range(0, len(t), 100):
        rec.write(SampleBlock("/adis16350/imu", t[a:a + 100],
                              {k: v[a:a + 100] for k, v in chans.items()}, FS_HZ))
    rec.close()
    if rec.error is not None:
        raise RuntimeError(rec.error)
    (path,) = folder.glob("*.mcap")
    return path


def _ros2_messages(sig: Signals, typestore):
    from imunoise.daq import ros2_msgs as m

    T = typestore.types
    vec = T["geometry_msgs/msg/Vector3"]
    cov = np.zeros(9)
    for i in range(len(sig.ns)):
        ns = int(sig.ns[i])
        hdr = T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=int(np.clip(ns // 10**9, -2**31,
                                                                   2**31 - 1)),
                                                  nanosec=ns % 10**9), frame_id="imu")
        imu = T[m.IMU](header=hdr, orientation=T["geometry_msgs/msg/Quaternion"](
            x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=cov,
            angular_velocity=vec(*sig.gyro[i]), angular_velocity_covariance=cov,
            linear_acceleration=vec(*sig.accel[i]), linear_acceleration_covariance=cov)
        temp = None
        if i % 20 == 0:
            temp = T[m.TEMPERATURE](header=hdr, temperature=float(sig.temp[i]), variance=0.0)
        yield max(ns, 0), imu, temp


def write_rosbag2(folder: Path, sig: Signals, storage: str) -> Path:
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from imunoise.daq import ros2_msgs as m

    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(folder, version=9 if storage == "mcap" else 8, storage_plugin=plugin) as w:
        conn = w.add_connection("/imu/data", m.IMU, typestore=ts)
        tconn = w.add_connection("/imu/temperature", m.TEMPERATURE, typestore=ts)
        for ns, imu, temp in _ros2_messages(sig, ts):
            w.write(conn, ns, ts.serialize_cdr(imu, m.IMU))
            if temp is not None:
                w.write(tconn, ns, ts.serialize_cdr(temp, m.TEMPERATURE))
    return folder


def write_ros1(path: Path, sig: Signals, compression: str | None) -> Path:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    T = ts.types
    imu_t, temp_t = "sensor_msgs/msg/Imu", "sensor_msgs/msg/Temperature"
    vec = T["geometry_msgs/msg/Vector3"]
    cov = np.zeros(9)
    bag = Writer(path)
    if compression:
        bag.set_compression(getattr(Writer.CompressionFormat, compression.upper()))
    bag.chunk_threshold = CHUNK_BYTES
    with bag:
        conn = bag.add_connection("/imu/data", imu_t, typestore=ts)
        tconn = bag.add_connection("/imu/temperature", temp_t, typestore=ts)
        for i in range(len(sig.ns)):
            ns = int(sig.ns[i])
            hdr = T["std_msgs/msg/Header"](seq=i + 1, stamp=T["builtin_interfaces/msg/Time"](
                sec=int(np.clip(ns // 10**9, 0, 2**32 - 1)), nanosec=ns % 10**9),
                frame_id="imu")
            msg = T[imu_t](header=hdr, orientation=T["geometry_msgs/msg/Quaternion"](
                x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=cov,
                angular_velocity=vec(*sig.gyro[i]), angular_velocity_covariance=cov,
                linear_acceleration=vec(*sig.accel[i]), linear_acceleration_covariance=cov)
            log = max(ns, 1)
            bag.write(conn, log, ts.serialize_ros1(msg, imu_t))
            if i % 20 == 0:
                temp = T[temp_t](header=hdr, temperature=float(sig.temp[i]), variance=0.0)
                bag.write(tconn, log, ts.serialize_ros1(temp, temp_t))
    return path


def _csv_rows(sig: Signals, time_text: Callable[[int], str]) -> list[str]:
    vals = np.hstack([sig.gyro, sig.accel])
    text = sig.text_values or {}
    rows = []
    for i in range(len(sig.ns)):
        fields = [text.get((i, c), repr(float(vals[i, c]))) for c in range(6)]
        rows.append(",".join([time_text(i), *fields]))
    return rows


def write_csv(path: Path, sig: Signals) -> Path:
    t = sig.t_s if sig.t_s is not None else (sig.ns - T0_NS) * 1e-9
    header = "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z"
    path.write_text("\n".join([header, *_csv_rows(sig, lambda i: repr(float(t[i])))]) + "\n")
    return path


def write_euroc(folder: Path, sig: Signals) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "data.csv"
    header = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
    if sig.t_s is not None:
        def stamp(i: int) -> str:
            # a mutated time of 1e300 s written in ns is inf: that is the mutation
            return repr(float(sig.t_s[i]) * 1e9)  # type: ignore[index]
    else:
        def stamp(i: int) -> str:
            return str(int(sig.ns[i]))
    path.write_text("\n".join([header, *_csv_rows(sig, stamp)]) + "\n")
    (folder / "sensor.yaml").write_text("rate_hz: 100\ngyroscope_noise_density: 1.7e-4\n")
    return path


def write_seed(fmt: str, where: Path, sig: Signals) -> Path:
    """Write ``sig`` in format ``fmt`` under the new folder ``where``; the path to read."""
    where.mkdir(parents=True, exist_ok=True)
    if fmt == "mcap-imunoise":
        return write_mcap_imunoise(where / "rec", sig)
    if fmt.startswith("mcap-"):
        return write_mcap_official(where / "seed.mcap", sig, fmt.removeprefix("mcap-"))
    if fmt.startswith("rosbag2-"):
        return write_rosbag2(where / "bag", sig, fmt.removeprefix("rosbag2-"))
    if fmt.startswith("ros1"):
        return write_ros1(where / "seed.bag", sig, fmt.partition("-")[2] or None)
    if fmt == "csv":
        return write_csv(where / "seed.csv", sig)
    if fmt == "euroc":
        return write_euroc(where / "imu0", sig)
    raise ValueError(fmt)


# ---- byte mutations ------------------------------------------------------------------------

def _flip(data: bytearray, rng: np.random.Generator) -> str:
    k = int(rng.integers(1, 9))
    for _ in range(k):
        i = int(rng.integers(0, len(data)))
        data[i] ^= int(rng.integers(1, 256))
    return f"{k} byte(s) flipped"


def _truncate(data: bytearray, rng: np.random.Generator) -> str:
    n = int(rng.integers(0, len(data)))
    del data[n:]
    return f"cut at byte {n}"


def _zero(data: bytearray, rng: np.random.Generator) -> str:
    a = int(rng.integers(0, len(data)))
    n = int(rng.integers(1, 4096))
    data[a:a + n] = bytes(len(data[a:a + n]))
    return f"{n} bytes zeroed at {a}"


def _duplicate(data: bytearray, rng: np.random.Generator) -> str:
    a = int(rng.integers(0, len(data)))
    n = int(rng.integers(1, 4096))
    at = int(rng.integers(0, len(data)))
    data[at:at] = data[a:a + n]
    return f"{n} bytes from {a} repeated at {at}"


def _delete(data: bytearray, rng: np.random.Generator) -> str:
    a = int(rng.integers(0, len(data)))
    n = int(rng.integers(1, 2048))
    del data[a:a + n]
    return f"{n} bytes deleted at {a}"


def _huge_length(data: bytearray, rng: np.random.Generator) -> str:
    value = int(rng.choice([2**64 - 1, 2**63, 2**32 - 1, 2**31, 10**12, 0]))
    width = 8 if value >= 2**32 or rng.random() < 0.5 else 4
    anchors = _length_fields(bytes(data))
    at = int(rng.choice(anchors)) if anchors and rng.random() < 0.8 else \
        int(rng.integers(0, max(1, len(data) - width)))
    data[at:at + width] = struct.pack("<Q" if width == 8 else "<I", value % 2**(8 * width))
    return f"length field at {at} set to {value}"


def _length_fields(data: bytes) -> list[int]:
    """Offsets of record length fields: MCAP records (and a chunk's size fields), ROS 1 record
    header and data lengths; empty for other formats (a random offset is used then)."""
    if data.startswith(b"#ROSBAG V2.0\n"):
        out, pos = [], 13
        while pos + 4 <= len(data) and len(out) < 10_000:
            (hlen,) = struct.unpack_from("<I", data, pos)
            if pos + 8 + hlen > len(data):
                break
            (dlen,) = struct.unpack_from("<I", data, pos + 4 + hlen)
            out.extend([pos, pos + 4 + hlen])
            pos += 8 + hlen + dlen
        return out
    if not data.startswith(b"\x89MCAP0\r\n"):
        return []
    out, pos = [], 8
    while pos + 9 <= len(data) and len(out) < 10_000:
        op, n = struct.unpack_from("<BQ", data, pos)
        out.append(pos + 1)
        if op == 0x06:  # chunk: its uncompressed size and compressed length fields too
            out.extend([pos + 9 + 16, pos + 9 + 32])
        if pos + 9 + n > len(data):
            break
        pos += 9 + n
    return out


def _garbage(data: bytearray, rng: np.random.Generator) -> str:
    a = int(rng.integers(0, len(data)))
    n = int(rng.integers(1, 512))
    data[a:a] = rng.integers(0, 256, n, dtype=np.uint8).tobytes()
    return f"{n} random bytes inserted at {a}"


BYTE_MUTATIONS: dict[str, Callable[[bytearray, np.random.Generator], str]] = {
    "flip": _flip, "truncate": _truncate, "zero": _zero, "duplicate": _duplicate,
    "delete": _delete, "huge length": _huge_length, "garbage": _garbage}


def _long_line(data: bytearray, rng: np.random.Generator) -> str:
    n = int(rng.choice([70_000, 300_000]))
    data[len(data):] = b"1" * n
    return f"{n} characters without a newline appended"


TEXT_BYTE_MUTATIONS = {**BYTE_MUTATIONS, "long line": _long_line}


# ---- rosbag2 metadata mutations ------------------------------------------------------------

def _metadata_mutation(meta: Path, rng: np.random.Generator) -> str:
    import yaml

    text = meta.read_text()
    kind = int(rng.integers(0, 8))
    if kind == 0:
        meta.write_text(text[: int(rng.integers(0, len(text)))] + "\n  - [unclosed: {\n")
        return "metadata.yaml broken"
    doc = yaml.safe_load(text)
    info = doc["rosbag2_bagfile_information"]
    if kind == 1:
        target = str(rng.choice(["../../../../etc/passwd", "/etc/passwd", "../outside.mcap",
                                 "sub/../../x.db3"]))
        info["relative_file_paths"] = [target]
        what = f"file path {target!r}"
    elif kind == 2:
        info["relative_file_paths"] = ["missing_0.mcap"] + list(info["relative_file_paths"])
        what = "a missing file listed"
    elif kind == 3:
        count = int(rng.choice([10**20, -5, 0]))
        info["message_count"] = count
        for t in info.get("topics_with_message_count", []):
            t["message_count"] = count
        what = f"message counts {count}"
    elif kind == 4:
        info["duration"] = {"nanoseconds": int(rng.choice([-5, 10**30]))}
        info["starting_time"] = {"nanoseconds_since_epoch": int(rng.choice([-1, 10**25]))}
        what = "duration and start time"
    elif kind == 5:
        info["relative_file_paths"] = "not a list"
        what = "file list not a list"
    elif kind == 6:
        doc = ["not", "a", "mapping"]
        what = "not a mapping"
    else:
        info["storage_identifier"] = str(rng.choice(["", "rosbag_v2", "sqlite3", "mcap"]))
        info.pop("topics_with_message_count", None)
        what = "storage identifier changed, topics removed"
    meta.write_text(yaml.safe_dump(doc))
    return what


# ---- cases ---------------------------------------------------------------------------------

@dataclass
class Case:
    """One mutant: its format, how it was made, and the path to give the commands."""

    fmt: str
    mutation: str
    path: Path
    folder: Path | None = None  # everything of this case lies below it
    index: int = 0  # mutant number within its format

    @property
    def is_mcap(self) -> bool:
        return self.path.suffix == ".mcap"


def _storage_file(folder: Path) -> Path:
    files = sorted(p for p in folder.iterdir() if p.suffix in (".mcap", ".db3"))
    return files[0]


def make_case(fmt: str, index: int, rng: np.random.Generator, where: Path,
              seeds: dict[str, Path]) -> Case:
    """Mutant ``index`` of format ``fmt`` under ``where`` (a new folder): a content mutation
    written afresh, or a byte or metadata mutation of the clean seed in ``seeds``."""
    where.mkdir(parents=True)
    text = fmt in ("csv", "euroc")
    roll = rng.random()
    if roll < 0.25:
        table = {**CONTENT_MUTATIONS, **(TEXT_MUTATIONS if text else {})}
        name = str(rng.choice(sorted(table)))
        sig = clean_signals(seed=index)
        table[name](sig, rng)
        return Case(fmt, name, write_seed(fmt, where / "w", sig))
    seed = seeds[fmt]
    anchor = seed.parent if fmt in ("mcap-imunoise", "euroc") else seed
    target = where / anchor.name
    if anchor.is_dir():
        shutil.copytree(anchor, target)
    else:
        shutil.copy(anchor, target)
    path = target / seed.name if anchor != seed else target
    victim = path
    if fmt.startswith("rosbag2-"):
        if roll < 0.45:
            return Case(fmt, _metadata_mutation(path / "metadata.yaml", rng), path)
        victim = _storage_file(path)
    table = TEXT_BYTE_MUTATIONS if text else BYTE_MUTATIONS
    name = str(rng.choice(sorted(table)))
    data = bytearray(victim.read_bytes())
    what = table[name](data, rng)
    if fmt == "rosbag2-sqlite3" and rng.random() < 0.5:
        what = _sqlite_rows(victim, rng)
    else:
        victim.write_bytes(bytes(data))
    return Case(fmt, f"{name}: {what}", path)


def _sqlite_rows(db: Path, rng: np.random.Generator) -> str:
    """Damage inside a valid sqlite3 file: message blobs cut or flipped, stamps altered."""
    import sqlite3

    con = sqlite3.connect(db)
    try:
        kind = int(rng.integers(0, 3))
        if kind == 0:
            con.execute("UPDATE messages SET data = substr(data, 1, ?) WHERE id % 7 = 0",
                        (int(rng.integers(0, 40)),))
            what = "message blobs cut"
        elif kind == 1:
            con.execute("UPDATE messages SET timestamp = ?", (int(rng.integers(0, 10**18)),))
            what = "every timestamp the same"
        else:
            con.execute("UPDATE messages SET topic_id = 99 WHERE id % 5 = 0")
            what = "messages of an unknown topic"
        con.commit()
    finally:
        con.close()
    return f"sqlite rows: {what}"


def write_seeds(folder: Path) -> dict[str, Path]:
    """The clean seed of every format under ``folder``."""
    sig = clean_signals()
    return {fmt: write_seed(fmt, folder / fmt, sig) for fmt in FORMATS}


def iter_cases(folder: Path, per_format: int, seed: int = 0,
               formats: tuple[str, ...] = FORMATS) -> Iterator[Case]:
    """``per_format`` mutants of each format, interleaved, from a fixed seed."""
    seeds = write_seeds(folder / "seeds")
    rng = np.random.default_rng(seed)
    for i in range(per_format):
        for fmt in formats:
            where = folder / "cases" / f"{fmt}-{i}"
            case = make_case(fmt, i, rng, where, seeds)
            case.folder, case.index = where, i
            yield case


# ---- running the commands and checking the outcome ------------------------------------------

def commands_for(case: Case, out_dir: Path, full: bool = False) -> list[list[str]]:
    """The command lines run on a mutant: a cheap fit on every one, and in turn (by its number
    within its format) analyze in memory and streamed, replay, diagnose and export-kalibr,
    more often with ``full``; repair on every MCAP file (its output is the last argument)."""
    index = case.index
    every = {"analyze": 1, "replay": 4, "diagnose": 6, "kalibr": 20, "stream": 3} if full else \
        {"analyze": 5, "replay": 8, "diagnose": 25, "kalibr": 60, "stream": 7}
    p = str(case.path)
    cmds = [["fit", p, "--channel", "gyro_x", "--model", "white", "--json"]]
    if index % every["analyze"] == 0:
        cmds.append(["analyze", p, "--json", "--channel", "gyro_x"])
    if case.is_mcap and index % every["stream"] == 1:
        cmds.append(["analyze", p, "--json", "--channel", "gyro_y", "--stream", "always"])
    if index % every["replay"] == 1:
        cmds.append(["replay", p, "--speed", "max", "--json", "--no-progress"])
    if index % every["diagnose"] == 2:
        cmds.append(["diagnose", p, "--channel", "gyro_x", "--model", "white", "--json"])
    if index % every["kalibr"] == 3:
        cmds.append(["export-kalibr", p, "-o", str(out_dir / "imu.yaml")])
    if case.is_mcap:
        cmds.append(["repair", p, "-o", str(case.path.parent / "repaired.mcap")])
    return cmds


@dataclass
class Outcome:
    command: str
    code: int
    stdout: str
    stderr: str
    seconds: float
    warnings: list[str]
    cpu_seconds: float = 0.0
    """Processor time of this process while the command ran: unlike the wall time, not
    stretched by other work sharing the machine."""

    def problems(self) -> list[str]:
        """What is wrong with this outcome (empty when the exit was clean)."""
        out = []
        if "Traceback" in self.stderr or self.code not in (0, 2):
            out.append(f"exit {self.code}: {self.stderr[-2000:]}")
        if self.warnings:
            out.append(f"warnings: {self.warnings[:3]}")
        if self.code == 2:
            if self.stderr.count("\n") != 1 or len(self.stderr.rstrip("\n")) >= MAX_MESSAGE:
                out.append(f"message not one short line ({len(self.stderr)} characters): "
                           f"{self.stderr[:400]!r}")
        elif self.code == 0 and self.command in ("analyze", "fit", "diagnose", "replay"):
            try:
                json.loads(self.stdout, parse_constant=_reject_constant)
            except ValueError as exc:
                out.append(f"stdout is not strict JSON ({exc})")
        return out


def _reject_constant(name: str) -> float:
    raise ValueError(f"non-finite number {name} in the JSON")


def run_cli(argv: list[str]) -> Outcome:
    """``imunoise.cli.main(argv)`` in this process, with stdout, stderr and Python warnings
    captured; an exception escaping it is reported as exit 1 with its traceback."""
    import traceback

    from imunoise.cli import main

    out, err = io.StringIO(), io.StringIO()
    start, cpu_start = time.perf_counter(), time.process_time()
    with warnings.catch_warnings(record=True) as caught, \
            contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        warnings.simplefilter("always")
        try:
            code = main(argv)
        except SystemExit as exc:
            code = int(exc.code or 0) if not isinstance(exc.code, str) else 1
        except BaseException:  # noqa: BLE001 - what the fuzzing is looking for
            err.write(traceback.format_exc())
            code = 1
    return Outcome(argv[0], code, out.getvalue(), err.getvalue(), time.perf_counter() - start,
                   [f"{w.category.__name__}: {w.message}" for w in caught],
                   time.process_time() - cpu_start)


def check_repaired(path: Path) -> str | None:
    """None when the official reader with CRC validation and rosbags both read ``path``
    entirely; else what failed."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as f:
            reader = make_reader(f, validate_crcs=True)
            for _ in reader.iter_messages():
                pass
        with open(path, "rb") as f:
            from mcap.stream_reader import StreamReader

            for _ in StreamReader(f, validate_crcs=True).records:
                pass
    except Exception as exc:  # noqa: BLE001 - any failure is the finding
        return f"mcap reader: {type(exc).__name__}: {str(exc)[:200]}"
    try:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as r:
            for _ in r.messages():
                pass
    except Exception as exc:  # noqa: BLE001
        return f"rosbags: {type(exc).__name__}: {str(exc)[:200]}"
    return None
