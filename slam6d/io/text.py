"""Fast parsing of whitespace-separated numeric text, with exact line numbers on failure.

The fast path is a compiled single pass over the file's bytes (plain decimal numbers, optional
exponent): about 20x faster than ``numpy.loadtxt`` and 5x faster than splitting the text into
Python strings, which matters because ASCII scans of ~100k points are read by the dozen. Anything
it does not recognise (``nan``, ``inf``, hex, other delimiters, ragged rows) sends the file down the
general path, which hands it to numpy and, when that fails too, walks the lines to find the first
bad one, so big valid files stay fast and broken ones still get a precise message.
"""

from __future__ import annotations

from pathlib import Path

import numba
import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.io.source import read_file_text


def read_text_file(path: Path, expected: str = "") -> str:
    """A text file's contents, or a :class:`FormatError` naming it (binary or unreadable files).

    ``expected`` says what the format wants (e.g. "'x y z' per line"), so the message tells the user
    what the file should have looked like.
    """
    return read_file_text(path, expected)


def parse_numeric_rows(
    path: Path,
    text: str,
    allowed_columns: tuple[int, ...],
    comment: str = "#",
    delimiter: str | None = None,
    first_line: int = 1,
) -> NDArray[np.float64]:
    """Rows of numbers, every row with the same column count (one of ``allowed_columns``).

    ``first_line`` is the 1-based line number of ``text``'s first line in the file (for headers).
    """
    if delimiter is None and text.isascii():
        fast = parse_numeric_bytes(text.encode("ascii"), allowed_columns, comment)
        if fast is not None:
            return fast
    lines = text.splitlines()
    body = [ln for ln in lines if ln.strip() and not ln.lstrip().startswith(comment)]
    if not body:
        return np.empty((0, allowed_columns[0]))
    if delimiter is not None:
        body = [ln.replace(delimiter, " ") for ln in body]
    ncols = len(body[0].split())
    try:
        values = np.array(" ".join(body).split(), dtype=np.float64)
    except ValueError:
        values = None
    if values is not None and ncols in allowed_columns and values.size == ncols * len(body):
        return values.reshape(-1, ncols)
    _raise_first_bad_line(path, lines, allowed_columns, comment, delimiter, first_line)
    raise AssertionError("unreachable")


# exact powers of ten: a mantissa below 2**53 divided or multiplied by one of these is correctly rounded
_POW10 = np.array([10.0**k for k in range(23)])


@numba.njit(cache=True, nogil=True)  # nogil: `slam6d run` imports the engine on a thread meanwhile
def _parse_ascii_numbers(buf, comment, pow10):  # type: ignore[no-untyped-def]
    """(values, columns per row, ok) from ASCII bytes; ok is False on anything but plain numbers in even rows."""
    n = buf.shape[0]
    out = np.empty(n // 2 + 1)
    count = 0
    ncols = -1
    line_cols = 0
    i = 0
    while i < n:
        c = buf[i]
        if c == 10 or c == 13 or c == 11 or c == 12:  # \n \r \v \f end a row, as str.splitlines says
            if line_cols > 0:
                if ncols < 0:
                    ncols = line_cols
                elif line_cols != ncols:
                    return out[:count], ncols, False
            line_cols = 0
            i += 1
            continue
        if c == 32 or c == 9:
            i += 1
            continue
        if c == comment and line_cols == 0:
            while i < n and not (buf[i] == 10 or buf[i] == 13 or buf[i] == 11 or buf[i] == 12):
                i += 1
            continue
        negative = False
        if c == 45 or c == 43:  # - +
            negative = c == 45
            i += 1
        mantissa = 0
        digits = 0
        shift = 0  # decimal exponent of the mantissa's last digit
        seen = False
        while i < n and 48 <= buf[i] <= 57:
            seen = True
            if digits < 18:
                mantissa = mantissa * 10 + (buf[i] - 48)
                if mantissa > 0:
                    digits += 1
            else:
                shift += 1
            i += 1
        if i < n and buf[i] == 46:  # '.'
            i += 1
            while i < n and 48 <= buf[i] <= 57:
                seen = True
                if digits < 18:
                    mantissa = mantissa * 10 + (buf[i] - 48)
                    shift -= 1
                    if mantissa > 0:
                        digits += 1
                i += 1
        if not seen:
            return out[:count], ncols, False
        if i < n and (buf[i] == 101 or buf[i] == 69):  # e E
            i += 1
            exp_negative = False
            if i < n and (buf[i] == 45 or buf[i] == 43):
                exp_negative = buf[i] == 45
                i += 1
            exponent = 0
            exp_seen = False
            while i < n and 48 <= buf[i] <= 57:
                exp_seen = True
                if exponent < 100000:
                    exponent = exponent * 10 + (buf[i] - 48)
                i += 1
            if not exp_seen:
                return out[:count], ncols, False
            shift += -exponent if exp_negative else exponent
        if i < n and not (buf[i] == 32 or buf[i] == 9 or buf[i] == 13 or buf[i] == 10 or buf[i] == 11 or buf[i] == 12):
            return out[:count], ncols, False
        value = float(mantissa)
        if shift < 0:
            value = value / pow10[-shift] if shift >= -22 else value * 10.0**shift
        elif shift > 0:
            value = value * pow10[shift] if shift <= 22 else value * 10.0**shift
        out[count] = -value if negative else value
        count += 1
        line_cols += 1
    if line_cols > 0:
        if ncols < 0:
            ncols = line_cols
        elif line_cols != ncols:
            return out[:count], ncols, False
    return out[:count], ncols, True


def parse_numeric_bytes(
    data: bytes, allowed_columns: tuple[int, ...], comment: str = "#"
) -> NDArray[np.float64] | None:
    """Rows of plain decimal numbers from ASCII bytes, or None when the compiled fast path cannot
    read them (then :func:`parse_numeric_rows` gives the exact answer or the exact error).

    Exact to the last bit for numbers of up to 15 significant digits whose decimal exponent (of
    the last digit) stays within ±22; others may differ from ``float()`` in the last bit.
    """
    if len(comment) != 1:
        return None
    buf = np.frombuffer(data, dtype=np.uint8)
    values, ncols, ok = _parse_ascii_numbers(buf, ord(comment), _POW10)
    if not ok:
        return None
    if ncols < 0:
        return np.empty((0, allowed_columns[0]))
    if ncols not in allowed_columns:
        return None
    return values.reshape(-1, ncols)


def _raise_first_bad_line(
    path: Path,
    lines: list[str],
    allowed_columns: tuple[int, ...],
    comment: str,
    delimiter: str | None,
    first_line: int,
) -> None:
    expected: int | None = None
    for offset, raw in enumerate(lines):
        stripped = raw.strip()
        if not stripped or stripped.startswith(comment):
            continue
        line_no = first_line + offset
        fields = (stripped.replace(delimiter, " ") if delimiter else stripped).split()
        if expected is None:
            if len(fields) not in allowed_columns:
                cols = " or ".join(str(c) for c in allowed_columns)
                raise FormatError(path, f"expected {cols} numbers per line, found {len(fields)}", line_no)
            expected = len(fields)
        elif len(fields) != expected:
            raise FormatError(
                path, f"expected {expected} numbers per line like the first, found {len(fields)}", line_no
            )
        for column, field in enumerate(fields, start=1):
            try:
                float(field)
            except ValueError:
                raise FormatError(path, f"field {column} is not a number", line_no) from None
    raise FormatError(path, "could not parse numeric rows")
