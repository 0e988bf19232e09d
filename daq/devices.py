"""Open a device by name: real hardware or a register-level simulator behind real transports.
The one place where a board is assembled: driver, transport, and for ``sim:`` devices the
chip models and their sources.

``open_device("sim:adis16350")`` starts a Bus Pirate emulator on a pseudo-terminal with the
ADIS16350 model behind it and drives it with the real driver through the real pyserial;
``open_device("sim:razor")`` puts the ITG-3200 and ADXL345 models under smbus2's ioctl layer.
"""

from __future__ import annotations

from collections.abc import Callable

from imunoise.daq.acquisition import Acquisition
from imunoise.daq.clock import Clock, RealClock, VirtualClock

DEVICES: dict[str, str] = {
    "adis16350": "ADIS16350 through a Bus Pirate serial-SPI bridge (--port)",
    "itg3200": "ITG-3200 gyroscope on I2C (--bus)",
    "adxl345": "ADXL345 accelerometer on I2C (--bus)",
    "razor": "ITG-3200 + ADXL345 on one I2C bus (--bus), as two streams",
    "sim:adis16350": "simulated ADIS16350 behind an emulated Bus Pirate on a pty",
    "sim:itg3200": "simulated ITG-3200 under smbus2",
    "sim:adxl345": "simulated ADXL345 under smbus2",
    "sim:razor": "simulated ITG-3200 + ADXL345 under smbus2",
}
DEFAULT_RATES_HZ = {"adis16350": 102.4, "itg3200": 100.0, "adxl345": 100.0, "razor": 100.0}


def valid_devices() -> str:
    return ", ".join(DEVICES)


def open_device(spec: str, *, port: str | None = None, bus: int | None = None,
                rate_hz: float | None = None, seed: int | None = None,
                realtime: bool = True, clock: Clock | None = None,
                max_outage_s: float = 30.0, **options: object) -> Acquisition:
    """An :class:`Acquisition` for ``spec`` (see :data:`DEVICES`), not yet opened.

    Args:
        spec: device name; ``sim:`` prefixes select the simulators.
        port: serial port of the Bus Pirate (``adis16350``).
        bus: I2C bus number (``itg3200``, ``adxl345``, ``razor``).
        rate_hz: sample rate (the nearest one the chip supports is used; see ``config``).
        seed: seed of the simulated noise.
        realtime: simulators run in real time (False: as fast as the host allows, on a
            virtual clock shared by simulator and acquisition).
        clock: explicit clock (overrides ``realtime``).
        max_outage_s: how long the device may stay unreachable before the run fails.
        options: driver options (``range_dps``, ``taps``, ``range_g``, ``address``...) and
            simulator options (``gyro``, ``accel``, ``temperature`` sources; ``noise``, the
            :data:`imunoise.daq.sim.signals.NoiseFactory` that draws the default sources, e.g.
            :func:`imunoise.analysis.noise_stream.stream_factory`; without it they are white noise;
            ``bench``, a :class:`imunoise.daq.sim.bench.BenchPlacement`: the simulated chips
            also see that bench's motion).

    Raises:
        ValueError: unknown spec, or a missing ``port``/``bus``, naming the valid choices.
    """
    if spec not in DEVICES:
        raise ValueError(f"unknown device {spec!r}: choose one of {valid_devices()}")
    simulated = spec.startswith("sim:")
    base = spec.removeprefix("sim:")
    if not simulated:
        options.pop("noise", None)  # simulators' options: real hardware makes its own
        options.pop("bench", None)
    rate = float(rate_hz) if rate_hz is not None else DEFAULT_RATES_HZ[base]
    if rate <= 0:
        raise ValueError(f"rate must be positive, got {rate_hz}")
    if clock is None:
        clock = RealClock() if (realtime or not simulated) else VirtualClock()
    if not simulated:
        if base == "adis16350" and not port:
            raise ValueError("device adis16350 needs --port (the Bus Pirate's serial port, "
                             "e.g. /dev/ttyUSB0)")
        if base != "adis16350" and bus is None:
            raise ValueError(f"device {base} needs --bus (the I2C bus number, e.g. 1 for "
                             "/dev/i2c-1)")
    builder = _BUILDERS[base]
    acq = builder(simulated=simulated, port=port, bus=bus, rate=rate,
                  seed=0 if seed is None else int(seed), clock=clock, options=dict(options))
    acq.max_outage_s = float(max_outage_s)
    return acq


