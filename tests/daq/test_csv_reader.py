"""CSV reader and channel selection: clean files, repaired files and one-line errors."""

import numpy as np
import pytest

from imunoise.core.record import ChannelSelectionError, Record, select_channels
from imunoise.daq.readers import ReadError, open_record
from imunoise.daq.readers.csv_file import read_csv


def _write(tmp_path, text, name="rec.csv"):
    p = tmp_path / name
    p.write_bytes(text.encode() if isinstance(text, str) else text)
    return p


def _csv(header, rows):
    body = "\n".join(",".join(f"{v:.12g}" for v in r) for r in rows)
    return ",".join(header) + "\n" + body + "\n"


def test_reads_channels_time_temperature_and_ignores_other_columns(tmp_path):
    rng = np.random.default_rng(0)
    n = 500
    t = 1000.0 + np.arange(n) / 200.0
    g = rng.normal(0, 0.01, (n, 3))
    a = rng.normal(0, 0.1, (n, 3)) + [0, 0, 9.81]
    temp = 25 + 0.001 * np.arange(n)
    rows = np.column_stack([t, g, a, temp, np.ones(n)])
    p = _write(tmp_path, _csv(["t", "gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y",
                                "accel_z", "temp", "status"], rows))
    rec = open_record(p)
    assert isinstance(rec, Record) and rec.source == str(p)
    assert list(rec.channels) == ["gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z"]
    gx = rec.channels["gyro_x"]
    assert gx.units == "rad/s" and rec.channels["accel_z"].units == "m/s^2"
    assert gx.fs_hz == 200.0 and gx.t0_s == 1000.0 and gx.n_samples == n
    np.testing.assert_allclose(gx.values, g[:, 0], rtol=1e-11)
    np.testing.assert_allclose(rec.channels["accel_z"].values, a[:, 2], rtol=1e-11)
    assert list(gx.segment_starts) == [0]
    assert rec.temperature is not None and rec.temperature.units == "degC"
    np.testing.assert_allclose(rec.temperature.values, temp, rtol=1e-11)
    assert rec.warnings == []
    assert rec.metadata["ignored_columns"] == "status" and rec.metadata["format"] == "csv"


def test_subset_without_time_column_uses_rate(tmp_path):
    p = _write(tmp_path, "accel_z,gyro_y\n9.8,0.1\n9.81,0.2\n9.79,0.3\n")
    rec = read_csv(p, rate_hz=50.0)
    assert list(rec.channels) == ["gyro_y", "accel_z"]
    assert rec.channels["gyro_y"].fs_hz == 50.0
    np.testing.assert_allclose(rec.channels["accel_z"].values, [9.8, 9.81, 9.79])
    with pytest.raises(ReadError, match="no time column 't'.*--rate"):
        read_csv(p)


def test_rate_overrides_inferred_rate_and_jittered_times(tmp_path):
    rng = np.random.default_rng(1)
    t = np.round(np.arange(3000) / 300.0 + rng.uniform(0, 1e-4, 3000), 3)  # 1 ms stamps
    p = _write(tmp_path, _csv(["t", "gyro_x"], np.column_stack([t, np.zeros(3000)])))
    assert read_csv(p).channels["gyro_x"].fs_hz == pytest.approx(300.0, rel=1e-3)
    assert read_csv(p, rate_hz=301.0).channels["gyro_x"].fs_hz == 301.0


def test_time_in_milliseconds_is_flagged(tmp_path):
    p = _write(tmp_path, "t,gyro_x\n0,1\n10,2\n20,3\n30,4\n")
    rec = read_csv(p)
    assert rec.channels["gyro_x"].fs_hz == 0.1
    assert any("0.1 Hz: is 't' in seconds?" in w for w in rec.warnings)


def test_gaps_and_backwards_time_become_segments(tmp_path):
    t = np.arange(100) / 10.0
    t[40:] += 5.0  # a 5 s gap before row 40
    t[70:] -= 3.0  # time jumps back before row 70
    x = np.arange(100.0)
    p = _write(tmp_path, _csv(["t", "gyro_z"], np.column_stack([t, x])))
    rec = read_csv(p)
    s = rec.channels["gyro_z"]
    assert list(s.segment_starts) == [0, 40, 70]
    np.testing.assert_array_equal(s.values, x)  # nothing lost
    text = " | ".join(rec.warnings)
    assert "backwards or repeats at 1 place(s) (first before sample 71)" in text
    assert "50 sample(s) missing in 1 gap(s) (largest 5.1 s, before sample 41)" in text


def test_nan_and_empty_values_split_only_their_channel(tmp_path):
    lines = ["t,gyro_x,gyro_y"]
    for i in range(20):
        gx = "nan" if i == 5 else ("" if i == 12 else f"{i}")
        lines.append(f"{i * 0.1:.1f},{gx},{-i}")
    p = _write(tmp_path, "\n".join(lines) + "\n")
    rec = read_csv(p)
    gx, gy = rec.channels["gyro_x"], rec.channels["gyro_y"]
    assert gx.n_samples == 18 and not np.isnan(gx.values).any()
    assert list(gx.segment_starts) == [0, 5, 11]
    np.testing.assert_array_equal(gx.values[:6], [0, 1, 2, 3, 4, 6])
    assert gy.n_samples == 20 and list(gy.segment_starts) == [0]
    assert any("gyro_x: 2 missing or non-finite" in w for w in rec.warnings)


