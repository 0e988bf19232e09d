"""``imunoise export-kalibr``: a Kalibr ``imu.yaml`` from a recording's fitted noise models.

FILE is a recording (.csv, .mcap, rosbag2 folder), analysed with the default model
(white + bias_instability + random_walk) on every gyro and accelerometer axis, or the JSON
written by ``imunoise analyze --json`` (no recomputation).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from imunoise.commands.common import add_rate_option
from imunoise.errors import UsageError
from imunoise.export.files import write_text_atomically
from imunoise.export.kalibr import COMBINE, KalibrError, kalibr_values, render_yaml
from imunoise.pipeline.reading import read_record


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export-kalibr", help="Kalibr-style imu.yaml", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("file", help="recording (.csv, .mcap, rosbag2 folder) or analyze --json output")
    p.add_argument("-o", "--output", default="imu.yaml", metavar="OUT",
                   help="where to write the YAML (default imu.yaml; '-' for stdout)")
    p.add_argument("--inflate", type=_factor, default=1.0, metavar="X",
                   help="multiply all four values by X (stated in the file), default 1")
    p.add_argument("--combine", choices=COMBINE, default="max",
                   help="how the three axes become one value (default max: conservative)")
    p.add_argument("--topic", default=None, metavar="TOPIC",
                   help="IMU topic to use when the file has several")
    p.add_argument("--overbound", action="store_true",
                   help="take N and K from each axis' over-bounding model (white noise and random "
                        "walk on or above the measured Allan deviation's upper 95 %% bound at "
                        "every tau): values a filter can use without becoming overconfident")
    p.add_argument("--rostopic", default=None, metavar="NAME",
                   help="value of rostopic in the YAML (default: the recording's IMU topic, "
                        "else /imu0)")
    add_rate_option(p)
    p.set_defaults(func=run)


def _factor(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number: {text!r}")
    return v


def load_channels(path: str, rate_hz: float | None = None, static: str = "auto"
                  ) -> tuple[dict, dict]:
    """Fitted channels and facts (``file``, ``rostopic``) from a recording or analyze JSON."""
    p = Path(path)
    if not p.exists():
        raise UsageError(f"{path}: no such file or folder")
    if p.suffix.lower() == ".json":
        try:
            doc = json.loads(p.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise UsageError(f"{path}: not an analyze JSON document ({exc})") from None
        if not isinstance(doc, dict) or not isinstance(doc.get("channels"), dict):
            raise UsageError(f"{path}: not an analyze JSON document (no 'channels' object)")
        return doc["channels"], {"file": path, "rostopic": None,
                                 "dataset": doc.get("dataset", {}), "notes": _notes(doc)}
    return fitted_channels(path, rate_hz, static)


def imu_topic(metadata: dict[str, str]) -> str | None:
    """The one IMU topic a reader listed in ``metadata["topics"]``, if there is exactly one."""
    topics = [t for t in metadata.get("topics", "").split(",") if t.strip()]
    imu = [t.strip() for t in topics if not t.strip().lower().endswith(("temperature", "temp"))]
    return imu[0] if len(imu) == 1 else None


def fitted_channels(path: str, rate_hz: float | None = None, static: str = "auto"
                    ) -> tuple[dict[str, dict], dict]:
    """Every inertial channel of a recording analysed as ``imunoise analyze`` does (default
    model fitted, still stretches only unless ``static="all"``), and the facts of the
    recording (``file``, ``rostopic``, ``dataset``, ``notes`` for the file's comments).

    Raises UsageError when the sensor never rested (numbers from moving data are not noise)
    unless ``static="all"``."""
    from imunoise.pipeline.channel_analysis import analyze_record
    from imunoise.pipeline.documents import analysis_json

    record = read_record(path, rate_hz, static)
    never_still = [f"{topic}: {m['summary']}" for topic, m in
                   record.facts.get("motion", {}).items() if m.get("used", "").startswith("all (")]
    if never_still and static == "auto":
        raise UsageError("export-kalibr: the sensor never rested (" + "; ".join(never_still)
                         + "): noise numbers from moving data are not the sensor's noise; "
                         "record it at rest, or give --static all to export anyway")
    keys = [k for k, s in record.channels.items() if s.units in ("rad/s", "m/s^2")]
    doc = analysis_json(path, record, analyze_record(record, keys))
    return doc["channels"], {"file": path, "rostopic": imu_topic(record.metadata),
                             "dataset": doc.get("dataset", {}), "notes": _notes(doc)}


def _notes(doc: dict) -> list[str]:
    """The recording's timing and motion facts, one line each, for the yaml's comments."""
    lines = []
    for topic, t in (doc.get("timing") or {}).items():
        lines.append(f"{topic}: {t['fs_hz']:.6g} Hz, {t['missing_samples']} sample(s) missing, "
                     f"time stamp jitter rms {t['jitter_rms_s']:.3g} s (max "
                     f"{t['jitter_max_s']:.3g} s)")
    for topic, m in (doc.get("motion") or {}).items():
        lines.append(f"{topic}: {m['summary']}; used: {m.get('used', 'all')}")
    return lines


def run(args: argparse.Namespace) -> int:
    channels, facts = load_channels(args.file, args.rate, args.static)
    try:
        imu = kalibr_values(channels, topic=args.topic,
                            rostopic=args.rostopic or facts.get("rostopic"),
                            combine=args.combine, inflate=args.inflate,
                            overbound=args.overbound)
    except KalibrError as exc:
        raise UsageError(f"export-kalibr: {exc}") from None
    text = render_yaml(imu, source=os.path.basename(str(args.file).rstrip("/")),
                       stated=facts.get("dataset") or {}, notes=facts.get("notes") or [])
    if args.output == "-":
        sys.stdout.write(text)
        return 0
    write_text_atomically(args.output, text)
    print(f"wrote {args.output}", file=sys.stderr)
    return 0
