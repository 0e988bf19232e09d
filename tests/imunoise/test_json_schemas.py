"""The JSON documents the command line prints follow the schemas shipped in docs/schemas/
(draft 2020-12), and the schemas are strict enough to reject a broken document."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from referencing import Registry, Resource

from tests.shared_paths import REPO

SCHEMAS = REPO / "docs" / "schemas"
FS = 100.0
DOCUMENTS = ("analyze", "fit", "diagnose", "plan", "replicates")


def _registry() -> Registry:
    resources = [(p.name, Resource.from_contents(json.loads(p.read_text())))
                 for p in sorted(SCHEMAS.glob("*.schema.json"))]
    return Registry().with_resources(resources)


def validator(name: str) -> jsonschema.Draft202012Validator:
    schema = json.loads((SCHEMAS / f"{name}.schema.json").read_text())
    return jsonschema.Draft202012Validator(schema, registry=_registry())


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    """Six IMU channels and a temperature, 5 min at 100 Hz, a gap in gyro_x."""
    rng = np.random.default_rng(11)
    n = 30_000
    t = np.arange(n) / FS
    gyro = 1e-3 * rng.normal(size=(3, n)) + np.cumsum(2e-5 * rng.normal(size=(3, n)), axis=1)
    accel = 2e-2 * rng.normal(size=(3, n)) + np.array([[0.0], [0.0], [9.81]])
    gyro[0, 5000:5005] = np.nan
    temp = 25 + 0.5 * np.sin(2 * np.pi * t / t[-1])
    path = tmp_path_factory.mktemp("schemas") / "imu.csv"
    np.savetxt(path, np.column_stack([t, *gyro, *accel, temp]), delimiter=",",
               header="t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,temp", comments="",
               fmt="%.10g")
    return path


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> list[Path]:
    """Two recordings of one gyro (white noise, a random walk), 5 min at 100 Hz each."""
    d = tmp_path_factory.mktemp("replicates")
    paths = []
    for seed in (21, 22):
        rng = np.random.default_rng(seed)
        n = 30_000
        x = 1e-3 * rng.normal(size=n) + np.cumsum(1e-5 * rng.normal(size=n))
        path = d / f"run{seed}.csv"
        np.savetxt(path, np.column_stack([np.arange(n) / FS, x]), delimiter=",",
                   header="t,gyro_x", comments="", fmt="%.10g")
        paths.append(path)
    return paths


def _cli(args: list[str]) -> dict:
    out = subprocess.run([sys.executable, "-m", "imunoise", *args, "--json"],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout)


@pytest.fixture(scope="module")
def documents(recording, runs) -> dict[str, list[dict]]:
    f = str(recording)
    model = "white,bias_instability,random_walk"
    return {
        "analyze": [_cli(["analyze", f])],
        "fit": [_cli(["fit", f, "--channel", "gyro_x", "--model", model]),
                _cli(["fit", f, "--channel", "accel_z", "--model", "white,temperature"])],
        "diagnose": [_cli(["diagnose", f, "--channel", "gyro_y", "--model", "white"])],
        "plan": [_cli(["plan", f, "--channel", "gyro_x", "--target", "N=5%,K=50%"]),
                 _cli(["plan", "--model", "white:N=3e-4,random_walk:K=2e-5", "--rate", "100",
                       "--target", "K=20%", "--method", "likelihood"])],
        "replicates": [_cli(["diagnose", *map(str, runs), "--channel", "gyro_x", "--model",
                             "white,random_walk", "--rounds", "1"])],
    }


@pytest.mark.parametrize("name", ["common", *DOCUMENTS])
def test_the_schemas_are_draft_2020_12(name):
    schema = json.loads((SCHEMAS / f"{name}.schema.json").read_text())
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)


@pytest.mark.parametrize("name", DOCUMENTS)
def test_the_command_lines_documents_follow_their_schema(name, documents):
    for doc in documents[name]:
        errors = [f"{list(e.absolute_path)}: {e.message}"
                  for e in validator(name).iter_errors(doc)]
        assert not errors, errors[:5]


def test_the_python_api_documents_follow_the_schemas(recording):
    import imunoise

    rec = imunoise.read(str(recording))
    validator("fit").validate(imunoise.fit(rec["gyro_z"], "white,random_walk").document())
    validator("analyze").validate(imunoise.analyze(rec, ["gyro_z"]))


def _broken(doc: dict, path: list, value: object = None, delete: bool = False) -> dict:
    out = copy.deepcopy(doc)
    node = out
    for key in path[:-1]:
        node = node[key]
    if delete:
        del node[path[-1]]
    else:
        node[path[-1]] = value
    return out


def test_the_schemas_reject_broken_documents(documents):
    """Each schema fails a document that breaks the contract (so the test above can fail)."""
    fit = documents["fit"][0]
    diagnose = documents["diagnose"][0]
    analyze = documents["analyze"][0]
    plan = documents["plan"][0]
    replicates = documents["replicates"][0]
    key = next(iter(analyze["channels"]))
    cases = [
        ("fit", _broken(fit, ["model"], delete=True)),
        ("fit", _broken(fit, ["allan", "adev"], "0.1")),
        ("fit", _broken(fit, ["error", "chi2_per_dof"], -1.0)),
        ("fit", _broken(fit, ["model", 0, "ci95", "N"], [1.0])),
        ("diagnose", _broken(diagnose, ["suggestions", 0, "apply"], delete=True)),
        ("diagnose", _broken(diagnose, ["suggestions", 0, "significant"], "yes")),
        ("analyze", _broken(analyze, ["channels", key, "psd"], delete=True)),
        ("analyze", _broken(analyze, ["channels", key, "failures"], [{"tau_s": [1.0]}])),
        ("plan", _broken(plan, ["targets", 0, "record_s"], -5.0)),
        ("plan", _broken(plan, ["targets", 0, "method"], "guess")),
        ("replicates", _broken(replicates, ["replicates", "per_run", 0, "white#0.N",
                                            "unresolved"], delete=True)),
        ("replicates", _broken(replicates, ["replicates", "amplitudes", 0, "kind"], "level")),
        ("replicates", _broken(replicates, ["replicates", "runs"],
                               replicates["replicates"]["runs"][:1])),
        ("replicates", _broken(replicates, ["replicates", "runs", 0, "error", "holdout",
                                            "changed"], "none")),
    ]
    for name, doc in cases:
        assert not validator(name).is_valid(doc), name


def test_the_schemas_accept_the_parts_being_added(documents):
    """The optional parts the contract announces validate when present: the error's psd,
    holdout and time_domain parts, the fit's psd block with model_psd, analyze's coherence;
    and additional keys are allowed (extensions)."""
    fit = copy.deepcopy(documents["fit"][0])
    n = len(fit["allan"]["tau_s"])
    miss = {"half": 1, "by": 2, "failures": [{"tau_s": [20.48, 655.36], "max_abs_z": 7.2,
                                              "direction": "measured above model"}],
            "unresolved": [{"param": "random_walk.K", "value": 3.6e-4,
                            "ci95": [2.6e-4, 5.0e-4]}]}
    fit["error"].update(
        psd={"deviance_per_bin": 1.2, "bins": 186, "outside_95": 0.06,
             "misses": [{"f_hz": [23.0, 34.4], "max_abs_z": 53.1,
                         "direction": "measured above model", "deviance_share": 0.55}]},
        holdout={"chi2_per_dof": 1.3, "parts": 2,
                 "changed": [{"param": "resonance.f0", "values": [20.69, 19.91], "z": 5.2,
                              "source": "psd"}],
                 "misses": [miss],
                 "changes_free": {"chi2_per_dof": 1.1, "halves": [1.0, 1.2],
                                  "params": ["resonance.f0"], "misses": [miss]},
                 "joint_difference": {"params": ["white.N", "random_walk.K"], "chi2": 7.1,
                                      "dof": 2, "p": 0.029}},
        time_domain=None)
    fit["psd"] = {"f_hz": [0.1] * n, "psd": [1.0] * n, "dof": [2.0] * n, "ci_low": [0.5] * n,
                  "ci_high": [2.0] * n, "model_psd": [1.0] * n, "z": [0.0] * n}
    fit["something_new"] = {"any": "thing"}
    validator("fit").validate(fit)
    wrong = copy.deepcopy(fit)
    wrong["error"]["holdout"]["changed"][0]["source"] = "spectrum"
    with pytest.raises(jsonschema.ValidationError, match="spectrum"):
        validator("fit").validate(wrong)
    wrong = copy.deepcopy(fit)
    wrong["error"]["holdout"]["changes_free"]["misses"][0]["half"] = 3
    with pytest.raises(jsonschema.ValidationError, match="3 is not one of"):
        validator("fit").validate(wrong)
    wrong = copy.deepcopy(fit)
    wrong["error"]["psd"]["misses"][0]["deviance_share"] = 55.0
    with pytest.raises(jsonschema.ValidationError, match="maximum"):
        validator("fit").validate(wrong)
    wrong = copy.deepcopy(fit)
    wrong["error"]["holdout"]["joint_difference"]["dof"] = 0
    with pytest.raises(jsonschema.ValidationError, match="minimum"):
        validator("fit").validate(wrong)
    analyze = copy.deepcopy(documents["analyze"][0])
    analyze["coherence"] = {"pairs": []}
    validator("analyze").validate(analyze)


def test_a_filter_replacement_follows_the_schema(tmp_path):
    """A real diagnose document whose first suggestion replaces the model's filter (action
    "replace", with its label) validates, and an action outside the contract's does not."""
    from imunoise.analysis.noise_stream import simulate

    fs, n = 50.0, 360_000  # 2 h: a Bartlett window given to the model as a low-pass
    x = simulate([("white", {"N": 3e-4}), ("bias_instability", {"B": 5e-5}),
                  ("random_walk", {"K": 2e-6}), ("bartlett", {"taps": 3.0})], n, fs, rng=2)
    path = tmp_path / "bartlett.csv"
    np.savetxt(path, np.column_stack([np.arange(n) / fs, x]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    doc = _cli(["diagnose", str(path), "--channel", "gyro_x", "--model",
                "white,bias_instability,random_walk,lowpass"])
    top = doc["suggestions"][0]
    assert (top["action"], top["label"], top["significant"]) == \
        ("replace", "lowpass by bartlett", True)
    validator("diagnose").validate(doc)
    assert not validator("diagnose").is_valid(_broken(doc, ["suggestions", 0, "action"],
                                                      "swap"))
