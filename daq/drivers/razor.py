"""SparkFun 9DOF Razor: an ITG-3200 and an ADXL345 on one I2C bus, recorded as two streams.

Each chip keeps its own clock and rate, so each is its own stream (``/razor/itg3200/imu``
with the gyro channels, ``/razor/adxl345/imu`` with the accelerometer channels) with its own
sample times. The gyro has no FIFO and is polled on its sample phase
(:class:`imunoise.daq.poll_schedule.DataReadySchedule`); the accelerometer's FIFO is drained right
after
a gyro sample has been read, when the gyro's next sample is furthest away, once
:data:`ADXL_EVERY_ENTRIES` have come (or ``adxl.poll_period_s`` has passed, if sooner) and
only until :data:`ADXL_SHARE` of a gyro period has passed since the poll began (the rest stays
in the FIFO for the next gyro period), so that at high gyro rates the shared bus is free, and
the poll over, well before the gyro's next sample is due.
"""

from __future__ import annotations

import math

from imunoise.core.blocks import SampleBlock
from imunoise.daq.drivers.adxl345 import Adxl345
from imunoise.daq.drivers.common import StreamBuffer
from imunoise.daq.drivers.itg3200 import Itg3200

ADXL_SHARE = 0.5
"""The accelerometer's drain ends this fraction of a gyro period after the poll began; when
the gyro's own read took that long (the simulated chip drawing its next chunk of noise, a slow
bus), the drain waits for the next gyro sample (the FIFO holds 32 samples)."""
ADXL_EVERY_ENTRIES = 8
"""The accelerometer is drained once about this many entries have come, a quarter of its FIFO,
so that the FIFO keeps room for a stall of the whole host of three quarters of its length
(30 ms at 800 Hz); drained only at its watermark (16), with drains cut short by the gyro's
next sample, it was often half full and a 38 ms stall overran it (simulated Razor at 1 kHz,
90 s: one overrun)."""
ADXL_URGENT_ENTRIES = 20
"""With this many entries possibly in the FIFO, it is drained after every gyro sample even
when the gyro's read used up its share of the period, and for :data:`ADXL_SHARE` of a gyro
period from the drain's own start: a stretch of slow gyro reads must not starve it until it
overruns, nor hold it full with one entry read per drain (both seen in the simulated Razor at
1 kHz on a slow host: 22 gyro reads in a row over half a period each took the FIFO from 15
entries to full, and drains that read one entry each kept it there)."""


class Razor:
    """Both chips of a Razor board on one bus."""

    name = "razor"
    model = "SparkFun 9DOF Razor (ITG-3200 + ADXL345)"
    polls_data_ready = True

    def __init__(self, itg: Itg3200, adxl: Adxl345) -> None:
        self.itg, self.adxl = itg, adxl
        self.rate_hz = itg.rate_hz
        self.poll_period_s = itg.poll_period_s
        self._adxl_due = -math.inf
        self._adxl_every_s = min(adxl.poll_period_s, ADXL_EVERY_ENTRIES / adxl.rate_hz)
        self.config: dict[str, str] = self._describe()

    @property
    def found_new_sample(self) -> bool:
        """Whether the last poll found a new gyro sample (the stream the polls lock to)."""
        return self.itg.found_new_sample

    def open(self) -> None:
        self.itg.open()
        self.adxl.open()
        self.config = self._describe()

    def _describe(self) -> dict[str, str]:
        """Both chips' configuration, keys prefixed with the chip name."""
        config = {"device": self.name, "model": self.model,
                  "rate_hz": self.itg.config["rate_hz"],
                  "accel_rate_hz": self.adxl.config["rate_hz"]}
        config.update({f"itg3200.{k}": v for k, v in self.itg.config.items()})
        config.update({f"adxl345.{k}": v for k, v in self.adxl.config.items()})
        return config

    def close(self) -> None:
        self.itg.close()
        self.adxl.close()

    def poll(self) -> int:
        clock = self.adxl.clock
        started = clock.now()
        n = self.itg.poll()
        now = clock.now()
        deadline = started + ADXL_SHARE / self.itg.rate_hz
        if n > 0 and now >= self._adxl_due:
            urgent = self.adxl.entries_at_most(now) >= ADXL_URGENT_ENTRIES
            if now >= deadline and not urgent:
                return n  # no time left before the next gyro sample; the FIFO waits
            if urgent:
                deadline = max(deadline, now + ADXL_SHARE / self.itg.rate_hz)
            # Right after a gyro sample, until ADXL_SHARE of a gyro period has passed; a
            # drain cut short goes on after the next gyro sample.
            n += self.adxl.poll(deadline=deadline)
        elif n == 0 and now >= self._adxl_due + 0.5 * self._adxl_every_s:
            # The gyro delivers nothing (data-ready stuck until it is reopened): no gyro
            # sample to make way for, and the accelerometer's FIFO must not overrun.
            n += self.adxl.poll()
        else:
            return n
        self._adxl_due = now if self.adxl.fifo_left else now + self._adxl_every_s
        return n

    def take_blocks(self) -> list[SampleBlock]:
        return self.itg.take_blocks() + self.adxl.take_blocks()

    @property
    def streams(self) -> list[StreamBuffer]:
        return self.itg.streams + self.adxl.streams
