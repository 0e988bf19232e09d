"""Fast parse of a CSV body of plain numbers: the CSV reader's fast path (Apache Arrow).

``np.loadtxt`` takes about 1.3 s for 1e6 rows of seven columns, a quarter of a first
``imunoise diagnose`` of such a file. Arrow's CSV reader (``pyarrow.csv``) splits the body
into blocks and converts them on every core, with a correctly rounded decimal conversion
(the same double as ``strtod`` and ``np.loadtxt``); with its import it reads that file in
about a quarter of a second. It is asked to read exactly what ``np.loadtxt`` reads, and gives
up (None) on anything else, leaving the file to ``np.loadtxt`` and its error messages:

- fields are split at the delimiter alone (no quoting, no escapes): a quote is part of its
  field and makes the conversion fail;
- every row has as many fields as the header (blank lines are skipped, as ``np.loadtxt``
  skips them);
- a field asked for is a decimal number, ``nan`` or ``inf`` with spaces or tabs around it,
  or empty (a missing value, NaN as the reader's slower path reads it); a word such as
  ``NA`` or ``null`` is not a missing value here.

Columns not asked for are split but not converted, as ``loadtxt(usecols=...)`` skips them.

The reader uses it for bodies of at least
:data:`imunoise.daq.readers.csv_file.FAST_PARSE_MIN_BYTES`; below that, importing pyarrow
costs more than it saves.
"""

from __future__ import annotations

from typing import Any

import numpy as np

_DELIMITERS = (",", ";", "\t")


def _arrow() -> tuple[Any, Any] | None:
    """``(pyarrow, pyarrow.csv)``, or None: pyarrow is a declared dependency, but a broken
    install must only cost the fast path."""
    try:
        import pyarrow
        import pyarrow.csv
    except Exception:  # noqa: BLE001 - any import failure leaves the file to np.loadtxt
        return None
    return pyarrow, pyarrow.csv


def parse_numbers(body: bytes | memoryview, n_fields: int, usecols: list[int], delim: str
                  ) -> np.ndarray | None:
    """The columns ``usecols`` of the CSV rows in ``body`` (no header; ``n_fields`` fields per
    row) as a float64 array of shape (rows, len(usecols)), or None when the fast path does not
    apply (no pyarrow, or a row or field ``np.loadtxt`` would read differently). The array is
    the transpose of a C-ordered one: each column is contiguous, so taking the columns apart
    copies nothing."""
    if delim not in _DELIMITERS or n_fields < 1:
        return None
    if not usecols or max(usecols) >= n_fields or len(set(usecols)) != len(usecols):
        return None
    arrow = _arrow()
    if arrow is None:
        return None
    pa, pcsv = arrow
    names = [f"c{i}" for i in range(n_fields)]
    wanted = [names[i] for i in usecols]
    try:
        table = pcsv.read_csv(
            pa.BufferReader(pa.py_buffer(body)),
            read_options=pcsv.ReadOptions(column_names=names),
            parse_options=pcsv.ParseOptions(delimiter=delim, quote_char=False,
                                            double_quote=False, escape_char=False,
                                            newlines_in_values=False,
                                            ignore_empty_lines=True),
            convert_options=pcsv.ConvertOptions(
                include_columns=wanted, column_types=dict.fromkeys(wanted, pa.float64()),
                null_values=[""], strings_can_be_null=False,
                quoted_strings_can_be_null=False))
    except (pa.ArrowException, ValueError, OSError):
        return None
    out = np.empty((len(usecols), table.num_rows))
    for j, name in enumerate(wanted):
        _copy_chunks(table.column(name).chunks, out[j])
    return out.T


def _copy_chunks(chunks: Any, out: np.ndarray) -> None:
    """Copy float64 Arrow arrays, one after another, into ``out``; a null (a missing value)
    becomes NaN, as the slower path reads an empty field.

    Read from each array's buffers: pyarrow's own ``to_numpy`` and ``fill_null`` import pandas
    (about 0.25 s, a twentieth of a first ``imunoise diagnose``) to convert a plain column."""
    pos = 0
    for chunk in chunks:
        n = len(chunk)
        validity, data = chunk.buffers()[:2]
        part = out[pos:pos + n]
        part[:] = np.frombuffer(data, dtype=np.float64, count=n, offset=chunk.offset * 8)
        if chunk.null_count:
            # the validity bitmap holds one bit per value, least significant bit first
            bits = np.unpackbits(np.frombuffer(validity, dtype=np.uint8), bitorder="little")
            part[bits[chunk.offset:chunk.offset + n] == 0] = np.nan
        pos += n
    if pos != out.size:
        raise ValueError(f"Arrow column of {pos} values for {out.size} rows")
