"""Register-level model of the ITG-3200 gyroscope as its I2C wire sees it.

Power-up values (FS_SEL = 0, internal oscillator), WHO_AM_I, the sample clock from DLPF_CFG and
SMPLRT_DIV (the internal oscillator runs a few percent off; the gyro PLLs are exact),
RAW_DATA_RDY and ITG_RDY in INT_STATUS only when enabled, cleared by reading INT_STATUS (or
any register with INT_ANYRD_2CLEAR), data registers latched per sample and read big-endian
with auto-increment, H_RESET and SLEEP. Faults: wrong WHO_AM_I, data-ready stuck low.
"""

from __future__ import annotations

import math

import numpy as np

from imunoise.daq.clock import Clock
from imunoise.daq.drivers import itg3200 as itg
from imunoise.daq.sim.bench import SensorOnBench
from imunoise.daq.sim.i2c_chip import RegisterChip, SourceBuffer
from imunoise.daq.sim.signals import SignalSource, TemperatureSource, drifting_temperature

INTERNAL_OSC_ERROR = -0.03  # the datasheet allows -15..+10 % over temperature
PLL_LOCK_S = 0.001
_REGS = itg.REGISTERS
REG_END = _REGS.addr("GYRO_ZOUT") + 1  # last data byte


class Itg3200Sim(RegisterChip):
    """An ITG-3200 at ``address`` driven by a gyro source in rad/s and a temperature source.

    Fault switches: ``who_am_i`` (the ID byte to answer), ``stuck_ready`` (data stops:
    RAW_DATA_RDY never sets again until H_RESET).
    """

    def __init__(self, clock: Clock, gyro: SignalSource,
                 temperature: TemperatureSource | None = None, *, address: int = 0x68) -> None:
        super().__init__(clock)
        self.gyro = SourceBuffer(gyro)
        self.temperature = temperature or drifting_temperature()
        self.who_am_i = address & 0x7E
        self.stuck_ready = False
        self.pll_error_ppm = 0.0  # frequency error of the gyro-referenced clock
        self.samples_made = 0
        self.environment: SensorOnBench | None = None  # the bench it sits on, if any
        self._rate: tuple[tuple, float] | None = None
        self._reset()

    def _reset(self) -> None:
        self.stuck_ready = False  # a hung conversion is cured by a reset
        self.regs[:] = bytes(len(self.regs))
        self._int_status = 0
        self._restart()

    def _restart(self) -> None:
        self._t0 = self.clock.now()
        self._index = -1
        self._pll_at = self.clock.now() + PLL_LOCK_S

    @property
    def rate_hz(self) -> float:
        # Asked at every bus access: recomputed only when a setting it depends on changed.
        key = (self.regs[itg.REG["DLPF_CFG"]], self.regs[itg.REG["CLK_SEL"]],
               self.regs[itg.REG["SMPLRT_DIV"]], self.pll_error_ppm)
        if self._rate is None or self._rate[0] != key:
            self._rate = (key, self._rate_of_registers())
        return self._rate[1]

    def _rate_of_registers(self) -> float:
        dlpf = int(_REGS["DLPF_CFG"].counts(self.regs[itg.REG["DLPF_CFG"]]))
        f_int = itg.DLPF_CFG.get(dlpf, (0.0, 1000.0))[1]
        clk = int(_REGS["CLK_SEL"].counts(self.regs[itg.REG["CLK_SEL"]]))
        if clk == itg.CLK_INTERNAL:
            f_int *= 1.0 + INTERNAL_OSC_ERROR
        else:
            f_int *= 1.0 + self.pll_error_ppm * 1e-6
        return f_int / (self.regs[itg.REG["SMPLRT_DIV"]] + 1)

    def _update(self) -> None:
        now = self.clock.now()
        pwr = self.regs[itg.REG["PWR_MGM"]]
        if pwr & itg.PWR_SLEEP or self.stuck_ready:
            return
        if now >= self._pll_at:
            self._int_status |= itg.INT_ITG_RDY
        index = int(math.floor((now - self._t0) * self.rate_hz))
        if index <= self._index:
            return
        x = self.gyro.skip_take_last(index - self._index)
        if self.environment is not None:  # the bench's rotation rate at this sample's time
            x = x + self.environment.at(self._t0 + index / self.rate_hz)[0, :3]
        self.samples_made += index - self._index
        self._index = index
        fs_sel = int(_REGS["FS_SEL"].counts(self.regs[itg.REG["FS_SEL"]]))
        # FS_SEL 0..2 are reserved; the part is only specified at 3.
        gain = 1.0 if fs_sel == itg.FS_SEL_2000DPS else 1.3
        counts = [int(_REGS[n].from_si(v * gain)) for n, v in zip(itg.GYRO_FIELDS, x,
                                                                       strict=True)]
        temp = float(self.temperature(np.array([now - self.power_on]))[0])
        t_counts = int(_REGS["TEMP_OUT"].from_si(temp))
        data = _REGS.block_bytes(itg.DATA_FIELDS, [t_counts, *counts])
        base = _REGS.addr("TEMP_OUT")
        self.regs[base:base + len(data)] = bytes(data)
        self._int_status |= itg.INT_RAW_DATA_RDY

    def _next(self, pointer: int) -> int:
        # Auto-increment stops in the reserved area after the data registers.
        if REG_END < pointer < itg.REG["PWR_MGM"]:
            return pointer
        return (pointer + 1) % self.n_registers

    def _on_write(self, reg: int, value: int) -> None:
        if reg == itg.REG["WHO_AM_I"]:
            self.who_am_i = value & 0x7E
        elif reg == itg.REG["PWR_MGM"]:
            if value & itg.PWR_H_RESET:
                self._reset()
                return
            old = self.regs[reg]
            self.regs[reg] = value
            if (old ^ value) & 0x07:
                self._int_status &= ~itg.INT_ITG_RDY
                self._pll_at = self.clock.now() + PLL_LOCK_S
        elif reg in (itg.REG["SMPLRT_DIV"], itg.REG["DLPF_FS"]):
            self.regs[reg] = value
            self._restart()
        elif reg in (itg.REG["INT_CFG"],):
            self.regs[reg] = value
        # other registers are read-only or reserved

    def _read_byte(self, reg: int) -> int:
        if reg == itg.REG["WHO_AM_I"]:
            return self.who_am_i
        if reg == itg.REG["INT_STATUS"]:
            cfg = self.regs[itg.REG["INT_CFG"]]
            enabled = (itg.INT_ITG_RDY if cfg & itg.INT_CFG_ITG_RDY_EN else 0) | \
                (itg.INT_RAW_DATA_RDY if cfg & itg.INT_CFG_RAW_RDY_EN else 0)
            return self._int_status & enabled
        return self.regs[reg]

    def _after_read(self, start: int, n: int) -> None:
        cfg = self.regs[itg.REG["INT_CFG"]]
        touched_status = start <= itg.REG["INT_STATUS"] < start + n
        if touched_status or cfg & itg.INT_CFG_ANYRD_2CLEAR:
            self._int_status &= ~itg.INT_RAW_DATA_RDY
        if start <= REG_END and start + n > _REGS.addr("GYRO_XOUT"):
            self.gyro.prefetch()  # the host has its sample: draw ahead now
