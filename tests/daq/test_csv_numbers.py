"""The CSV reader's fast number parser: the same doubles as np.loadtxt, or it gives up."""

import io
import subprocess
import sys

import numpy as np
import pytest

from imunoise.daq.readers import ReadError, csv_numbers
from imunoise.daq.readers.csv_file import FAST_PARSE_MIN_BYTES, read_csv
from imunoise.daq.readers.csv_numbers import parse_numbers

pytestmark = pytest.mark.skipif(csv_numbers._arrow() is None, reason="pyarrow is not importable")

FORMATS = ["{:.10g}", "{:.15g}", "{:.6e}", "{:+.8f}", " {:.3f} ", "{:.4E}", "{:.0f}"]


def _body(rows: int, seed: int = 0) -> tuple[bytes, np.ndarray]:
    """Rows of five fields in assorted notations (one empty field in each 97th row) and what
    np.loadtxt reads from them, empty fields as NaN."""
    rng = np.random.default_rng(seed)
    values = rng.choice([-1.0, 1.0], (rows, 5)) * rng.uniform(1.0, 10.0, (rows, 5)) \
        * 10.0 ** rng.integers(-6, 7, (rows, 5))
    lines = []
    for i, row in enumerate(values):
        fields = [FORMATS[(i + k) % len(FORMATS)].format(v) for k, v in enumerate(row)]
        if i % 97 == 3:
            fields[2] = ""
        lines.append(",".join(fields))
    body = ("\n".join(lines) + "\n").encode()
    ref = np.loadtxt(io.BytesIO(body.replace(b",,", b",nan,")), delimiter=",",
                     dtype=np.float64, ndmin=2, comments=None)
    return body, ref


def test_same_doubles_as_loadtxt_bit_for_bit():
    body, ref = _body(30_000)
    out = parse_numbers(body, 5, [0, 1, 2, 3, 4], ",")
    assert out is not None, "the fast path gave up on plain numbers"
    assert out.shape == ref.shape
    assert np.array_equal(out.view(np.int64), ref.view(np.int64))  # -0.0 and NaN included
    assert np.isnan(out[3, 2]) and np.isnan(ref[3, 2])


def test_columns_asked_for_in_their_order_and_text_elsewhere_skipped():
    body, ref = _body(30_000, seed=1)
    lines = body.decode().splitlines()
    tagged = ("\n".join(f"{line},ok\r" for line in lines) + "\n").encode()  # CRLF too
    out = parse_numbers(tagged, 6, [4, 0], ",")
    assert out is not None
    assert np.array_equal(out, ref[:, [4, 0]], equal_nan=True)


def _with_field(body: bytes, field: str) -> bytes:
    """``body`` with the second field of its row 1234 replaced by ``field``."""
    lines = body.decode().splitlines()
    parts = lines[1234].split(",")
    parts[1] = field
    lines[1234] = ",".join(parts)
    return ("\n".join(lines) + "\n").encode()


@pytest.mark.parametrize("field", ["nan", "-inf", " NaN ", "0.12345678901234567", "1e23",
                                   "3e-30", "4.9e-324", "1e400", "+.5", "5."])
def test_words_and_long_numbers_read_as_loadtxt_reads_them(field):
    text = _with_field(_body(3_000, seed=5)[0], field)
    out = parse_numbers(text, 5, [0, 1, 2, 3, 4], ",")
    ref = np.loadtxt(io.BytesIO(text.replace(b",,", b",nan,")), delimiter=",",
                     dtype=np.float64, ndmin=2, comments=None)
    assert out is not None
    assert np.array_equal(out.view(np.int64), ref.view(np.int64))


@pytest.mark.parametrize("field", ["1.5x", ".", "-", "  ", "1e", "1e+", "--1", "1,2", "NA",
                                   "null", '"2.5"', "0x10", "1_0"])
def test_gives_up_where_loadtxt_would_not_read_the_same(field):
    text = _with_field(_body(30_000, seed=2)[0], field)
    assert parse_numbers(text, 5, [0, 1, 2, 3, 4], ",") is None


def test_each_column_comes_contiguous_and_a_last_row_without_newline_counts():
    body, ref = _body(30_000, seed=4)
    out = parse_numbers(body, 5, [3, 1], ",")
    assert out is not None
    # the reader takes the columns apart without copying them
    assert all(out[:, j].flags.c_contiguous for j in range(2))
    assert np.shares_memory(np.ascontiguousarray(out.T), out)
    cut = parse_numbers(body.rstrip(b"\n"), 5, [3, 1], ",")
    assert cut is not None and cut.shape == (30_000, 2)
    assert np.array_equal(cut, ref[:, [3, 1]], equal_nan=True)


