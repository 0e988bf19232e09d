"""CSV reading speed: 10^6 rows x 8 columns (t, 6 IMU channels, temp) through
imunoise.daq.readers.csv_file.read_csv, with its fast parser (imunoise.daq.readers.csv_numbers,
Apache Arrow's CSV reader) and with np.loadtxt alone, against the standard-library csv module
with float() per field (the usual hand-written reader), all measured in the same run.
Run: python bench/bench_csv.py
"""

from __future__ import annotations

import csv
import tempfile
import time
from pathlib import Path

import numpy as np

from imunoise.daq.readers import csv_file
from imunoise.daq.readers.csv_file import read_csv

ROWS = 1_000_000
HEADER = "t,gyro_x,gyro_y,gyro_z,accel_x,accel_y,accel_z,temp"


def _stdlib(path: Path) -> np.ndarray:
    with path.open(newline="") as f:
        reader = csv.reader(f)
        next(reader)
        return np.array([[float(v) for v in row] for row in reader])


def main() -> None:
    rng = np.random.default_rng(0)
    data = np.column_stack([np.arange(ROWS) / 100.0, rng.normal(0, 0.01, (ROWS, 6)),
                            25 + rng.normal(0, 0.01, ROWS)])
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "imu.csv"
        np.savetxt(path, data, delimiter=",", fmt="%.9g", header=HEADER, comments="")
        size_mb = path.stat().st_size / 1e6
        read_csv(path)  # pyarrow imported before timing
        t0 = time.perf_counter()
        rec = read_csv(path)
        t_ours = time.perf_counter() - t0
        fast_limit = csv_file.FAST_PARSE_MIN_BYTES
        csv_file.FAST_PARSE_MIN_BYTES = 1 << 62  # every body to np.loadtxt
        try:
            t0 = time.perf_counter()
            slow = read_csv(path)
            t_loadtxt = time.perf_counter() - t0
        finally:
            csv_file.FAST_PARSE_MIN_BYTES = fast_limit
        t0 = time.perf_counter()
        ref = _stdlib(path)
        t_ref = time.perf_counter() - t0
    np.testing.assert_allclose(rec.channels["gyro_x"].values, ref[:, 1])
    assert np.array_equal(rec.channels["gyro_x"].values, slow.channels["gyro_x"].values)
    print(f"{ROWS:,} rows, {size_mb:.0f} MB")
    print(f"read_csv:                   {t_ours:.2f} s ({ROWS / t_ours / 1e6:.2f} M rows/s)")
    print(f"read_csv, np.loadtxt alone: {t_loadtxt:.2f} s ({t_loadtxt / t_ours:.1f}x slower)")
    print(f"stdlib csv + float (ref):   {t_ref:.2f} s ({t_ref / t_ours:.1f}x slower)")


if __name__ == "__main__":
    main()
