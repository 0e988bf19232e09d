"""Assemble the I2C devices (ITG-3200, ADXL345, Razor) on a real or simulated bus."""

from __future__ import annotations

from collections.abc import Callable

from daq.acquisition import Acquisition
from daq.clock import Clock
from daq.drivers.adxl345 import Adxl345, odr_hz, rate_code
from daq.drivers.itg3200 import Itg3200, rate_settings
from daq.drivers.razor import Razor
from daq.transports.i2c import I2CBus


class SimulatedRig:
    """Handles on the simulated chips and adapter of a simulated I2C device (for faults)."""

    def __init__(self, adapter, itg=None, adxl=None) -> None:
        self.adapter = adapter
        self.itg = itg
        self.adxl = adxl


def build_i2c_acquisition(which: str, *, simulated: bool, bus: int | None, rate: float,
                          seed: int, clock: Clock, options: dict) -> Acquisition:
    """Acquisition of ``itg3200``, ``adxl345`` or ``razor`` on bus ``bus`` or a simulator."""
    itg_addr = int(options.pop("itg_address", 0x68))
    adxl_addr = int(options.pop("adxl_address", 0x53))
    range_g = int(options.pop("range_g", 16))
    accel_rate = float(options.pop("accel_rate_hz", rate))
    retries = int(options.pop("retries", 3))
    opener: Callable | None = None
    rig = None
    if simulated:
        from daq.sim.adxl345 import Adxl345Sim
        from daq.sim.fake_i2c import SimulatedI2CAdapter
        from daq.sim.itg3200 import Itg3200Sim
        from daq.sim.signals import default_sources

        chips: dict = {}
        itg_sim = adxl_sim = None
        noise = options.pop("noise", None)
        if which in ("itg3200", "razor"):
            fs = rate_settings(rate)[2]
            gyro = options.pop("gyro", None) or default_sources("itg3200", fs, seed, noise)[0]
            itg_sim = Itg3200Sim(clock, gyro, options.pop("temperature", None),
                                 address=itg_addr)
            chips[itg_addr] = itg_sim
        if which in ("adxl345", "razor"):
            fs = odr_hz(rate_code(accel_rate))
            accel = options.pop("accel", None) or default_sources("adxl345", fs, seed, noise)[1]
            adxl_sim = Adxl345Sim(clock, accel)
            chips[adxl_addr] = adxl_sim
        adapter = SimulatedI2CAdapter(chips, clock=clock,
                                      bus_hz=float(options.pop("bus_hz", 400e3)))
        opener = adapter.open_bus
        rig = SimulatedRig(adapter, itg_sim, adxl_sim)
        bus = 0 if bus is None else bus
    assert bus is not None
    i2c = I2CBus(bus, retries=retries, clock=clock, opener=opener,
                 label=f"simulated I2C bus {bus}" if simulated else None)
    driver: Itg3200 | Adxl345 | Razor
    if which == "itg3200":
        driver = Itg3200(i2c, rate_hz=rate, address=itg_addr, clock=clock, **options)
    elif which == "adxl345":
        driver = Adxl345(i2c, rate_hz=accel_rate, range_g=range_g, address=adxl_addr,
                         clock=clock, **options)
    else:
        driver = Razor(
            Itg3200(i2c, rate_hz=rate, address=itg_addr, prefix="/razor/itg3200", clock=clock),
            Adxl345(i2c, rate_hz=accel_rate, range_g=range_g, address=adxl_addr,
                    prefix="/razor/adxl345", clock=clock))
    acq = Acquisition(driver, clock=clock)
    acq.simulator = rig
    return acq
