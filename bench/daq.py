"""Benchmark: sustained simulated throughput and CPU cost of each acquisition stack.

Each stack runs at its chip's top rate on a virtual clock (faster than real time), through the
real driver, transport library (pyserial on a pty, smbus2 over the simulated ioctl layer) and
register-level simulator. Printed per stack: samples delivered per wall-clock second, CPU
seconds per second of data (what real-time recording at that rate would cost this host), and
the samples the bus or bridge really allows. The reference measured in the same run is the
bare library doing the same transfers without driver, simulator logic or acquisition loop.

Usage: python bench/daq.py [--seconds S]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))

import serial

from imunoise.daq.devices import open_device
from imunoise.daq.sim.buspirate_pty import BusPirateEmulator
from imunoise.daq.sim.fake_i2c import BITS_PER_BYTE, BITS_START_STOP
from imunoise.daq.transports.buspirate import encode_frames

BAUD = 115200
I2C_HZ = 400e3


def run_stack(spec: str, rate: float, seconds: float, **kw) -> dict[str, float]:
    acq = open_device(spec, rate_hz=rate, realtime=False, seed=1, **kw)
    with acq:
        acq.open()
        wall0, cpu0 = time.perf_counter(), time.process_time()
        n = 0
        for b in acq.blocks(seconds):
            if b.stream.endswith("/imu"):
                n += len(b)
        wall = time.perf_counter() - wall0
        cpu = time.process_time() - cpu0
        stats = acq.stats
    return {"samples": n, "wall": wall, "cpu": cpu, "dropped": stats.dropped,
            "rate": float(acq.config.get("rate_hz", rate)), "seconds": seconds}


def bare_serial_round_trips(n: int) -> float:
    """Seconds per ADIS sample for pyserial alone: same 7 frames on the same emulated pty."""
    emu = BusPirateEmulator(None).start()
    try:
        ser = serial.Serial(emu.port, BAUD, timeout=1)
        ser.write(bytes(20))
        time.sleep(0.05)
        ser.reset_input_buffer()
        ser.write(b"\x01")
        ser.read(4)
        frames = encode_frames([0x0400, 0x0600, 0x0800, 0x0A00, 0x0C00, 0x0E00, 0x0000])
        t0 = time.perf_counter()
        for _ in range(n):
            ser.write(frames)
            ser.read(len(frames))
        dt = (time.perf_counter() - t0) / n
        ser.close()
        return dt
    finally:
        emu.close()


def bare_smbus2_reads(n: int) -> float:
    """Seconds per ADXL FIFO entry for smbus2 alone: one 6-byte block read each."""
    acq = open_device("sim:adxl345", rate_hz=3200, realtime=False)
    rig = acq.simulator
    bus = rig.adapter.open_bus()
    bus.write_byte_data(0x53, 0x2D, 0x08)
    t0 = time.perf_counter()
    for _ in range(n):
        bus.read_i2c_block_data(0x53, 0x32, 6)
    dt = (time.perf_counter() - t0) / n
    bus.close()
    acq.close()
    return dt


def i2c_bits(n_data: int, read: bool = True) -> int:
    """Bits on the wire of a register read of ``n_data`` bytes (address, register, repeated
    start, address, data)."""
    return BITS_START_STOP + BITS_PER_BYTE * (n_data + (3 if read else 2))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=20.0, help="simulated seconds per stack")
    args = ap.parse_args()
    s = args.seconds
    print(f"imunoise DAQ benchmark: {s:g} simulated seconds per stack, virtual clock\n")
    print(f"{'stack':34s} {'rate Hz':>8s} {'samples/s':>11s} {'x realtime':>10s} "
          f"{'CPU s per s':>11s} {'dropped':>8s}")
    rows = [
        ("sim:adis16350 (Bus Pirate, pty)", "sim:adis16350", 819.2, {}),
        ("sim:adxl345 (smbus2, FIFO)", "sim:adxl345", 3200.0, {}),
        ("sim:itg3200 (smbus2, polled)", "sim:itg3200", 8000.0, {}),
        ("sim:itg3200 at 2 kHz", "sim:itg3200", 2000.0, {}),
        ("sim:razor (ITG + ADXL, 100 Hz)", "sim:razor", 100.0, {}),
    ]
    results = {}
    for label, spec, rate, kw in rows:
        r = run_stack(spec, rate, s, **kw)
        results[label] = r
        sps = r["samples"] / r["wall"]
        per_s = r["cpu"] / s
        print(f"{label:34s} {r['rate']:8.1f} {sps:11.0f} {s / r['wall']:10.1f} "
              f"{per_s:11.3f} {r['dropped']:8d}")

    print("\nReference, same run: the bare libraries doing the same transfers")
    t_ser = bare_serial_round_trips(2000)
    t_adis = results["sim:adis16350 (Bus Pirate, pty)"]["wall"] / \
        max(1, results["sim:adis16350 (Bus Pirate, pty)"]["samples"])
    print(f"  pyserial round trip of one ADIS sample's 7 frames on the pty: "
          f"{t_ser * 1e6:7.1f} us; full stack per sample {t_adis * 1e6:7.1f} us "
          f"({t_adis / t_ser:.2f}x)")
    t_i2c = bare_smbus2_reads(20000)
    adxl = results["sim:adxl345 (smbus2, FIFO)"]
    t_adxl = adxl["wall"] / max(1, adxl["samples"])
    print(f"  smbus2 6-byte block read through the simulated ioctl: {t_i2c * 1e6:7.1f} us; "
          f"full ADXL345 stack per sample {t_adxl * 1e6:7.1f} us ({t_adxl / t_i2c:.2f}x)")

    print("\nWhat the links allow (wire time only)")
    frame_bytes = 7 * 5
    print(f"  Bus Pirate at {BAUD} baud, 8N1: one ADIS sample = {frame_bytes} bytes each way "
          f"-> at most {BAUD / 10 / frame_bytes:.0f} samples/s (plus USB latency per round "
          f"trip: about {1 / (1e-3 + frame_bytes * 10 / BAUD):.0f} samples/s with a 1 ms "
          "latency timer); the ADIS's 819.2 Hz needs a faster bridge.")
    itg_poll = i2c_bits(1) + i2c_bits(8)
    print(f"  I2C at {I2C_HZ / 1e3:.0f} kHz: ITG-3200 poll (INT_STATUS + 8 data bytes) = "
          f"{itg_poll} bits -> at most {I2C_HZ / itg_poll:.0f} samples/s; blind 8-byte reads "
          f"{I2C_HZ / i2c_bits(8):.0f}/s. Its 8 kHz is out of reach; measured above: "
          f"{results['sim:itg3200 (smbus2, polled)']['samples'] / s:.0f} delivered/s with "
          f"{results['sim:itg3200 (smbus2, polled)']['dropped'] / s:.0f}/s flagged as lost.")
    adxl_bits = i2c_bits(6) + (i2c_bits(1) * 2) / 16
    print(f"  I2C at {I2C_HZ / 1e3:.0f} kHz: ADXL345 FIFO entry = {i2c_bits(6)} bits (+ status "
          f"reads per drain) -> at most {I2C_HZ / adxl_bits:.0f} samples/s; 3200 Hz uses "
          f"{3200 * adxl_bits / I2C_HZ * 100:.0f} % of the bus (the data sheet recommends "
          "<= 800 Hz at 400 kHz).")


if __name__ == "__main__":
    main()
