"""Rolling analyzer: the live curve and fit are those of the batch tools, scheduling, history."""

from __future__ import annotations

import json
import os
import signal
import time

import numpy as np
import pytest

from imunoise.analysis.allan import oadev
from imunoise.analysis.channel_state import RecentSamples
from imunoise.analysis.fit import fit_allan, fit_series
from imunoise.cli import main
from imunoise.core.blocks import SampleBlock
from imunoise.live.channel import LiveChannel
from imunoise.live.scheduler import RollingAnalyzer
from imunoise.web.views import live as views

FS = 100.0
N_TRUE = 3e-3   # rad/s/sqrt(Hz)
K_TRUE = 2e-5   # rad/s/sqrt(s)
DEFAULT = "white,bias_instability,random_walk"


def _white_rw(n: int, seed: int, k: float = K_TRUE) -> np.ndarray:
    rng = np.random.default_rng(seed)
    white = rng.normal(0, N_TRUE * np.sqrt(FS), n)
    return white + np.cumsum(rng.normal(0, k / np.sqrt(FS), n))


def _feed_random_blocks(est, y: np.ndarray, seed: int = 0) -> None:
    rng = np.random.default_rng(seed)
    i = 0
    while i < y.size:
        k = int(rng.integers(1, 997))
        est.update(y[i:i + k])
        i += k


def _params(fit_terms) -> dict[tuple[str, str], float]:
    return {(t["term"], k): v for t in fit_terms for k, v in t["params"].items()}


def _cis(fit_terms) -> dict[tuple[str, str], list[float]]:
    return {(t["term"], k): v for t in fit_terms for k, v in t["ci95"].items()}


def test_live_curve_is_the_batch_octave_curve_across_gaps_and_block_sizes() -> None:
    y = _white_rw(150_000, 1)
    a = LiveChannel("gyro_x", FS, m0=512)  # exact to m = 512, strided (stride 1) beyond
    _feed_random_blocks(a, y[:60_000])
    a.update(y[60_000:], new_segment=True)
    live = a.curve()
    ref = oadev(y, FS, m="octave", segment_starts=[0, 60_000], ci=0.95)
    np.testing.assert_array_equal(live.m, ref.m)
    np.testing.assert_array_equal(live.n_terms, ref.n_terms)  # full-estimate counts
    np.testing.assert_allclose(live.dev, ref.dev, rtol=1e-9)
    assert np.all(live.ci_low < live.dev) and np.all(live.dev < live.ci_high)


def test_strided_curve_reports_full_counts_and_stays_within_its_band() -> None:
    y = _white_rw(300_000, 2)
    a = LiveChannel("gyro_x", FS)
    a._state._allan.history_points = 1 << 14  # force a coarse stride (16) beyond m0 = 4096
    a._state._allan._hist = np.zeros(1 << 14)
    a.update(y)
    live, ref = a.curve(), oadev(y, FS, m="octave", ci=0.95)
    np.testing.assert_array_equal(live.n_terms, ref.n_terms)
    exact = live.m <= 4096
    np.testing.assert_allclose(live.dev[exact], ref.dev[exact], rtol=1e-9)
    half = (ref.ci_high - ref.ci_low)[~exact] / 2
    assert np.all(np.abs(live.dev[~exact] - ref.dev[~exact]) < 0.1 * half)


