"""The shared timing model: rate, real gaps, jitter re-timed on the grid, same answer from every
reader."""

from __future__ import annotations

import numpy as np
import pytest

from imunoise.core.blocks import SampleBlock
from imunoise.core.timing import analyse_stamps
from imunoise.daq.readers import open_record
from tests.mcap_helpers import record_blocks

FS = 250.0
P = 1.0 / FS


def host_stamped(seed: int, n_kept: int = 14_000, lost: int = 97, late: int = 132,
                 t0: float = 1.7e9) -> tuple[np.ndarray, np.ndarray]:
    """A 250 Hz sensor stamped by a computer on receipt: ``lost`` samples really missing,
    ``late`` stamps delayed by 0.6 to 1.8 periods (the next one on time again, so it looks
    early), and 5 % of a period of ordinary latency noise. Returns (stamps in ns, lost grid
    positions)."""
    rng = np.random.default_rng(seed)
    n = n_kept + lost
    gone = np.sort(rng.choice(np.arange(100, n - 100), lost, replace=False))
    keep = np.ones(n, bool)
    keep[gone] = False
    t = np.arange(n)[keep] * P + rng.normal(0.0, 0.05 * P, n_kept)
    delayed = rng.choice(np.arange(10, n_kept - 10), late, replace=False)
    t[delayed] += rng.uniform(0.6, 1.8, late) * P
    return np.rint((t0 + t) * 1e9).astype(np.int64), gone


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_jitter_is_retimed_and_only_real_losses_are_gaps(seed):
    ns, gone = host_stamped(seed)
    tm = analyse_stamps(ns, name="/imu")
    assert tm.missing == 97
    # adjacent losses merge into one gap: one segment per run of lost grid positions
    runs = 1 + int(np.count_nonzero(np.diff(gone) > 1))
    assert len(tm.segment_starts) == runs + 1
    assert tm.backward == 0
    # the rate from 56 s of stamps whose noise is 5 % of a period: far better than 1e-4
    assert tm.fs_hz == pytest.approx(FS, rel=1e-5)
    assert 0.8 * P < tm.jitter_max_s < 2.0 * P
    assert any("re-timed on the grid, not treated as gaps" in n for n in tm.notes)
    assert any("97 sample(s) missing" in n for n in tm.notes)


def test_jitter_alone_is_one_segment():
    ns, _ = host_stamped(5, lost=0)
    tm = analyse_stamps(ns)
    assert tm.missing == 0 and list(tm.segment_starts) == [0]
    assert tm.fs_hz == pytest.approx(FS, rel=1e-5)


def test_sequence_numbers_decide_the_losses():
    n = 5000
    seq = np.arange(n) + 7
    seq[3000:] += 4  # four messages lost
    t = seq * P + np.random.default_rng(3).normal(0, 0.3 * P, n)  # stamps too noisy to tell
    tm = analyse_stamps(t, seq=seq)
    assert tm.missing == 4 and list(tm.segment_starts) == [0, 3000]
    assert tm.fs_hz == pytest.approx(FS, rel=1e-4)


def test_quantised_stamps_and_a_given_rate():
    rng = np.random.default_rng(1)
    t = np.round(np.arange(3000) / 300.0 + rng.uniform(0, 1e-4, 3000), 3)  # 1 ms stamps
    tm = analyse_stamps(t)
    assert tm.missing == 0 and list(tm.segment_starts) == [0]
    assert tm.fs_hz == pytest.approx(300.0, rel=1e-4)
    assert analyse_stamps(t, rate_hz=301.0).fs_hz == 301.0


def test_time_going_backwards_is_a_boundary_and_counted():
    t = np.arange(200) * P
    t[120:] -= 30 * P
    tm = analyse_stamps(t)
    assert list(tm.segment_starts) == [0, 120] and tm.backward == 1 and tm.missing == 0
    with pytest.raises(ValueError, match="fewer than two increasing"):
        analyse_stamps(np.array([5.0, 5.0]))


def test_csv_and_mcap_of_the_same_stamps_give_the_same_timing(tmp_path):
    ns, _ = host_stamped(4, n_kept=6000, lost=20, late=60)
    t = ns.astype(np.float64) * 1e-9
    values = np.random.default_rng(0).normal(0, 1e-3, ns.size)
    csv = tmp_path / "imu.csv"
    with open(csv, "w") as f:
        f.write("t,gyro_x\n")
        for sec, nsec, v in zip(ns // 10**9, ns % 10**9, values, strict=True):
            f.write(f"{sec}.{nsec:09d},{float(v)!r}\n")
    zeros = np.zeros_like(values)
    block = SampleBlock("/adis16350/imu", t,
                        {"gyro_x": values, "gyro_y": zeros, "gyro_z": zeros}, FS)
    record_blocks(tmp_path / "bag", [block])
    (mcap,) = (tmp_path / "bag").glob("*.mcap")
    a = open_record(csv).channels["gyro_x"]
    b = open_record(mcap).channels["gyro_x"]
    assert a.fs_hz == b.fs_hz
    np.testing.assert_array_equal(a.segment_starts, b.segment_starts)
    assert len(a.segment_starts) > 1
    np.testing.assert_array_equal(a.values, b.values)
    # replaying the file block by block sees the same gaps, not one per late stamp
    from imunoise.daq.readers.mcap import iter_blocks

    blocks = [blk for blk in iter_blocks(mcap) if "gyro_x" in blk.channels]
    assert sum(blk.gap_before != 0 for blk in blocks) == len(b.segment_starts) - 1
    assert sum(len(blk) for blk in blocks) == b.n_samples
