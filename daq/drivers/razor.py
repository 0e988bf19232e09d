"""SparkFun 9DOF Razor: an ITG-3200 and an ADXL345 on one I2C bus, recorded as two streams.

Each chip keeps its own clock and rate, so each is its own stream (``/razor/itg3200/imu``
with the gyro channels, ``/razor/adxl345/imu`` with the accelerometer channels) with its own
sample times. The gyro is polled at its rate; the accelerometer FIFO is drained every
``adxl.poll_period_s`` by count of gyro polls.
"""

from __future__ import annotations

import math

from core.blocks import SampleBlock
from daq.drivers.adxl345 import Adxl345
from daq.drivers.common import StreamBuffer
from daq.drivers.itg3200 import Itg3200


class Razor:
    """Both chips of a Razor board on one bus."""

    name = "razor"
    model = "SparkFun 9DOF Razor (ITG-3200 + ADXL345)"

    def __init__(self, itg: Itg3200, adxl: Adxl345) -> None:
        self.itg, self.adxl = itg, adxl
        self.rate_hz = itg.rate_hz
        self.poll_period_s = itg.poll_period_s
        self.adxl_every = max(1, int(math.floor(adxl.poll_period_s / itg.poll_period_s)))
        self._n = 0
        self.config: dict[str, str] = self._describe()

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
        n = self.itg.poll()
        self._n += 1
        if self._n % self.adxl_every == 0:
            n += self.adxl.poll()
        return n

    def take_blocks(self) -> list[SampleBlock]:
        return self.itg.take_blocks() + self.adxl.take_blocks()

    @property
    def streams(self) -> list[StreamBuffer]:
        return self.itg.streams + self.adxl.streams
