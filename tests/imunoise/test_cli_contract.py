"""CONTRACT.md's command line, checked on the real ``imunoise`` in subprocesses.

One table of runs (command line, expected exit code, what stderr must name, which output must
not appear) over small generated CSV and MCAP inputs; the runs go in parallel once per module
and each row is then its own test. JSON documents are checked against schemas written from
CONTRACT.md (required keys and shapes; extra keys are allowed by the contract).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from imunoise.cli import build_parser
from tests.mcap_helpers import make_blocks, record_blocks

FS = 100.0
N = 6000  # 60 s: octave taus up to ~20 s, enough for three-term fits
CONTRACT_COMMANDS = ["record", "serve", "replay", "analyze", "fit", "diagnose",
                     "export-kalibr", "repair", "reproduce"]


# ---------------------------------------------------------------------------------- inputs
def _write_csv(path: Path, header: str, cols: list[np.ndarray]) -> Path:
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=header, comments="",
               fmt="%.10g")
    return path


def _make_inputs(d: Path) -> dict[str, Path]:
    rng = np.random.default_rng(7)
    t = np.arange(N) / FS
    gyro = 1e-3 * rng.normal(size=(3, N)) + np.cumsum(2e-5 * rng.normal(size=(3, N)), axis=1)
    accel = 2e-2 * rng.normal(size=(3, N)) + np.array([[0.0], [0.0], [9.81]])
    temp = 25 + 0.5 * np.sin(2 * np.pi * t / t[-1])
    p: dict[str, Path] = {"dir": d}
    p["csv"] = _write_csv(d / "imu.csv", "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,temp",
                          [t, *gyro, *accel, temp])
    g = gyro[0].copy()
    g[1000:1010] = np.nan
    p["nan_csv"] = _write_csv(d / "nan.csv", "t,gyro_x,accel_x", [t, g, accel[0]])
    tb = t.copy()
    tb[3000:] -= 5.0
    p["backwards_csv"] = _write_csv(d / "backwards.csv", "t,gyro_x", [tb, gyro[0]])
    p["short_csv"] = _write_csv(d / "short.csv", "t,gyro_x", [t[:12], gyro[0, :12]])
    p["all_nan_csv"] = _write_csv(d / "all_nan.csv", "t,gyro_x", [t, np.full(N, np.nan)])
    p["no_channels_csv"] = _write_csv(d / "other.csv", "t,speed,rpm", [t, gyro[0], gyro[1]])
    (d / "empty.csv").write_text("")
    p["empty_csv"] = d / "empty.csv"
    (d / "empty.mcap").write_bytes(b"")
    p["empty_mcap"] = d / "empty.mcap"
    (d / "random.mcap").write_bytes(rng.bytes(4096))
    p["random_mcap"] = d / "random.mcap"
    (d / "random.csv").write_bytes(rng.bytes(4096))
    p["random_csv"] = d / "random.csv"
    (d / "notabag").mkdir()
    (d / "notabag" / "notes.txt").write_text("not a bag")
    p["notabag"] = d / "notabag"
    one = record_blocks(d / "one", make_blocks(6, 1000, seed=3))
    p["mcap"] = Path(one.stats.files[0])
    two = record_blocks(d / "two", make_blocks(6, 1000, stream="/a/imu", seed=4)
                        + make_blocks(6, 1000, stream="/b/imu", seed=5))
    p["two_topics"] = Path(two.stats.files[0])
    return p


# ---------------------------------------------------------------------------------- the table
@dataclass
class Run:
    argv: list[str]
    code: int
    stderr_has: tuple[str, ...] = ()  # substrings of the one stderr line (code != 0)
    json_schema: str | None = None  # name in SCHEMAS: stdout is that JSON document
    not_created: tuple[str, ...] = ()  # output paths (under the input folder) that must not exist
    check: str | None = None  # extra check of the JSON document, see CHECKS
    env: dict[str, str] = field(default_factory=dict)


FIT = ["--channel", "gyro_x", "--model", "white,random_walk"]
# Rows already covered elsewhere (analyze on bad CSVs: test_cli_analyze; fit on unknown terms
# and channels: test_fit; replay and repair on bad MCAP files: test_bad_input) are not repeated.
RUNS: dict[str, Run] = {
    # JSON documents: shapes, strict numbers, nothing else on stdout
    "fit json topic selector": Run(["fit", "{two_topics}", "--channel", "/b/imu:gyro_x",
                                    "--model", "white", "--json"], 0, json_schema="fit",
                                   check="channel /b/imu:gyro_x"),
    "fit json warns of nan": Run(["fit", "{nan_csv}", *FIT, "--json"], 0, json_schema="fit",
                                 check="warning non-finite"),
    "fit json warns of backwards time": Run(["fit", "{backwards_csv}", *FIT, "--json"], 0,
                                            json_schema="fit", check="warning backwards"),
    "diagnose json": Run(["diagnose", "{csv}", "--channel", "gyro_y", "--model", "white",
                          "--json"], 0, json_schema="diagnose", check="best first"),
    "analyze json": Run(["analyze", "{csv}", "--json"], 0, json_schema="analyze",
                        check="all six channels"),
    "analyze json topic selectors": Run(
        ["analyze", "{two_topics}", "--json", "--channel", "/a/imu:gyro_x", "--channel",
         "/b/imu:accel_z"], 0, json_schema="analyze",
        check="channels /a/imu:gyro_x /b/imu:accel_z"),
    "analyze json too short to fit": Run(["analyze", "{short_csv}", "--json"], 0,
                                         check="unfitted gyro_x"),
    "replay json": Run(["replay", "{nan_csv}", "--speed", "max", "--json"], 0,
                       check="replay keeps every sample"),
    # bad usage and bad input: exit 2, one line naming the problem, nothing written
    "unknown term": Run(["fit", "{csv}", "--channel", "gyro_x", "--model", "white,flicker"], 2,
                        ("flicker", "valid terms")),
    "unknown term before reading": Run(["diagnose", "{dir}/gone.csv", "--channel", "gyro_x",
                                        "--model", "bogus"], 2, ("bogus", "valid terms")),
    "unknown topic": Run(["analyze", "{two_topics}", "--channel", "/c/imu:gyro_x"], 2,
                         ("/c/imu:gyro_x", "/a/imu:gyro_x")),
    "ambiguous bare channel": Run(["fit", "{two_topics}", "--channel", "gyro_x", "--model",
                                   "white"], 2, ("ambiguous", "/a/imu:gyro_x", "/b/imu:gyro_x")),
    "temperature is not fitted": Run(["diagnose", "{csv}", "--channel", "temp", "--model",
                                      "white"], 2, ("temperature",)),
    "parameter above nyquist": Run(["diagnose", "{csv}", "--channel", "gyro_x", "--model",
                                    "white,sinusoid:f=1000"], 2, ("sinusoid.f", "range")),
    "parameter not a number": Run(["fit", "{csv}", "--channel", "gyro_x", "--model",
                                   "white:N=abc"], 2, ("N=abc",)),
    "bad rate": Run(["fit", "{csv}", *FIT, "--rate", "0"], 2, ("rate", "'0'")),
    "missing file": Run(["fit", "{dir}/missing.csv", *FIT], 2, ("missing.csv", "no such")),
    "empty csv": Run(["analyze", "{empty_csv}", "--json", "--report", "{dir}/r1.html"], 2,
                     ("empty.csv", "empty"), not_created=("r1.html",)),
    "empty mcap": Run(["diagnose", "{empty_mcap}", *FIT], 2, ("empty.mcap", "empty")),
    "random bytes mcap": Run(["export-kalibr", "{random_mcap}", "-o", "{dir}/k1.yaml"], 2,
                             ("random.mcap", "not an MCAP"), not_created=("k1.yaml",)),
    "random bytes csv": Run(["fit", "{random_csv}", *FIT], 2, ("random.csv", "not a CSV")),
    "folder not a bag": Run(["analyze", "{notabag}", "--report", "{dir}/r2.html"], 2,
                            ("notabag", "rosbag2"), not_created=("r2.html",)),
    "all values nan": Run(["fit", "{all_nan_csv}", *FIT], 2, ("all_nan.csv", "no valid")),
    "csv without known channels": Run(["export-kalibr", "{no_channels_csv}", "-o",
                                       "{dir}/k2.yaml"], 2, ("other.csv", "no IMU channel"),
                                      not_created=("k2.yaml",)),
    "unknown channel with report": Run(["analyze", "{csv}", "--channel", "nope", "--report",
                                        "{dir}/r3.html"], 2, ("nope",), not_created=("r3.html",)),
    "serve missing replay": Run(["serve", "--replay", "{dir}/gone.mcap", "--port", "1"], 2,
                                ("gone.mcap",)),
    # serve parses --model with the grammar of fit: a held parameter passes (the run then
    # stops at the missing replay file), an unknown term is refused by name
    "serve held parameter": Run(["serve", "--replay", "{dir}/gone.mcap", "--port", "1",
                                 "--model", "white,gauss_markov:T=100"], 2, ("gone.mcap",)),
    "serve unknown term": Run(["serve", "--replay", "{dir}/gone.mcap", "--port", "1",
                               "--model", "white,flicker"], 2, ("flicker", "valid terms")),
    "serve non-live term": Run(["serve", "--replay", "{dir}/gone.mcap", "--port", "1",
                                "--model", "white,temperature"], 2, ("temperature",)),
    "replay serve missing file": Run(["replay", "{dir}/gone.mcap", "--serve"], 2,
                                     ("gone.mcap", "no such")),
    "missing required option": Run(["fit", "{csv}", "--model", "white"], 2, ("--channel",)),
    # D: seconds or 90s / 30m / 8h (the duration is read before the device is opened)
    "duration 8h accepted": Run(["record", "--device", "nosuch", "--out", "{dir}/rec1",
                                 "--duration", "8h"], 2, ("unknown device",),
                                not_created=("rec1",)),
    "duration 30m accepted": Run(["record", "--device", "nosuch", "--out", "{dir}/rec1",
                                  "--duration", "30m", "--rotate", "90s"], 2,
                                 ("unknown device",)),
    "duration 90 accepted": Run(["record", "--device", "nosuch", "--out", "{dir}/rec1",
                                 "--duration", "90"], 2, ("unknown device",)),
    "record out is a file": Run(["record", "--device", "sim:adis16350", "--out", "{csv}",
                                 "--duration", "1s"], 2, ("imu.csv", "not a folder")),
    # runtime failure: exit 1, still one line
    "device absent": Run(["record", "--device", "adis16350", "--port", "/dev/imunoise-absent",
                          "--out", "{dir}/rec2"], 1, ("/dev/imunoise-absent",),
                         not_created=("rec2",)),
}


# ---------------------------------------------------------------------------------- schemas
def _array(items: dict | None = None, n: int | None = None) -> dict:
    s: dict = {"type": "array", "items": items or {"type": ["number", "null"]}}
    if n is not None:
        s["minItems"] = s["maxItems"] = n
    return s


_PAIR = _array({"type": ["number", "null"]}, 2)
_MODEL = {"type": "array", "items": {
    "type": "object", "required": ["term", "params", "ci95"],
    "properties": {"term": {"type": "string"},
                   "params": {"type": "object", "additionalProperties": {"type": "number"}},
                   "ci95": {"type": "object", "additionalProperties": _PAIR}}}}
_CHANNEL = {
    "type": "object",
    "required": ["channel", "units", "fs_hz", "n_samples", "duration_s", "model", "error",
                 "failures", "allan"],
    "properties": {
        "channel": {"type": "string"},
        "units": {"enum": ["rad/s", "m/s^2"]},
        "fs_hz": {"type": "number", "exclusiveMinimum": 0},
        "n_samples": {"type": "integer", "minimum": 1},
        "duration_s": {"type": "number", "exclusiveMinimum": 0},
        "model": _MODEL,
        "error": {"type": "object", "required": ["chi2_per_dof", "max_abs_z"],
                  "properties": {"chi2_per_dof": {"type": "number", "minimum": 0},
                                 "max_abs_z": {"type": "number", "minimum": 0}}},
        "failures": {"type": "array", "items": {
            "type": "object", "required": ["tau_s", "max_abs_z", "direction"],
            "properties": {"tau_s": _array({"type": "number"}, 2),
                           "max_abs_z": {"type": "number"},
                           "direction": {"type": "string"}}}},
        "allan": {"type": "object",
                  "required": ["tau_s", "adev", "ci_low", "ci_high", "model_adev", "z"],
                  "properties": {k: _array() for k in ("tau_s", "adev", "ci_low", "ci_high",
                                                       "model_adev", "z")}},
        "warnings": _array({"type": "string"}),
    },
}
_SUGGESTION = {"type": "object",
               "required": ["term", "params", "chi2_per_dof_after", "significant", "why"],
               "properties": {"term": {"type": "string"},
                              "params": {"type": "object"},
                              "chi2_per_dof_after": {"type": ["number", "null"]},
                              "significant": {"type": "boolean"},
                              "why": {"type": "string", "minLength": 20}}}
_PSD = {"type": "object", "required": ["f_hz", "psd", "ci_low", "ci_high"],
        "properties": {k: _array() for k in ("f_hz", "psd", "ci_low", "ci_high")}}
SCHEMAS = {
    "fit": _CHANNEL,
    "diagnose": {"allOf": [_CHANNEL, {
        "required": ["suggestions"],
        "properties": {"suggestions": {"type": "array", "minItems": 1, "items": _SUGGESTION}}}]},
    "analyze": {"type": "object", "required": ["file", "channels"], "properties": {
        "file": {"type": "string"},
        "channels": {"type": "object", "minProperties": 1, "additionalProperties": {
            "allOf": [_CHANNEL, {"required": ["psd"], "properties": {"psd": _PSD}}]}}}},
}


def _same_lengths(channel: dict) -> None:
    """Parallel arrays run parallel: the Allan arrays along tau_s, the PSD ones along f_hz."""
    allan = channel["allan"]
    n = len(allan["tau_s"])
    assert n >= 5, allan["tau_s"]
    for k in ("adev", "ci_low", "ci_high", "model_adev", "z"):
        assert len(allan[k]) == n, k
    if "psd" in channel:
        m = len(channel["psd"]["f_hz"])
        assert m > 10 and all(len(channel["psd"][k]) == m for k in ("psd", "ci_low", "ci_high"))


def _strict_json(text: str) -> dict:
    def reject(token: str) -> None:
        raise AssertionError(f"non-finite number {token} in the JSON")

    return json.loads(text, parse_constant=reject)


# ---------------------------------------------------------------------------------- running
@dataclass
class Result:
    argv: list[str]
    code: int
    stdout: str
    stderr: str


def _expand(arg: str, paths: dict[str, Path]) -> str:
    return arg.format(**{k: str(v) for k, v in paths.items()})


def _run(argv: list[str]) -> Result:
    proc = subprocess.run([sys.executable, "-m", "imunoise", *argv], capture_output=True,
                          text=True, timeout=180)
    return Result(argv, proc.returncode, proc.stdout, proc.stderr)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    return _make_inputs(tmp_path_factory.mktemp("contract"))


@pytest.fixture(scope="module")
def results(inputs) -> dict[str, Result]:
    """Every run of the table, three at a time (most are short start-up-bound processes)."""
    argvs = {name: [_expand(a, inputs) for a in run.argv] for name, run in RUNS.items()}
    with ThreadPoolExecutor(max_workers=3) as pool:
        futures = {name: pool.submit(_run, argv) for name, argv in argvs.items()}
        return {name: f.result() for name, f in futures.items()}


@pytest.mark.parametrize("name", list(RUNS))
def test_contract_run(name, results, inputs):
    run, res = RUNS[name], results[name]
    assert "Traceback" not in res.stderr, res.stderr
    assert res.code == run.code, (res.argv, res.code, res.stderr)
    for out in run.not_created:
        assert not (inputs["dir"] / out).exists(), f"{out} written by a failed run"
    if run.code != 0:
        lines = res.stderr.splitlines()
        assert len(lines) == 1 and lines[0].startswith("imunoise"), res.stderr
        for needle in run.stderr_has:
            assert needle in lines[0], (needle, lines[0])
        assert res.stdout == ""
        return
    doc = _strict_json(res.stdout)  # the whole of stdout is one JSON document
    if run.json_schema:
        assert res.stderr == "", res.stderr
        jsonschema.validate(doc, SCHEMAS[run.json_schema])
        for ch in (doc["channels"].values() if run.json_schema == "analyze" else [doc]):
            _same_lengths(ch)
    if run.check:
        CHECKS[run.check.split()[0]](doc, run.check.split()[1:])


def _check_channel(doc: dict, args: list[str]) -> None:
    assert doc["channel"] == args[0]


def _check_warning(doc: dict, args: list[str]) -> None:
    assert any(args[0] in w for w in doc.get("warnings", [])), doc.get("warnings")


def _check_best_first(doc: dict, args: list[str]) -> None:
    sugg = doc["suggestions"]
    terms = [s["term"] for s in sugg]
    assert len(set(terms)) == len(terms) and "white" not in terms
    flags = [s["significant"] for s in sugg]
    assert flags == sorted(flags, reverse=True), flags  # significant ones lead
    log_p = [s["log10_p"] for s in sugg]
    assert log_p == sorted(log_p), log_p  # then by strength of evidence
    # the data hold a random walk the white-only model lacks: it is found and lowers the error
    assert sugg[0]["significant"] and sugg[0]["term"] in ("random_walk", "gauss_markov",
                                                          "bias_instability", "rate_ramp")
    assert sugg[0]["chi2_per_dof_after"] < doc["error"]["chi2_per_dof"]


def _check_channels(doc: dict, args: list[str]) -> None:
    assert list(doc["channels"]) == args
    for key, ch in doc["channels"].items():
        assert ch["channel"] == key


def _check_all_six(doc: dict, args: list[str]) -> None:
    chans = doc["channels"]
    assert list(chans) == ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    for key, ch in chans.items():
        assert ch["n_samples"] == N and ch["fs_hz"] == FS
        assert [m["term"] for m in ch["model"]] == ["white", "bias_instability", "random_walk"]
        assert ch["units"] == ("rad/s" if key.startswith("gyro") else "m/s^2")
        white = ch["model"][0]
        lo, hi = white["ci95"]["N"]
        assert lo <= white["params"]["N"] <= hi


def _check_replay(doc: dict, args: list[str]) -> None:
    rows = {r["channel"].split(":")[-1]: r for r in doc["channels"]}
    assert rows["gyro_x"]["samples"] == N - 10  # ten NaN removed from gyro_x only
    assert rows["accel_x"]["samples"] == N and rows["accel_x"]["gaps"] == 0
    assert all(math.isfinite(r["white_noise_density"]) for r in rows.values())


def _check_unfitted(doc: dict, args: list[str]) -> None:
    """Without a fit the shapes stay: an error object of nulls, arrays parallel to tau_s."""
    ch = doc["channels"][args[0]]
    assert ch["model"] == [] and ch["failures"] == []
    assert ch["error"] == {"chi2_per_dof": None, "max_abs_z": None}
    allan = ch["allan"]
    assert len(allan["tau_s"]) >= 1
    assert allan["model_adev"] == allan["z"] == [None] * len(allan["tau_s"])
    assert any("no model fit" in w for w in ch["warnings"])


CHECKS = {"channel": _check_channel, "warning": _check_warning, "best": _check_best_first,
          "channels": _check_channels, "all": _check_all_six, "replay": _check_replay,
          "unfitted": _check_unfitted}


# ---------------------------------------------------------------------------------- --help
def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_every_contract_command_exists():
    assert set(CONTRACT_COMMANDS) <= set(_subparsers())


@pytest.mark.parametrize("command", CONTRACT_COMMANDS)
def test_help_states_defaults_and_units(command):
    """Every option with a default says which; HZ, D, S values name their unit."""
    p = _subparsers()[command]
    for a in p._actions:
        if a.help in (None, argparse.SUPPRESS) or isinstance(a, argparse._HelpAction):
            continue
        text = a.help.lower()
        flag = isinstance(a, (argparse._StoreTrueAction, argparse._StoreFalseAction))
        if a.default not in (None, False, argparse.SUPPRESS) and not flag:
            assert "default" in text, (command, a.option_strings, a.help)
        if a.metavar == "HZ":
            assert "hz" in text, (command, a.option_strings, a.help)
        if a.metavar == "D":
            assert "90s" in text and "8h" in text, (command, a.option_strings, a.help)
        if a.metavar == "S":
            assert ", s " in text or " s)" in text or "seconds" in text, a.help


def test_help_runs_in_a_subprocess():
    """``--help`` of every command exits 0 and prints its usage, all in parallel."""
    with ThreadPoolExecutor(max_workers=3) as pool:
        res = list(pool.map(lambda c: _run([c, "--help"]), CONTRACT_COMMANDS))
    for command, r in zip(CONTRACT_COMMANDS, res, strict=True):
        assert r.code == 0 and r.stderr == "", (command, r.stderr)
        assert r.stdout.startswith(f"usage: imunoise {command}")


def test_replay_serve_paces_the_file_behind_the_api(inputs):
    """``replay FILE --serve --speed X``: the API comes up and the samples arrive on the
    sample clock (X times real time), not all at once; Ctrl-C ends it with exit 0."""
    import time

    import httpx

    from tests.live_helpers import free_port, interrupt

    port, speed = free_port(), 4.0
    proc = subprocess.Popen([sys.executable, "-m", "imunoise", "replay", str(inputs["mcap"]),
                             "--serve", "--port", str(port), "--speed", str(speed)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: list[tuple[float, int]] = []
    try:
        t_end = time.monotonic() + 60
        while time.monotonic() < t_end and proc.poll() is None and len(seen) < 2:
            try:
                health = httpx.get(f"http://127.0.0.1:{port}/health", timeout=5).json()
            except httpx.HTTPError:
                time.sleep(0.3)
                continue
            n = health["samples"]["received"]
            if n and (not seen or time.monotonic() - seen[0][0] > 1.5):
                seen.append((time.monotonic(), n))
            time.sleep(0.2)
        assert len(seen) == 2, proc.stderr.read() if proc.poll() is not None else "no samples"
        assert health["device"]["spec"] == f"replay:{inputs['mcap'].name}"
        (t1, n1), (t2, n2) = seen
        # 6000 IMU + 6000 temperature samples at 100 Hz: 15 s of replay at 4x
        assert n1 < 12_000 and n2 > n1
        rate = (n2 - n1) / (t2 - t1)  # both topics: 2 x 100 Hz x speed
        assert 0.3 * 2 * FS * speed < rate < 2.5 * 2 * FS * speed, rate
    finally:
        err = interrupt(proc)
    assert proc.returncode == 0, err
    assert "Traceback" not in err


def test_os_errors_are_one_line_runtime_failures(monkeypatch, capsys):
    """An OSError no command caught (disk full ...) is exit 1 with one line, no traceback."""
    from imunoise.cli import main
    from imunoise.commands import reproduce

    def full_disk(args):
        raise OSError(28, "No space left on device", "/data/night.mcap")

    monkeypatch.setattr(reproduce, "run", full_disk)
    assert main(["reproduce", "petkov2010"]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err == ["imunoise: No space left on device: /data/night.mcap"]


def test_closed_stdout_is_not_a_traceback(inputs):
    """``imunoise ... | head`` closing the pipe early ends the command without a traceback."""
    proc = subprocess.Popen([sys.executable, "-m", "imunoise", "replay", str(inputs["mcap"]),
                             "--speed", "max"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == 1
    assert err == "", err