@pytest.mark.parametrize(("model", "k"), [("white,random_walk", 3e-4), (DEFAULT, K_TRUE)])
def test_dashboard_coefficients_equal_imunoise_fit_on_the_same_samples(tmp_path, capsys,
                                                                        model, k) -> None:
    y = _white_rw(120_000, 3, k)
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.column_stack((np.arange(y.size) / FS, y)), delimiter=",",
               header="t,gyro_x", comments="", fmt="%.17g")
    assert main(["fit", str(path), "--channel", "gyro_x", "--model", model, "--json"]) == 0
    cli = json.loads(capsys.readouterr().out)
    rs = RollingAnalyzer(model=model.split(","))
    rs.update(SampleBlock(stream="/imu", t=np.arange(y.size) / FS, fs_hz=FS,
                          channels={"gyro_x": np.loadtxt(path, delimiter=",", skiprows=1)[:, 1]}))
    assert rs.refresh(force=True)
    live = views.coefficients(rs.get("gyro_x"))
    assert live["intervals"] == "profile" and live["fitted_samples"] == y.size
    p_live, p_cli = _params(live["model"]), _params(cli["model"])
    assert p_live.keys() == p_cli.keys()
    # The two curves agree to 1e-9 (streaming vs batch kernels); a weakly determined
    # parameter may amplify that to ~1e-5 relative, still a thousandth of its own interval.
    cis_cli = _cis(cli["model"])
    for k, v in p_cli.items():
        lo, hi = cis_cli[k]
        assert abs(p_live[k] - v) <= max(1e-6 * abs(v), 1e-3 * (hi - lo)), k
    for key, (lo, hi) in cis_cli.items():
        if lo > 0:
            assert _cis(live["model"])[key] == pytest.approx([lo, hi], abs=1e-3 * (hi - lo)), key
        else:
            # A term the data do not need sits at the bottom of its range (~1e-19), where
            # the likelihood is flat; the profile search narrows the upper end of [0, upper]
            # to 2 % from there (with five halvings only, the two ends differed by a factor
            # of 2.2 on one machine)
            live_lo, live_hi = _cis(live["model"])[key]
            assert live_lo == 0 and live_hi == pytest.approx(hi, rel=0.03), key
    # the same solution to the solver's tolerance (its parameters agree to 1e-6 above); a
    # term left at the bottom of its range still moves chi2/dof in the sixth digit
    assert live["error"]["chi2_per_dof"] == pytest.approx(cli["error"]["chi2_per_dof"],
                                                          rel=1e-5)
    assert live["failures"] == cli["failures"]
    allan = views.allan(rs.get("gyro_x"))
    np.testing.assert_allclose(allan["adev"], cli["allan"]["adev"], rtol=1e-9)
    # z is of order 1; the model curves agree to what the parameter agreement above allows
    # (a few 1e-6 relative), far inside the estimates' own scatter (several per cent)
    np.testing.assert_allclose(allan["z"], cli["allan"]["z"], atol=1e-3)
    np.testing.assert_allclose(allan["model_adev"], cli["allan"]["model_adev"], rtol=1e-4)


def test_warm_refits_track_the_cold_fit_and_long_records_stay_within_its_intervals() -> None:
    y = _white_rw(400_000, 4)  # beyond 2^18 samples: strided taus with stride 2
    a = LiveChannel("gyro_x", FS)
    a.update(y[:200_000])
    assert a.refit(full=True)
    a.update(y[200_000:])
    assert a.refit()  # warm start from the previous result, linearised intervals
    warm = views.coefficients(a)
    assert warm["intervals"] == "jacobian"
    cold = fit_allan(a.curve(), DEFAULT, intervals="jacobian")
    # The two solves stop at the solver's tolerance: a hundredth of the interval apart.
    for t in cold.terms:
        for k, v in t.params.items():
            lo, hi = t.ci95[k]
            assert abs(_params(warm["model"])[(t.term, k)] - v) < 0.01 * (hi - lo), k
    assert warm["error"]["chi2_per_dof"] == pytest.approx(cold.chi2_per_dof, rel=1e-3)
    batch, _ = fit_series(y, FS, DEFAULT)  # what ``imunoise fit`` gives on this record
    assert a.refit(full=True)
    live = views.coefficients(a)
    for t in batch.terms:
        lo, hi = t.ci95["N" if t.term == "white" else next(iter(t.params))]
        name = next(iter(t.params))
        v = _params(live["model"])[(t.term, name)]
        assert abs(v - t.params[name]) < 0.1 * (hi - lo), (t.term, v, t.params[name])


def test_psd_view_matches_the_fitted_model_and_survives_non_finite_samples() -> None:
    y = _white_rw(200_000, 3)
    y[100_000:100_010] = np.nan  # a burst of bad samples is a gap, not a crash
    a = LiveChannel("gyro_x", FS)
    _feed_random_blocks(a, y, seed=5)
    assert a.n_samples == 200_000 - 10 and a.n_segments == 2
    assert a.curve().n_terms[0] == 200_000 - 10 - 2  # no difference spans the gap
    a.refit()
    p = views.psd(a)
    f, psd, model = (np.array(p[k]) for k in ("f_hz", "psd", "model_psd"))
    assert p["units"] == "(rad/s)^2/Hz" and np.all(np.isfinite(psd))
    hi = f > 1.0
    inside = (np.array(p["ci_low"]) <= model) & (model <= np.array(p["ci_high"]))
    assert inside[hi].mean() > 0.85
    assert np.median(psd[hi] / (2 * N_TRUE**2)) == pytest.approx(1.0, abs=0.05)


