"""The Razor's shared bus: the accelerometer's FIFO is drained after a gyro sample only while
half a gyro period remains, and waits otherwise, losing nothing, unless it may be filling up:
then it is drained all the same (simulated chips under the real smbus2, virtual clock)."""

from __future__ import annotations

from imunoise.daq.devices import open_device
from imunoise.daq.drivers.razor import ADXL_SHARE, ADXL_URGENT_ENTRIES

RATE_HZ = 1000.0


Drain = tuple[float, float | None, bool, float]


def _run(slow_every: int) -> tuple[dict, list[Drain]]:
    """Two seconds of the Razor at 1 kHz on a virtual clock; every ``slow_every``-th gyro read
    that finds a sample takes 0.6 of a period. Returns samples and gaps per stream and, per
    accelerometer drain, (poll start, deadline, whether the gyro read before it was slow, the
    driver's bound of the entries in the FIFO)."""
    acq = open_device("sim:razor", rate_hz=RATE_HZ, realtime=False, seed=3)
    acq.open()
    razor, clock = acq.driver, acq.clock
    period = 1.0 / razor.itg.rate_hz
    itg_poll, adxl_poll = razor.itg.poll, razor.adxl.poll
    state = {"fresh": 0, "slow": False, "started": 0.0}
    drains: list[Drain] = []

    def gyro() -> int:
        state["started"] = clock.now()
        n = itg_poll()
        state["slow"] = False
        if n:
            state["fresh"] += 1
            if slow_every and state["fresh"] % slow_every == 0:
                clock.advance(0.6 * period)  # a chunk of noise drawn, a slow transfer
                state["slow"] = True
        return n

    def accel(deadline: float | None = None) -> int:
        drains.append((state["started"], deadline, state["slow"],
                       razor.adxl.entries_at_most(clock.now())))
        return adxl_poll(deadline=deadline)

    razor.itg.poll, razor.adxl.poll = gyro, accel
    counts: dict[str, list[int]] = {}
    for block in acq.blocks(2.0):
        c = counts.setdefault(block.stream, [0, 0])
        c[0] += len(block)
        c[1] += max(0, block.gap_before)
    acq.close()
    return counts, drains


def test_a_slow_gyro_read_leaves_the_fifo_for_the_next_period():
    """Every tenth gyro read takes 0.6 of a period: no drain follows those unless the FIFO may
    be filling up, the others keep up (the accelerometer at 800 Hz, one entry or more after
    most of 900 gyro samples a second), and nothing is lost."""
    counts, drains = _run(slow_every=10)
    plain, _ = _run(slow_every=0)
    period = 1.0 / RATE_HZ
    after_sample = [d for d in drains if d[1] is not None]
    assert len(after_sample) > 1000
    # a drain begins after a gyro read that used up its share of the period only when the
    # FIFO may hold ADXL_URGENT_ENTRIES, and then has half a period from its own start
    after_slow = [d for d in after_sample if d[2]]
    assert all(bound >= ADXL_URGENT_ENTRIES for *_, bound in after_slow)
    assert len(after_slow) < 0.5 * len(after_sample) / 10
    # the others end half a gyro period after the poll began
    for started, deadline, _, bound in after_sample:
        if bound < ADXL_URGENT_ENTRIES:
            assert abs(deadline - (started + ADXL_SHARE * period)) < 1e-9
    # the FIFO waited and lost nothing; neither did the gyro
    gyro, accel = counts["/razor/itg3200/imu"], counts["/razor/adxl345/imu"]
    assert gyro[1] == 0 and accel[1] == 0
    assert abs(gyro[0] - 2.0 * RATE_HZ) <= 2
    # at most what the FIFO still held at the end differs from the run without slow reads
    assert plain["/razor/adxl345/imu"][0] - 32 <= accel[0] <= plain["/razor/adxl345/imu"][0]


def test_slow_gyro_reads_in_a_row_do_not_starve_the_fifo():
    """Every gyro read takes 0.6 of a period, longer than the accelerometer's share: once the
    FIFO may hold ADXL_URGENT_ENTRIES it is drained after each gyro sample all the same, for
    half a period from the drain's start, and overruns never (without that it filled in
    about 40 ms and overran for the rest of the run)."""
    counts, drains = _run(slow_every=1)
    accel = counts["/razor/adxl345/imu"]
    assert accel[1] == 0
    assert accel[0] >= 2.0 * 800 - 40  # all but what the FIFO held at the end
    assert sum(1 for d in drains if d[1] is not None) > 100