def test_rows_without_time_are_dropped(tmp_path):
    p = _write(tmp_path, "t,gyro_x\n0,1\n0.1,2\nnan,3\n0.3,4\n0.4,5\n")
    rec = read_csv(p)
    np.testing.assert_array_equal(rec.channels["gyro_x"].values, [1, 2, 4, 5])
    assert list(rec.channels["gyro_x"].segment_starts) == [0, 2]
    assert any("1 row(s) without a valid time" in w for w in rec.warnings)


def test_incomplete_last_line_is_dropped(tmp_path):
    p = _write(tmp_path, "t,gyro_x,gyro_y\n0,1,2\n0.1,3,4\n0.2,5")
    rec = read_csv(p)
    np.testing.assert_array_equal(rec.channels["gyro_x"].values, [1, 3])
    assert any("incomplete" in w for w in rec.warnings)


def test_semicolon_bom_crlf_and_quoted_header(tmp_path):
    p = _write(tmp_path, b'\xef\xbb\xbf"t";"Gyro_X"\r\n0;1.5\r\n0.5;2.5\r\n1.0;3.5\r\n')
    rec = read_csv(p)
    np.testing.assert_array_equal(rec.channels["gyro_x"].values, [1.5, 2.5, 3.5])
    assert rec.channels["gyro_x"].fs_hz == 2.0


@pytest.mark.parametrize("content, message", [
    ("", "empty file"),
    ("   \n\n", "empty file"),
    ("t,gyro_x\n", "no data rows"),
    ("t,speed,x\n0,1,2\n",
     r"no IMU channel columns \(expected some of gyro_x.*found t, speed, x\)"),
    ("t,gyro_x\n0,1\n0.1,abc\n0.2,3\n",
     "bad CSV data: line 3, column 2: 'abc' is not a number"),
    ("t,gyro_x,gyro_y\n0,1,2\n0.1,2\n0.2,3,4\n",
     "bad CSV data: line 3 has 2 field.s., expected at least 3"),
    ("t,gyro_x,gyro_x\n0,1,2\n", "duplicate column"),
    ("t,gyro_x\n0,1\n", "need at least two rows"),
    ("gyro_x,t\nnan,0\nnan,1\n", "no valid values in any IMU channel"),
])
def test_bad_files_are_one_line_errors(tmp_path, content, message):
    p = _write(tmp_path, content)
    with pytest.raises(ReadError, match=message) as info:
        open_record(p)
    assert "\n" not in str(info.value) and str(p) in str(info.value)


def test_random_bytes_and_binary(tmp_path):
    rng = np.random.default_rng(3)
    for i in range(5):
        p = _write(tmp_path, rng.integers(0, 256, 2000, dtype=np.uint8).tobytes(), f"r{i}.csv")
        with pytest.raises(ReadError) as info:
            open_record(p)
        assert "\n" not in str(info.value)
    p = _write(tmp_path, b"t,gyro_x\n0,1\n\x00\x01\x02", "nul.csv")
    with pytest.raises(ReadError, match="binary"):
        open_record(p)


def test_dispatch_errors(tmp_path):
    with pytest.raises(ReadError, match="no such file"):
        open_record(tmp_path / "missing.csv")
    with pytest.raises(ReadError, match=r"unsupported file type '.txt': expected .csv, .mcap"):
        open_record(_write(tmp_path, "t,gyro_x\n0,1\n", "a.txt"))
    with pytest.raises(ReadError, match="not a rosbag2"):
        open_record(tmp_path)
    with pytest.raises(ReadError, match="bad rate"):
        open_record(_write(tmp_path, "gyro_x\n1\n2\n"), rate_hz=-1.0)


def _record(keys, temp=False):
    from imunoise.core.series import ChannelSeries

    def s(k):
        return ChannelSeries(name=k, units="rad/s", fs_hz=1.0, values=np.zeros(4))
    return Record(source="x", channels={k: s(k) for k in keys},
                  temperature=s("temp") if temp else None)


def test_select_channels():
    rec = _record(["gyro_x", "gyro_y", "accel_z"], temp=True)
    assert select_channels(rec, []) == ["gyro_x", "gyro_y", "accel_z"]
    assert select_channels(rec, ["accel_z", "gyro_x", "accel_z"]) == ["accel_z", "gyro_x"]
    assert select_channels(rec, ["temp"]) == ["temp"]
    assert rec.series("temp") is rec.temperature
    with pytest.raises(ChannelSelectionError,
                       match="unknown channel 'gyro_q'; valid channels: gyro_x, gyro_y, "
                             "accel_z, temp"):
        select_channels(rec, ["gyro_q"])
    multi = _record(["/a/imu:gyro_x", "/b/imu:gyro_x", "/a/imu:accel_x"])
    assert select_channels(multi, ["accel_x"]) == ["/a/imu:accel_x"]
    assert select_channels(multi, ["/b/imu:gyro_x"]) == ["/b/imu:gyro_x"]
    with pytest.raises(ChannelSelectionError, match="ambiguous: use one of /a/imu:gyro_x, "
                                                    "/b/imu:gyro_x"):
        select_channels(multi, ["gyro_x"])