def test_default_fit_recovers_coefficients_within_their_intervals() -> None:
    y = _white_rw(360_000, 4)
    a = LiveChannel("gyro_x", FS)
    _feed_random_blocks(a, y)
    assert a.refit(full=True)
    c = views.coefficients(a)
    terms = {t["term"]: t for t in c["model"]}
    lo, hi = terms["white"]["ci95"]["N"]
    assert lo <= N_TRUE <= hi and (hi - lo) / N_TRUE < 0.1
    lo, hi = terms["random_walk"]["ci95"]["K"]
    assert lo <= K_TRUE <= hi
    assert c["error"]["chi2_per_dof"] < 3.0 and c["failures"] == []
    assert terms["white"]["conventional"]["N"]["units"] == "deg/sqrt(h)"
    assert terms["white"]["conventional"]["N"]["value"] == pytest.approx(
        terms["white"]["params"]["N"] * 180 / np.pi * 60)


def test_adding_a_missing_sinusoid_lowers_the_error_and_removing_it_restores_it() -> None:
    t = np.arange(200_000) / FS
    y = _white_rw(t.size, 6) + 0.01 * np.sin(2 * np.pi * 2.7 * t)
    a = LiveChannel("gyro_x", FS)
    a.update(y)
    assert a.refit()
    before = views.coefficients(a)["error"]["chi2_per_dof"]
    assert before > 10 and views.coefficients(a)["failures"]
    change = views.model_change(a.add_term("sinusoid"))
    assert change["error_before"]["chi2_per_dof"] == before
    after = change["error_after"]["chi2_per_dof"]
    assert after < before / 10
    # The same as fitting the model from scratch, as ``imunoise fit`` would.
    ref, _ = fit_series(y, FS, DEFAULT + ",sinusoid")
    assert after == pytest.approx(ref.chi2_per_dof, rel=0.05)
    sine = next(m for m in views.coefficients(a)["model"] if m["term"] == "sinusoid")
    assert sine["params"]["f"] == pytest.approx(2.7, rel=1e-3)
    assert sine["params"]["A"] == pytest.approx(0.01, rel=0.05)
    hist = views.history(a)
    assert [h["revision"] for h in hist] == [0, 1]
    assert hist[1]["chi2_per_dof"] < hist[0]["chi2_per_dof"]
    # the PSD part beside the Allan part: the line missing from the spectrum, then modelled;
    # the same number /coefficients reports for the current fit
    assert hist[0]["psd_deviance_per_bin"] > 5.0 > hist[1]["psd_deviance_per_bin"]
    assert hist[1]["psd_deviance_per_bin"] == pytest.approx(
        views.coefficients(a)["error"]["psd"]["deviance_per_bin"], rel=1e-12)
    removed = views.model_change(a.remove_term("sinusoid"))
    assert removed["error_after"]["chi2_per_dof"] == before  # same model, same samples


def test_diagnosis_finds_the_missing_sinusoid_and_adding_it_gives_its_error() -> None:
    t = np.arange(120_000) / FS
    y = _white_rw(t.size, 6) + 0.01 * np.sin(2 * np.pi * 2.7 * t)
    rs = RollingAnalyzer()
    rs.update(SampleBlock(stream="/imu", t=t, fs_hz=FS, channels={"gyro_x": y}))
    rs.refresh(force=True)
    d = views.diagnosis(rs.get("gyro_x"))
    top = d["suggestions"][0]
    assert top["term"] == "sinusoid" and top["significant"]
    assert top["params"]["f"] == pytest.approx(2.7, rel=0.01)
    change = views.model_change(rs.get("gyro_x").add_term("sinusoid"))
    assert change["error_after"]["chi2_per_dof"] == pytest.approx(
        top["chi2_per_dof_after"], rel=0.05)


