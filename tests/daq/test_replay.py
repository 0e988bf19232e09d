import numpy as np

from imunoise.cli import main
from imunoise.core.blocks import SampleBlock
from imunoise.daq.replay import ReplaySummary, open_blocks, replay
from tests.mcap_helpers import make_blocks, record_blocks


class _FakeTime:
    def __init__(self):
        self.now = 0.0

    def clock(self):
        return self.now

    def sleep(self, s):
        self.now += s


def _white(n, fs, sigma, seed=0, gap_at=None):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    blocks = []
    for a in range(0, n, 1000):
        sl = slice(a, min(a + 1000, n))
        blocks.append(SampleBlock("/d/imu", t[sl], {"gyro_x": rng.normal(0, sigma, sl.stop - a)},
                                  fs, gap_before=3 if a == gap_at else 0))
    return blocks


def test_paced_replay_follows_the_sample_clock():
    fake = _FakeTime()
    got = []
    blocks = _white(5000, 100.0, 1.0)  # 50 s of samples
    replay(iter(blocks), got.append, speed=5.0, sleep=fake.sleep, clock=fake.clock)
    assert abs(fake.now - 49.99 / 5.0) < 0.01
    assert all(len(b) <= 50 for b in got)  # 0.1 s of sample time per piece, times the speed
    assert sum(len(b) for b in got) == 5000


def test_unpaced_replay_never_sleeps():
    fake = _FakeTime()
    got = []
    replay(iter(_white(3000, 100.0, 1.0)), got.append, speed=None, sleep=fake.sleep,
           clock=fake.clock)
    assert fake.now == 0.0 and len(got) == 3


def test_summary_white_noise_density_and_gaps():
    fs, sigma = 200.0, 0.02
    summary = ReplaySummary()
    for b in _white(40_000, fs, sigma, seed=4, gap_at=20_000):
        summary(b)
    (row,) = summary.rows()
    assert row["samples"] == 40_000 and row["gaps"] == 1
    # std of white noise estimated from 40k differences: relative spread about 0.5 %
    assert abs(row["white_noise_density"] / (sigma / np.sqrt(fs)) - 1) < 0.03


def test_replay_command_streams_an_mcap_file(tmp_path, capsys):
    rec = record_blocks(tmp_path, make_blocks(5, 200, skip={2: 4}))
    blocks, total = open_blocks(rec.stats.files[0])
    assert total == 1000
    assert main(["replay", rec.stats.files[0], "--speed", "max"]) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("/adis16350/imu:gyro_x"))
    assert line.split()[1:4] == ["1000", "10.0s", "1"]
