"""docker-compose.yml against the Compose specification schema, and its commands against our CLI."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest
import yaml

from imunoise.cli import build_parser
from tests.shared_paths import SHARED_REFERENCE

ROOT = Path(__file__).resolve().parents[2]
SCHEMA = SHARED_REFERENCE / "compose/compose-spec.json"


def _compose() -> dict:
    return yaml.safe_load((ROOT / "docker-compose.yml").read_text())


def _interpolate(value: str) -> str:
    """Compose-style ``${VAR:-default}`` / ``${VAR:?message}`` with nothing set."""
    def sub(m: re.Match) -> str:
        return m.group(2) if m.group(1) == ":-" else "x"
    return re.sub(r"\$\{[A-Z0-9_]+(:-|:\?)([^}]*)\}", sub, value)


def test_compose_file_validates_against_the_compose_spec() -> None:
    jsonschema = pytest.importorskip("jsonschema")
    if not SCHEMA.exists():
        pytest.skip(f"{SCHEMA} not found (the shared reference folder is absent)")
    validator = jsonschema.Draft7Validator(json.loads(SCHEMA.read_text()))
    doc = _compose()
    errors = [f"{'/'.join(map(str, e.path))}: {e.message}" for e in validator.iter_errors(doc)]
    assert errors == []
    # The validator does catch a misspelt key.
    typo = dict(doc, services={"imunoise": {"image": "x", "device": ["/dev/ttyUSB0"]}})
    assert not validator.is_valid(typo)


def test_service_maps_devices_data_port_and_health() -> None:
    svc = _compose()["services"]["imunoise"]
    devices = [_interpolate(d) for d in svc["devices"]]
    assert "/dev/ttyUSB0:/dev/ttyUSB0" in devices and "/dev/i2c-1:/dev/i2c-1" in devices
    assert "imunoise-data:/data" in svc["volumes"]
    assert [_interpolate(p) for p in svc["ports"]] == ["127.0.0.1:8000:8000"]
    assert "http://127.0.0.1:8000/health" in " ".join(svc["healthcheck"]["test"])
    assert "IMUNOISE_TOKEN" in svc["environment"]


@pytest.mark.parametrize("service", ["imunoise", "demo"])
def test_compose_commands_parse_with_the_cli(service: str) -> None:
    command = [_interpolate(c) for c in _compose()["services"][service]["command"]]
    args = build_parser().parse_args(command)
    assert args.command == "serve" and args.host == "0.0.0.0" and args.port == 8000
    assert args.out == "/data"


def test_dockerfile_command_parses_and_checks_health() -> None:
    text = (ROOT / "Dockerfile").read_text()
    cmd = json.loads(re.search(r"^CMD (\[.*\])$", text, re.M).group(1))
    args = build_parser().parse_args(cmd)
    assert args.command == "serve" and args.host == "0.0.0.0" and args.out == "/data"
    assert "/health" in re.search(r"HEALTHCHECK .*\n.*", text).group(0)
    assert shlex.split("imunoise")[0] in text