def test_scheduler_takes_channels_in_turn_within_its_cpu_budget() -> None:
    rs = RollingAnalyzer(cpu_budget=0.3, refit_interval_s=0.0, full_refit_interval_s=1e9)
    ys = {c: _white_rw(60_000, s) for s, c in enumerate(("gyro_x", "gyro_y", "gyro_z"))}
    for i in range(0, 60_000, 6000):
        rs.update(SampleBlock(stream="/imu", t=np.arange(6000) / FS, fs_hz=FS,
                              channels={c: y[i:i + 6000] for c, y in ys.items()}))
    order: list[str] = []
    cpu0, wall0 = time.thread_time(), time.monotonic()
    # at least 3 s and 3 jobs: the first job of each channel is a full fit, 0.3-0.55 s of CPU
    # depending on the machine, after which the budget holds the next one back 1-1.8 s
    while time.monotonic() - wall0 < 3.0 or (len(order) < 3 and time.monotonic() - wall0 < 30):
        n = rs.stats()["jobs_last_minute"]
        rs.refresh()
        if rs.stats()["jobs_last_minute"] > n:
            order.append(rs._jobs[-1][1])
        time.sleep(0.005)
        for c, y in ys.items():  # new data keeps every channel due
            rs.get(c).update(y[:100])
    cpu, wall = time.thread_time() - cpu0, time.monotonic() - wall0
    assert len(order) >= 3
    assert order[:3] == ["gyro_x", "gyro_y", "gyro_z"] or sorted(order[:3]) == sorted(ys)
    for k in range(len(order) - 2):  # round robin: no channel twice in three jobs
        assert len(set(order[k:k + 3])) == 3, order
    job_cpu = sum(j[3] for j in rs._jobs)
    longest = max(j[3] for j in rs._jobs)
    assert job_cpu <= 0.3 * wall + longest, (job_cpu, wall)
    assert cpu < 0.3 * wall + longest + 0.5  # the loop itself adds little
    s = rs.stats()
    assert set(s["median_cpu_s"]) & {"fit", "full"} and s["refit_period_s"] > 0


def test_model_errors_name_the_valid_terms() -> None:
    a = LiveChannel("gyro_x", FS)
    with pytest.raises(ValueError, match="valid terms: white, quantization"):
        a.add_term("flicker")
    with pytest.raises(ValueError, match="not in the model"):
        a.remove_term("sinusoid")
    with pytest.raises(ValueError, match="at least one term"):
        a.set_model([])
    with pytest.raises(ValueError, match="temperature term needs the whole temperature"):
        a.add_term("temperature")


def test_rolling_set_routes_channels_and_segments_on_gaps() -> None:
    rs = RollingAnalyzer(refit_interval_s=0.0)
    y = _white_rw(3000, 7)
    for i, gap in ((0, 0), (1000, 0), (2000, -1)):
        rs.update(SampleBlock(stream="/a/imu", t=np.arange(1000) / FS, fs_hz=FS, gap_before=gap,
                            channels={"gyro_x": y[i:i + 1000], "temp": np.full(1000, 25.0)}))
    rs.update(SampleBlock(stream="/b/imu", t=np.arange(10) / FS, fs_hz=FS,
                        channels={"gyro_x": np.zeros(10)}))
    assert rs.channels == ["gyro_x", "/b/imu:gyro_x"]
    a = rs.get("gyro_x")
    assert a.n_samples == 3000 and a.n_segments == 2
    with pytest.raises(KeyError, match="valid channels: gyro_x, /b/imu:gyro_x"):
        rs.get("temp")


def test_recent_samples_are_bounded_and_keep_segment_starts() -> None:
    r = RecentSamples(100)
    r.append(np.arange(60.0), True)
    r.append(np.arange(60.0, 90.0), False)
    r.append(np.arange(90.0, 130.0), True)
    values, starts = r.series()
    np.testing.assert_array_equal(values, np.arange(30.0, 130.0))
    np.testing.assert_array_equal(starts, [0, 60])
    r.append(np.arange(1000.0), False)
    values, starts = r.series()
    assert values.size == 100 and values[0] == 900.0 and list(starts) == [0]