def test_skips_blank_lines_and_gives_up_on_short_rows_and_other_delimiters():
    body, ref = _body(30_000, seed=3)
    blank = parse_numbers(body.replace(b"\n", b"\n\n", 1), 5, [0, 1], ",")
    assert blank is not None  # np.loadtxt skips blank lines too
    assert np.array_equal(blank, ref[:, [0, 1]], equal_nan=True)
    assert parse_numbers(body + b"1,2,3\n", 5, [0, 1], ",") is None
    assert parse_numbers(body + b"1,2,3,4,5,6\n", 5, [0, 1], ",") is None
    assert parse_numbers(body, 5, [0, 1], " ") is None


def _record_file(tmp_path, rows: int, bad_line: int | None = None):
    rng = np.random.default_rng(7)
    t = np.arange(rows) / 100.0
    g = rng.normal(0.0, 0.01, (rows, 3))
    text = ["t,gyro_x,gyro_y,gyro_z,note"]
    for i in range(rows):
        x = "oops" if i == bad_line else f"{g[i, 0]:.10g}"
        text.append(f"{t[i]:.10g},{x},{g[i, 1]:.10g},{g[i, 2]:.10g},still")
    p = tmp_path / "big.csv"
    p.write_text("\n".join(text) + "\n")
    return p


def test_reader_gives_the_same_record_with_and_without_the_fast_path(tmp_path, monkeypatch):
    p = _record_file(tmp_path, 40_000)
    assert p.stat().st_size > FAST_PARSE_MIN_BYTES
    body = p.read_bytes().split(b"\n", 1)[1]
    assert csv_numbers.parse_numbers(body, 5, [0, 1, 2, 3], ",") is not None  # the fast path
    fast = read_csv(p)
    monkeypatch.setattr(csv_numbers, "_arrow", lambda: None)
    slow = read_csv(p)
    for name in ("gyro_x", "gyro_y", "gyro_z"):
        assert np.array_equal(fast.channels[name].values, slow.channels[name].values)
        assert fast.channels[name].fs_hz == slow.channels[name].fs_hz == 100.0
    assert fast.metadata == slow.metadata and fast.warnings == slow.warnings


def test_small_files_do_not_load_the_fast_parser(tmp_path):
    code = ("import sys; from imunoise.daq.readers.csv_file import read_csv; "
            f"read_csv({str(_record_file(tmp_path, 200))!r}); "
            "print('imunoise.daq.readers.csv_numbers' in sys.modules, 'pyarrow' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["False", "False"]


def test_reader_still_names_the_bad_line_of_a_big_file(tmp_path):
    p = _record_file(tmp_path, 40_000, bad_line=30_000)
    with pytest.raises(ReadError, match=r"line 30002, column 2: 'oops' is not a number"):
        read_csv(p)


def test_big_files_are_read_without_loading_numba_or_pandas(tmp_path):
    # numba's import and cached machine code cost a process about 0.8 s, pandas's (which
    # pyarrow's own array conversion imports) about 0.25 s; a CSV is read without them (the
    # Allan kernels load numba for records of 2.1e6 points and more)
    p = _record_file(tmp_path, 40_000)
    text = p.read_text().splitlines()
    fields = text[5].split(",")
    text[5] = ",".join(fields[:2] + [""] + fields[3:])  # gyro_y of row 4 missing: removed
    p.write_text("\n".join(text) + "\n")
    code = ("import sys; from imunoise.daq.readers.csv_file import read_csv; "
            f"r = read_csv({str(p)!r}); "
            "print(r.channels['gyro_x'].n_samples, r.channels['gyro_y'].n_samples, "
            "'pyarrow' in sys.modules, 'numba' in sys.modules, 'pandas' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.split() == ["40000", "39999", "True", "False", "False"]


def test_columns_are_copied_from_every_chunk_and_offset_with_nulls_as_nan():
    pa = csv_numbers._arrow()[0]
    values = np.arange(40.0)
    valid = np.ones(40, dtype=bool)
    valid[[3, 17, 18, 39]] = False
    whole = pa.array(values, mask=~valid)
    # chunks that start inside a byte of the validity bitmap, and one without nulls
    chunks = [whole.slice(0, 5), whole.slice(5, 14), whole.slice(19, 20),
              pa.array(np.array([7.5, -1.0]))]
    out = np.empty(41)
    csv_numbers._copy_chunks(chunks, out)
    expected = np.concatenate([np.where(valid, values, np.nan)[:39], [7.5, -1.0]])
    assert np.array_equal(out, expected, equal_nan=True)
    with pytest.raises(ValueError, match="39 values for 41 rows"):
        csv_numbers._copy_chunks(chunks[:3], np.empty(41))
