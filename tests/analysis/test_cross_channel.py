"""The record's cross-channel document: coherence, classification, subtraction summary."""

from __future__ import annotations

import json

import numpy as np
import pytest

from imunoise.analysis.cross_channel import cross_channel_view
from tests.analysis.bench_records import NAMES, bench_record


def test_document_of_a_simulated_bench():
    x, _ = bench_record(41, n=1 << 17)
    values = {f"/imu:{c}": x[:, k] for k, c in enumerate(NAMES)}
    doc, residuals = cross_channel_view(values, 100.0, subtract=True)
    json.dumps(doc)  # JSON-ready
    assert len(doc["pairs"]) == 15
    assert np.shape(doc["msc"]) == (15, len(doc["f_hz"]))
    assert np.shape(doc["ci"]["low"]) == np.shape(doc["msc"])
    assert len(doc["threshold"]) == len(doc["f_hz"])
    lines = {(c["channel"], round(c["f_hz"], 1)): c for c in doc["classification"]}
    assert lines[("/imu:accel_x", 0.6)]["origin"] == "common"
    assert lines[("/imu:accel_z", 3.3)]["origin"] == "own"
    assert "linear vibration" in lines[("/imu:accel_x", 0.6)]["why"]
    assert set(doc["subtraction"]) == set(values)
    assert residuals["/imu:accel_y"].residual.shape == (1 << 17,)


def test_suggestions_are_classified_when_given():
    x, _ = bench_record(42, n=1 << 15)
    values = {c: x[:, k] for k, c in enumerate(NAMES)}
    sugg = {"accel_y": [{"term": "sinusoid", "params": {"A": 0.01, "f": 0.56},
                         "significant": True}]}
    doc, _ = cross_channel_view(values, 100.0, suggestions=sugg)
    mine = [c for c in doc["classification"] if c["channel"] == "accel_y"]
    assert mine[0]["source"] == "suggestion" and mine[0]["origin"] == "common"


def test_one_channel_or_unaligned_channels_are_value_errors():
    with pytest.raises(ValueError, match="two channels"):
        cross_channel_view({"a": np.zeros(100)}, 100.0)
    with pytest.raises(ValueError, match="time base"):
        cross_channel_view({"a": np.zeros(100), "b": np.zeros(90)}, 100.0)


def test_only_the_chosen_channels_are_classified():
    x, _ = bench_record(43, n=1 << 15)
    values = {c: x[:, k] for k, c in enumerate(NAMES)}
    sugg = {"accel_y": [{"term": "sinusoid", "params": {"A": 0.002, "f": 1.5},
                         "significant": True, "why": "A line."}]}
    doc, res = cross_channel_view(values, 100.0, suggestions=sugg, only=["accel_y"],
                                  subtract=True)
    assert {c["channel"] for c in doc["classification"]} == {"accel_y"}
    assert list(res) == ["accel_y"]
    assert doc["classification"][0]["common_with"] == ["gyro_x"]
    assert sugg["accel_y"][0]["why"].startswith("A line. Common, not accel_y's own")
    assert sugg["accel_y"][0]["origin"] == "common"


def test_coherence_computed_beforehand_gives_the_same_document():
    from imunoise.analysis.coherence import cross_spectra, log_coherence

    x, _ = bench_record(44, n=1 << 15)
    values = {c: x[:, k] for k, c in enumerate(NAMES)}
    sugg = {"accel_y": [{"term": "sinusoid", "params": {"A": 0.002, "f": 1.5},
                         "significant": True, "why": "A line."}]}
    doc, _ = cross_channel_view(values, 100.0, suggestions=sugg, only=["accel_y"])
    co = log_coherence(cross_spectra(x, 100.0, NAMES))
    again = {"accel_y": [dict(sugg["accel_y"][0], why="A line.")]}
    given, _ = cross_channel_view(values, 100.0, suggestions=again, only=["accel_y"],
                                  coherence=co)
    assert json.dumps(given) == json.dumps(doc)
    other = log_coherence(cross_spectra(x[:, ::-1], 100.0, NAMES[::-1]))
    with pytest.raises(ValueError, match="coherence given is of"):
        cross_channel_view(values, 100.0, coherence=other)
    with pytest.raises(ValueError, match="at ci 0.95"):
        cross_channel_view(values, 100.0, coherence=co, ci=0.9)
