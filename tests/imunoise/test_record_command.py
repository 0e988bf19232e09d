"""``imunoise record`` end to end on the simulated ADIS16350 (real pty, real pyserial)."""

import re

import numpy as np

from imunoise.cli import main
from imunoise.daq.readers import open_record
from imunoise.daq.readers.mcap import raw_counts


def test_record_simulated_adis16350(tmp_path, capsys):
    assert main(["record", "--device", "sim:adis16350", "--duration", "1.5s",
                 "--out", str(tmp_path), "--seed", "3"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    m = re.match(r"record: done: (\d+) samples in (\S+\.mcap)$", err[-1])
    assert m, err
    n, path = int(m.group(1)), m.group(2)
    assert n > 0
    r = open_record(path)
    assert r.channels["gyro_x"].n_samples == n
    assert sorted(r.channels) == sorted(["gyro_x", "gyro_y", "gyro_z",
                                         "accel_x", "accel_y", "accel_z"])
    md = r.metadata
    assert md["device"] == "sim:adis16350" and md["config.model"] == "ADIS16350"
    assert float(md["scale.gyro_x"]) == float(md["config.scale_gyro_rad_s_per_lsb"])
    counts = raw_counts(r.channels["gyro_x"].values, md, "gyro_x")
    back = counts * float(md["scale.gyro_x"])
    assert np.allclose(back, r.channels["gyro_x"].values, rtol=0, atol=1e-9)
    assert not list(tmp_path.glob(".imunoise-reserve"))


def test_record_unknown_device_is_usage_error(tmp_path, capsys):
    assert main(["record", "--device", "adis9999", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "adis9999" in err[0] and "sim:adis16350" in err[0]
