"""A parsed recording is kept per state of its file (imunoise.daq.readers.record_cache)."""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pytest

from imunoise.core.record import Record
from imunoise.daq.readers import open_record, record_cache


@pytest.fixture()
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    folder = tmp_path / "cache"
    monkeypatch.setenv("IMUNOISE_CACHE_DIR", str(folder))
    monkeypatch.delenv("IMUNOISE_CACHE_MB", raising=False)
    return folder


def _csv(path: Path, n: int = 400, seed: int = 0, gap: bool = True, nan: bool = True) -> Path:
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 100.0
    if gap:
        t[n // 2:] += 0.5  # 50 samples lost: two segments
    data = rng.normal(size=(n, 3))
    if nan:
        data[7, 1] = np.nan  # removed on reading, with a warning
    temp = 20.0 + 0.01 * np.arange(n)
    np.savetxt(path, np.column_stack([t, data, temp]), delimiter=",", comments="",
               header="t,gyro_x,gyro_y,accel_z,temp", fmt="%.10g")
    _age(path)
    return path


def _age(path: Path, seconds: float = 60.0) -> None:
    """Set the file's modification time into the past (a file just written is not cached)."""
    then = time.time() - seconds
    os.utime(path, (then, then))


def _same(a: Record, b: Record) -> None:
    assert list(a.channels) == list(b.channels)
    for k in a.channels:
        sa, sb = a.channels[k], b.channels[k]
        assert (sa.name, sa.units, sa.fs_hz, sa.t0_s) == (sb.name, sb.units, sb.fs_hz, sb.t0_s)
        np.testing.assert_array_equal(sa.values, sb.values)
        np.testing.assert_array_equal(sa.segment_starts, sb.segment_starts)
    assert a.temperature is not None and b.temperature is not None
    np.testing.assert_array_equal(a.temperature.values, b.temperature.values)
    assert (a.metadata, a.warnings, a.facts) == (b.metadata, b.warnings, b.facts)


def test_a_second_read_comes_from_the_cache_and_is_the_same_record(tmp_path, cache):
    f = _csv(tmp_path / "a.csv")
    first = open_record(f)
    assert len(list(cache.glob("*.npz"))) == 1
    assert first.warnings and len(first.channels["gyro_x"].segment_starts) == 2
    hit = record_cache.load(f, None)
    assert hit is not None
    _same(first, hit)
    _same(first, open_record(f))


def test_a_changed_file_is_parsed_again(tmp_path, cache):
    f = _csv(tmp_path / "a.csv", seed=1)
    open_record(f)
    _csv(f, seed=2)  # same size and name, new contents and time stamp
    again = open_record(f)
    rng = np.random.default_rng(2)
    expected = rng.normal(size=(400, 3))[:, 0]
    np.testing.assert_allclose(again.channels["gyro_x"].values, expected, rtol=1e-9)


def test_a_file_still_being_written_is_not_cached(tmp_path, cache):
    f = _csv(tmp_path / "a.csv")
    _age(f, 0.0)
    open_record(f)
    assert not cache.exists() or not list(cache.glob("*.npz"))


def test_a_damaged_entry_is_removed_and_the_file_parsed_again(tmp_path, cache):
    f = _csv(tmp_path / "a.csv")
    first = open_record(f)
    (entry,) = cache.glob("*.npz")
    entry.write_bytes(entry.read_bytes()[:1000])  # truncated
    assert record_cache.load(f, None) is None and not entry.exists()
    _same(first, open_record(f))
    assert entry.exists()


def test_a_cache_that_cannot_be_written_costs_only_the_parse(tmp_path, monkeypatch):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("x")
    monkeypatch.setenv("IMUNOISE_CACHE_DIR", str(blocker / "cache"))
    f = _csv(tmp_path / "a.csv")
    rec = open_record(f)
    assert rec.channels["gyro_x"].n_samples == 400


def test_the_rate_given_is_part_of_the_entry(tmp_path, cache):
    f = _csv(tmp_path / "a.csv", gap=False)
    assert open_record(f).channels["gyro_x"].fs_hz == pytest.approx(100.0)
    assert open_record(f, rate_hz=50.0).channels["gyro_x"].fs_hz == 50.0
    assert len(list(cache.glob("*.npz"))) == 2


def test_size_zero_turns_it_off_and_a_small_limit_keeps_the_newest(tmp_path, cache,
                                                                    monkeypatch):
    monkeypatch.setenv("IMUNOISE_CACHE_MB", "0")
    open_record(_csv(tmp_path / "a.csv"))
    assert not cache.exists()
    files = [_csv(tmp_path / f"{k}.csv", n=4000, seed=k) for k in range(3)]
    monkeypatch.setenv("IMUNOISE_CACHE_MB", "0.3")  # room for two entries of 130 kB
    for k, f in enumerate(files):
        open_record(f)
        entries = sorted(cache.glob("*.npz"), key=lambda p: p.stat().st_mtime)
        os.utime(entries[-1], (time.time() - 10 + k, time.time() - 10 + k))
    entries = list(cache.glob("*.npz"))
    assert len(entries) == 2 and sum(p.stat().st_size for p in entries) <= 0.3 * 2**20
    assert record_cache.load(files[2], None) is not None
    assert record_cache.load(files[0], None) is None


def test_an_mcap_recording_with_a_gap_and_temperature_is_kept_whole(tmp_path, cache):
    from tests.mcap_helpers import make_blocks, record_blocks

    rec = record_blocks(tmp_path, make_blocks(4, 500, skip={2: 30}))
    f = Path(rec.stats.files[0])
    _age(f)
    first = open_record(f)
    assert len(first.channels["gyro_x"].segment_starts) == 2 and first.temperature is not None
    hit = record_cache.load(f, None)
    assert hit is not None
    _same(first, hit)
    seg = first.channels["gyro_x"].segment_t0_s
    if seg is not None:
        np.testing.assert_array_equal(seg, hit.channels["gyro_x"].segment_t0_s)