def _adis(*, simulated: bool, port: str | None, bus: int | None, rate: float, seed: int,
          clock: Clock, options: dict) -> Acquisition:
    from imunoise.daq.drivers.adis16350 import Adis16350, sample_rate_hz, smpl_prd_for_rate
    from imunoise.daq.transports.buspirate import BusPirateSPI

    cleanup: list[Callable[[], None]] = []
    sim = None
    emulator = None
    if simulated:
        from imunoise.daq.sim.adis16350 import Adis16350Sim
        from imunoise.daq.sim.buspirate_pty import BusPirateEmulator, ChipClock
        from imunoise.daq.sim.signals import default_sources

        fs = sample_rate_hz(smpl_prd_for_rate(rate))
        gyro, accel = default_sources("adis16350", fs, seed, options.pop("noise", None))
        chip_clock = ChipClock(clock)
        sim = Adis16350Sim(chip_clock, options.pop("gyro", gyro), options.pop("accel", accel),
                           options.pop("temperature", None), source_rate_hz=fs)
        bench = options.pop("bench", None)
        if bench is not None:
            sim.environment = bench.view()
        emulator = BusPirateEmulator(sim, seed=seed, chip_clock=chip_clock).start()
        cleanup.append(emulator.close)
        port = emulator.port
        sim.emulator = emulator
    spi = BusPirateSPI(str(port), timeout_s=float(options.pop("timeout_s", 0.5)),
                       opener=emulator.serial_opener(clock) if emulator else None)
    driver = Adis16350(spi, rate_hz=rate, clock=clock, **options)
    acq = Acquisition(driver, clock=clock, on_close=cleanup)
    acq.simulator = sim
    return acq


class SimulatedRig:
    """Handles on the simulated chips and adapter of a simulated I2C device (for faults)."""

    def __init__(self, adapter, itg=None, adxl=None) -> None:
        self.adapter = adapter
        self.itg = itg
        self.adxl = adxl


def _i2c(*, simulated: bool, port: str | None, bus: int | None, rate: float, seed: int,
         clock: Clock, options: dict, which: str) -> Acquisition:
    """Acquisition of ``itg3200``, ``adxl345`` or ``razor`` on bus ``bus`` or a simulator."""
    from imunoise.daq.drivers.adxl345 import Adxl345, odr_hz, rate_code
    from imunoise.daq.drivers.itg3200 import Itg3200, rate_settings
    from imunoise.daq.drivers.razor import Razor
    from imunoise.daq.transports.i2c import I2CBus

    itg_addr = int(options.pop("itg_address", 0x68))
    adxl_addr = int(options.pop("adxl_address", 0x53))
    range_g = int(options.pop("range_g", 16))
    accel_rate = float(options.pop("accel_rate_hz", rate))
    retries = int(options.pop("retries", 3))
    opener: Callable | None = None
    rig = None
    if simulated:
        from imunoise.daq.sim.adxl345 import Adxl345Sim
        from imunoise.daq.sim.fake_i2c import SimulatedI2CAdapter
        from imunoise.daq.sim.itg3200 import Itg3200Sim
        from imunoise.daq.sim.signals import default_sources

        chips: dict = {}
        itg_sim = adxl_sim = None
        noise = options.pop("noise", None)
        bench = options.pop("bench", None)
        if which in ("itg3200", "razor"):
            fs = rate_settings(rate)[2]
            gyro = options.pop("gyro", None) or default_sources("itg3200", fs, seed, noise)[0]
            itg_sim = Itg3200Sim(clock, gyro, options.pop("temperature", None),
                                 address=itg_addr)
            if bench is not None:
                itg_sim.environment = bench.view()
            chips[itg_addr] = itg_sim
        if which in ("adxl345", "razor"):
            fs = odr_hz(rate_code(accel_rate))
            accel = options.pop("accel", None) or default_sources("adxl345", fs, seed, noise)[1]
            adxl_sim = Adxl345Sim(clock, accel)
            if bench is not None:
                adxl_sim.environment = bench.view()
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


_BUILDERS: dict[str, Callable[..., Acquisition]] = {
    "adis16350": _adis,
    "itg3200": lambda **kw: _i2c(which="itg3200", **kw),
    "adxl345": lambda **kw: _i2c(which="adxl345", **kw),
    "razor": lambda **kw: _i2c(which="razor", **kw),
}


def open_devices(specs: list[str], *, ports: list[str] | tuple = (), buses: list[int] | tuple = (),
                 rate_hz: float | None = None, seed: int | None = None,
                 bench: object | None = None, realtime: bool = True,
                 port_option: str = "--port", **options: object):
    """A :class:`imunoise.daq.device_group.DeviceGroup` of ``specs`` on one clock, not yet
    opened: ports and buses paired, topics named and seeds drawn as
    :mod:`imunoise.daq.device_group` says; ``bench`` (a :class:`imunoise.daq.sim.bench.Bench`)
    is shared by the simulated ones, each at its place in the group.

    Raises:
        ValueError: an unknown spec, or ports and buses that do not pair.
    """
    from imunoise.daq.device_group import DeviceGroup, member_seed, pair_devices
    from imunoise.daq.sim.bench import BenchPlacement

    for spec in specs:
        if spec not in DEVICES:
            raise ValueError(f"unknown device {spec!r}: choose one of {valid_devices()}")
    members = pair_devices(specs, ports, buses, port_option)
    clock = RealClock() if realtime else VirtualClock()
    epoch = clock.now()
    opened: list[tuple[str, Acquisition]] = []
    try:
        for m in members:
            kw = dict(options)
            if bench is not None and m.simulated:
                kw["bench"] = BenchPlacement(bench, m.position, seed=0 if seed is None
                                             else int(seed), epoch=epoch)
            opened.append((m.name, open_device(m.spec, port=m.port, bus=m.bus, rate_hz=rate_hz,
                                               seed=member_seed(seed, m.position), clock=clock,
                                               **kw)))
    except Exception:
        for _, acq in opened:
            acq.close()
        raise
    return DeviceGroup(opened, specs)
