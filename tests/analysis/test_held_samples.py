"""Held samples: repeated values beyond what the data's resolution explains."""

from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter

from imunoise.analysis.diagnosis import diagnose
from imunoise.analysis.evidence import held_samples
from imunoise.analysis.evidence.held import MIN_EXCESS
from tests.shared_paths import SHARED_DATA

FS = 100.0


def _hold(x: np.ndarray, starts: np.ndarray, length: int) -> np.ndarray:
    """``x`` with the sample before each start repeated over the next ``length`` samples."""
    y = x.copy()
    for s in starts:
        y[s:s + length] = y[s - 1]
    return y


def test_held_runs_are_counted_exactly():
    x = np.random.default_rng(1).standard_normal(200_000) * 1e-3
    starts = np.arange(1_000, 190_000, 2_000)  # 95 runs of 7 repeats each
    f = held_samples([_hold(x, starts, 7)], FS)
    assert f.significant and f.kind == "held_samples" and f.term is None
    assert f.params["count"] == 95 * 7 and f.details["runs"] == 95
    assert f.details["longest_samples"] == 7 and f.params["longest_s"] == pytest.approx(0.07)
    assert f.details["t_s"][:2] == pytest.approx([10.0, 30.0])
    assert f.details["run_samples"][:2] == [7, 7]
    assert f.params["share"] == pytest.approx(665 / 200_000)
    assert "665 samples" in f.why and "95 runs of up to 7 samples (0.07 s)" in f.why


def test_continuous_noise_without_holds_has_none():
    x = np.random.default_rng(2).standard_normal(100_000)
    f = held_samples([x], FS)
    assert not f.significant and f.params["count"] == 0
    assert f.why == "No held values: no sample equals the sample before it."


def test_a_pair_across_a_gap_is_no_repeat():
    rng = np.random.default_rng(3)
    a, b = rng.standard_normal(5_000), rng.standard_normal(5_000)
    b[0] = a[-1]  # equal values on either side of a gap
    assert held_samples([a, b], FS).params["count"] == 0
    assert held_samples([np.concatenate([a, b])], FS).params["count"] == 1


@pytest.mark.parametrize("kind", ["white", "moving_average", "markov"])
def test_chance_repeats_of_finely_quantized_noise_are_not_flagged(kind: str):
    # A resolution of 0.002-0.01 standard deviations makes a few hundred equal neighbours
    # in 1e5 samples by chance. The chance expectation is estimated within 30 % on every
    # seed (observed/expected 0.82-1.28 over 40 seeds of each kind), so none of them reaches
    # MIN_EXCESS times it.
    ratios = []
    for seed in range(40):
        x = np.random.default_rng(seed).standard_normal(100_000)
        if kind == "moving_average":
            x = np.convolve(x, np.ones(4) / 4, mode="same")
        elif kind == "markov":
            x = lfilter([1.0], [1.0, -0.9], x)
        q = (0.002, 0.004, 0.01)[seed % 3] * x.std()
        f = held_samples([np.round(x / q) * q], FS)
        assert f.details["testable"] and not f.significant
        ratios.append(f.statistic / f.details["expected_by_chance"])
    assert 0.9 < np.median(ratios) < 1.1
    assert 0.7 < min(ratios) and max(ratios) < 1.5 < MIN_EXCESS


@pytest.mark.parametrize("kind", ["white", "moving_average", "markov"])
def test_a_logger_reading_each_sample_twice_is_found_in_quantized_noise(kind: str):
    # counts whose first differences have a standard deviation of 8.5 steps: about 5 % of
    # neighbours equal by chance, within 20 % of the estimate; reading every sample twice
    # makes it over half
    x = np.random.default_rng(7).standard_normal(100_000)
    if kind == "moving_average":
        x = np.convolve(x, np.ones(4) / 4, mode="same")
    elif kind == "markov":
        x = lfilter([1.0], [1.0, -0.9], x)
    x = np.round(6.0 * np.sqrt(2.0) * x / np.diff(x).std())
    clean = held_samples([x], FS)
    assert clean.details["testable"] and not clean.significant
    assert 0.8 < clean.statistic / clean.details["expected_by_chance"] < 1.25
    twice = x.copy()
    twice[1::2] = twice[0::2]
    f = held_samples([twice], FS)
    assert f.significant and f.params["share"] > 0.5
    assert f.statistic > 5 * f.details["expected_by_chance"]


def test_coarse_data_cannot_be_judged():
    x = np.round(np.random.default_rng(4).standard_normal(50_000) * 2.0)  # counts, sigma 2
    x = _hold(x, np.arange(100, 49_000, 1_000), 10)
    f = held_samples([x], FS, units="m/s^2")
    assert not f.significant and f.p_value == 1.0 and not f.details["testable"]
    assert f.details["resolution"] == 1.0
    assert f.details["chance_per_pair"] > 0.1
    assert "held values cannot be told apart" in f.why and "1 m/s^2" in f.why


def test_a_channel_that_never_changes_is_held_throughout():
    f = held_samples([np.full(1_000, 0.25)], FS)
    assert f.significant and f.p_value == 0.0 and f.params["count"] == 999
    assert f.why.startswith("The channel never changes: all 1000 samples equal 0.25 rad/s.")