def test_a_stuck_sensor_gives_no_curve_and_no_fit_rather_than_zeros() -> None:
    rs = RollingAnalyzer()
    rs.update(SampleBlock(stream="/imu", t=np.arange(10_000) / FS, fs_hz=FS,
                          channels={"gyro_x": np.full(10_000, 0.25)}))
    assert rs.refresh(force=True) is False
    a = rs.get("gyro_x")
    assert views.allan(a)["tau_s"] == [] and views.coefficients(a)["error"] is None
    assert views.diagnosis(a)["suggestions"] == []


def test_worker_process_gives_the_inline_numbers_and_its_cpu_is_counted() -> None:
    t = np.arange(60_000) / FS
    y = _white_rw(t.size, 8) + 0.01 * np.sin(2 * np.pi * 2.7 * t)
    block = SampleBlock(stream="/imu", t=t, fs_hz=FS, channels={"gyro_x": y})
    inline, worker = RollingAnalyzer(), RollingAnalyzer(workers="process")
    try:
        for rs in (inline, worker):
            rs.update(block)
            assert rs.refresh()  # the first job: a full fit
            rs.get("gyro_x").add_term("sinusoid")
        a = views.coefficients(inline.get("gyro_x"))
        b = views.coefficients(worker.get("gyro_x"))
        assert a["model"] == b["model"] and a["error"] == b["error"]
        assert worker.get("gyro_x").job_cpu_s > 0
        assert worker.stats()["cpu_s_total"] >= worker._jobs[0][3] > 0.01
        for proc in list(worker._worker._pool._processes.values()):
            os.kill(proc.pid, signal.SIGKILL)  # a dead worker is replaced
            proc.join(10)
        assert worker.get("gyro_x").refit(full=True)
        assert views.coefficients(worker.get("gyro_x"))["intervals"] == "profile"
    finally:
        worker.close()


def test_coefficients_say_the_interval_now_and_the_time_to_a_target():
    """serve --target: each targeted parameter's interval now and the recording still needed,
    from the plan for the fitted model (imunoise.analysis.planning)."""
    from imunoise.analysis.noise_stream import simulate
    from imunoise.analysis.planning import parse_targets, plan

    fs, n = 10.0, 6000  # ten minutes; K to +-20 % needs about 33 (test_planning)
    y = simulate([("white", {"N": 1e-3}), ("random_walk", {"K": 1e-4})], n, fs, rng=5)
    a = LiveChannel("gyro_x", fs, model=["white", "random_walk"],
                        targets="N=5%,K=20%")
    a.update(y)
    assert a.refit(full=True)
    c = views.coefficients(a)
    white, walk = c["model"]
    assert white["relative_halfwidth"]["N"] < 0.05 and white["time_to_target_s"]["N"] == 0.0
    assert walk["target"]["K"] == 0.2 and walk["relative_halfwidth"]["K"] > 0.2
    spec = [(t["term"], t["params"]) for t in c["model"]]
    (p,) = plan(spec, fs, parse_targets("K=20%", spec))
    assert walk["time_to_target_s"]["K"] == pytest.approx(p.record_s - 600.0)
    again = views.coefficients(a)["model"][1]["time_to_target_s"]  # from the plan cache
    assert again == walk["time_to_target_s"]


def test_the_psd_part_is_computed_once_per_history_interval() -> None:
    t = np.arange(100_000) / FS
    a = LiveChannel("gyro_x", FS)
    a.update(_white_rw(t.size, 7))
    calls: list[int] = []
    plain = a.runner

    def counting(fn, *args):
        calls.append(fn.__name__ == "streaming_psd_part")
        return plain(fn, *args)

    a.runner = counting
    assert a.refit(full=True) and sum(calls) == 1  # the first entry
    for seed in (8, 9):  # within the interval: the latest entry carries the interval's part
        a.update(_white_rw(2_000, seed))
        assert a.refit() and sum(calls) == 1
    hist = views.history(a)
    assert len(hist) == 2 and hist[0]["psd_deviance_per_bin"] is not None
    assert hist[1]["psd_deviance_per_bin"] == hist[0]["psd_deviance_per_bin"]
    a._state.history_interval_s = 0.0
    a.update(_white_rw(2_000, 10))
    assert a.refit() and sum(calls) == 2
    assert len(views.history(a)) == 3
