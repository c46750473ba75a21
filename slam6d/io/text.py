"""Fast parsing of whitespace-separated numeric text, with exact line numbers on failure.

The fast path hands the whole file to numpy; only when that fails do we walk the lines to find
the first bad one, so big valid files stay fast and broken ones still get a precise message.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError


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
        for field in fields:
            try:
                float(field)
            except ValueError:
                raise FormatError(path, f"'{field}' is not a number", line_no) from None
    raise FormatError(path, "could not parse numeric rows")
