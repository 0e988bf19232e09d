"""Compiled parser of a CSV body of plain decimal numbers: the CSV reader's fast path.

``np.loadtxt`` takes about 1.3 s for 1e6 rows of seven columns, a quarter of a first
``imunoise diagnose`` of such a file; this parser (numba) reads them in about a tenth of that.
It converts only what it can convert exactly and gives up otherwise, leaving the file to
``np.loadtxt`` and its error messages:

- a field is ``[sign]digits[.digits][e[sign]digits]`` with spaces or tabs around it, or empty
  (a missing value, NaN as the reader's slower path reads it);
- its value is ``M * 10^e`` with the significand ``M`` of at most 2^53 and ``|e| <= 22``. Both
  are then exact doubles and one multiplication or division rounds once, so the result is the
  correctly rounded value (Clinger's fast path), the same double as ``strtod``. Numbers with
  more significant digits (17-digit ``repr`` output, nanosecond time stamps) or words
  (``nan``, ``inf``) make it give up;
- every row has as many fields as the header, a blank line makes it give up.

The reader uses it for bodies of at least
:data:`imunoise.daq.readers.csv_file.COMPILED_PARSE_MIN_BYTES`; below that, importing numba
and loading the machine code cost more than they save.

Columns not asked for are skipped unread, as ``loadtxt(usecols=...)`` skips them.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def _numba_jit() -> Any:
    """numba's ``njit``, or None: numba is a declared dependency, but it fails to import in
    many ways, and the reader then uses np.loadtxt alone."""
    try:
        from numba import njit
    except Exception:  # noqa: BLE001
        return None
    return njit


njit = _numba_jit()

_DELIMITERS = (",", ";", "\t")
_MAX_DIGITS = 17
_EXACT_SIGNIFICAND = 1 << 53
_EXACT_POWER = 22


def _jit(fn):
    return fn if njit is None else njit(cache=True, nogil=True)(fn)


def _inline(fn):
    # the helpers of one field are inlined into the row loop: called, they cost a third
    return fn if njit is None else njit(cache=True, nogil=True, inline="always")(fn)


@_inline
def _skip_blanks(buf: np.ndarray, i: int, delim: int) -> int:
    """The index of the first byte from ``i`` that is not a space (nor a tab, unless tabs
    delimit)."""
    n = buf.size
    while i < n and (buf[i] == 32 or (buf[i] == 9 and delim != 9)):
        i += 1
    return i


@_inline
def _digits(buf: np.ndarray, i: int, mant: int, count: int, fraction: bool
            ) -> tuple[int, int, int, int, bool]:
    """Digits from ``i`` appended to the significand ``mant`` of ``count`` significant digits:
    ``(next index, mant, count, places after the point, any digit)``; ``count`` past the
    limit means the significand is not exact."""
    n = buf.size
    places = 0
    seen = False
    while i < n and 48 <= buf[i] <= 57:
        seen = True
        d = buf[i] - 48
        if mant != 0 or d != 0:
            if count < _MAX_DIGITS:
                mant = mant * 10 + d
            count += 1
        if fraction:
            places += 1
        i += 1
    return i, mant, count, places, seen


@_inline
def _exponent(buf: np.ndarray, i: int) -> tuple[int, int, bool]:
    """The exponent after an ``e``: ``(next index, value, well formed)``."""
    n = buf.size
    neg = False
    if i < n and (buf[i] == 45 or buf[i] == 43):
        neg = buf[i] == 45
        i += 1
    e = 0
    start = i
    while i < n and 48 <= buf[i] <= 57:
        if e < 100000:
            e = e * 10 + (buf[i] - 48)
        i += 1
    return i, -e if neg else e, i > start


@_inline
def _value(mant: int, count: int, exp10: int, pow10: np.ndarray) -> tuple[float, bool]:
    """``mant * 10^exp10`` when it is correctly rounded by one operation."""
    if mant == 0:
        return 0.0, True
    if count > _MAX_DIGITS or mant > _EXACT_SIGNIFICAND:
        return 0.0, False
    if exp10 == 0:
        return float(mant), True
    if 0 < exp10 <= _EXACT_POWER:
        return float(mant) * pow10[exp10], True
    if -_EXACT_POWER <= exp10 < 0:
        return float(mant) / pow10[-exp10], True
    return 0.0, False


@_inline
def _field(buf: np.ndarray, i: int, delim: int, pow10: np.ndarray) -> tuple[float, int, bool]:
    """The number from ``i`` to the next delimiter or line end: ``(value, index of that end,
    converted exactly)``; an empty field is NaN."""
    n = buf.size
    first = i
    i = _skip_blanks(buf, i, delim)
    neg = False
    signed = i < n and (buf[i] == 45 or buf[i] == 43)
    if signed:
        neg = buf[i] == 45
        i += 1
    i, mant, count, _, seen = _digits(buf, i, 0, 0, False)
    dot = i < n and buf[i] == 46
    places = 0
    if dot:
        i, mant, count, places, seen_fraction = _digits(buf, i + 1, mant, count, True)
        seen = seen or seen_fraction
    exp10 = -places
    if seen and i < n and (buf[i] == 101 or buf[i] == 69):
        i, e, ok = _exponent(buf, i + 1)
        if not ok:
            return 0.0, i, False
        exp10 += e
    i = _skip_blanks(buf, i, delim)
    if i < n and buf[i] != delim and buf[i] != 10 and buf[i] != 13:
        return 0.0, i, False
    if not seen:
        # only a field with nothing in it is a missing value
        return np.nan, i, not (signed or dot or i != first)
    value, ok = _value(mant, count, exp10, pow10)
    return (-value if neg else value), i, ok


@_jit
def _parse(buf: np.ndarray, n_fields: int, column_slot: np.ndarray, delim: int,
           out: np.ndarray) -> int:
    """Parse the rows of ``buf`` into ``out`` (used columns x rows: each column contiguous, as
    the reader keeps them); field ``k`` of a row goes to column ``column_slot[k]`` (-1:
    skipped). Returns the number of rows, or -1 when a field or row is outside what this
    parser converts exactly."""
    pow10 = np.empty(_EXACT_POWER + 1)
    p = 1.0
    for k in range(_EXACT_POWER + 1):
        pow10[k] = p
        p *= 10.0
    n = buf.size
    i = 0
    row = 0
    while i < n:
        if row >= out.shape[1]:
            return -1
        for field in range(n_fields):
            slot = column_slot[field]
            if slot < 0:  # a column not asked for: find its end
                while i < n and buf[i] != delim and buf[i] != 10 and buf[i] != 13:
                    i += 1
            else:
                value, i, ok = _field(buf, i, delim, pow10)
                if not ok:
                    return -1
                out[slot, row] = value
            last = field == n_fields - 1
            at_delim = i < n and buf[i] == delim
            if at_delim == last:  # too many fields, or too few
                return -1
            if at_delim:
                i += 1
        if i < n and buf[i] == 13:
            i += 1
        if i < n:
            if buf[i] != 10:
                return -1
            i += 1
        row += 1
    return row


_compiled = None if njit is None else _parse


def parse_numbers(body: bytes, n_fields: int, usecols: list[int], delim: str
                  ) -> np.ndarray | None:
    """The columns ``usecols`` of the CSV rows in ``body`` (no header; ``n_fields`` fields per
    row) as a float64 array of shape (rows, len(usecols)), or None when the fast path does not
    apply (no numba, or a field it does not convert exactly). The array is the transpose of a
    C-ordered one: each column is contiguous, so taking the columns apart copies nothing."""
    if _compiled is None or delim not in _DELIMITERS:
        return None
    if not usecols or max(usecols) >= n_fields or len(set(usecols)) != len(usecols):
        return None
    slot = np.full(n_fields, -1, dtype=np.int64)
    slot[np.asarray(usecols, dtype=np.int64)] = np.arange(len(usecols))
    buf = np.frombuffer(body, dtype=np.uint8)
    # a last line without its newline is a row too
    rows = body.count(b"\n") + (0 if body.endswith(b"\n") else 1)
    out = np.empty((len(usecols), rows))
    try:
        n = _compiled(buf, n_fields, slot, ord(delim), out)
    except Exception:  # noqa: BLE001 - a compile failure leaves the file to np.loadtxt
        return None
    if n <= 0:
        return None
    return (out if n == rows else out[:, :n].copy()).T