def test_a_channel_stuck_at_its_start_says_it_cannot_judge():
    x = np.concatenate([np.full(140_000, 0.5), np.random.default_rng(9).standard_normal(1_000)])
    f = held_samples([x], FS)
    assert not f.significant and not f.details["testable"]
    assert f.details["longest_samples"] == 139_999 and f.details["expected_by_chance"] is None
    assert f.why.startswith("The first 131072 samples never change, so the data's resolution")
    assert "the longest run 139999 samples (1.4e+03 s)" in f.why


def test_too_short_a_record_says_so():
    f = held_samples([np.array([1.0, 1.0])], FS)
    assert not f.significant and f.why == "Too few samples to look for held values."


def test_diagnose_lists_held_samples_in_its_evidence():
    rng = np.random.default_rng(5)
    x = _hold(rng.standard_normal(60_000) * 1e-3, np.arange(500, 59_000, 600), 5)
    kinds = {f.kind: f for f in diagnose(x, FS, "white").findings}
    assert kinds["held_samples"].significant
    assert kinds["held_samples"].params["count"] == 98 * 5


def _need(path: Path) -> Path:
    if not path.exists():
        pytest.skip(f"reference data {path} not available (needs ../shared next to the repo)")
    return path


def test_galaxy_s5_resampled_night_holds_its_samples():
    d = np.load(_need(SHARED_DATA / "galaxy_s5" / "galaxy_s5_static_10hz.npz"))
    f = held_samples([d["gyro"][:, 1]], float(d["fs"]))
    assert f.significant
    assert f.params["count"] == 14254 and f.details["runs"] == 3318
    assert f.details["longest_samples"] == 19 and f.params["longest_s"] == pytest.approx(1.9)
    assert f.details["expected_by_chance"] < 10


def test_adis16405_gyro_repeats_are_chance_accels_too_coarse_mtig_has_none():
    d = np.load(_need(SHARED_DATA / "adis16405" / "run1.npz"))
    gyro = d["gyro_counts"][:, 0] * float(d["gyro_scale_dps"]) * np.pi / 180.0
    f = held_samples([gyro], 100.0)
    assert f.details["testable"] and not f.significant
    # the chance estimate matches the share of equal neighbours the counts show (0.045)
    assert f.details["chance_per_pair"] == pytest.approx(np.mean(np.diff(gyro) == 0), rel=0.1)
    accel = held_samples([d["accel_counts"][:, 0] * 1.0], 100.0)
    assert not accel.significant and not accel.details["testable"]
    m = np.load(_need(SHARED_DATA / "mtig_outliers" / "gyro_x.npz"))["gyro_x"]
    g = held_samples([m], 100.0)
    assert not g.significant and g.params["count"] == 0


def test_counted_block_by_block_as_in_one_piece():
    from imunoise.analysis.evidence.held import HeldCounter

    rng = np.random.default_rng(8)
    x = _hold(rng.standard_normal(30_000), np.arange(50, 29_000, 97), 6)
    x[10_000:10_040] = x[9_999]  # a long run
    whole = held_samples([x[:20_000], x[20_000:]], FS)
    # 400 random cuts, the gap between the segments, and cuts inside the long run and at its
    # edges, so that runs continue across blocks and blocks of one sample occur
    cuts = np.union1d(rng.choice(np.arange(1, 30_000), 400, replace=False),
                      [10_000, 10_001, 10_020, 10_040, 20_000])
    counter = HeldCounter()
    for k, part in enumerate(np.split(x, cuts)):
        if k == 0 or cuts[k - 1] == 20_000:
            counter.new_segment()
        counter.update(part)
    f = counter.finding(FS)
    assert f.to_dict() == whole.to_dict()
    assert whole.details["longest_samples"] == 40 and whole.details["runs"] > 290


def test_the_counter_keeps_its_own_copy_of_a_block():
    from imunoise.analysis.evidence.held import HeldCounter

    x = np.random.default_rng(10).standard_normal(5_000)
    counter = HeldCounter()
    counter.new_segment()
    block = x.copy()
    counter.update(block)
    block[:] = 0.0  # a reader refilling its buffer
    assert counter.finding(FS).to_dict() == held_samples([x], FS).to_dict()


def test_fit_warns_of_held_samples_in_json_and_text(tmp_path, capsys):
    import json

    from imunoise.cli import main

    rng = np.random.default_rng(11)
    x = _hold(rng.standard_normal(20_000) * 1e-3, np.arange(300, 19_000, 400), 4)
    path = tmp_path / "held.csv"
    np.savetxt(path, np.column_stack([np.arange(x.size) / FS, x]), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.10g")
    warning = ("188 samples (0.94 %) repeat the sample before them exactly, in runs of up to "
               "0.04 s: held values, not measurements (diagnose's held_samples evidence says "
               "more)")
    args = ["fit", str(path), "--channel", "gyro_x", "--model", "white,random_walk"]
    assert main([*args, "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["warnings"] == [warning]
    assert main(args) == 0
    assert capsys.readouterr().err.strip() == f"warning: {warning}"
