"""The compiled fast path of numeric text parsing agrees with Python's float() and defers what it cannot read."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam6d.errors import FormatError
from slam6d.io.text import parse_numeric_bytes, parse_numeric_rows


@pytest.mark.parametrize("fmt", ["%.2f", "%.6f", "%.3e", "%.10g", "%.15g"])
def test_fast_path_is_bit_exact_for_usual_number_formats(fmt: str) -> None:
    rng = np.random.default_rng(0)
    values = rng.normal(size=(2000, 3)) * 10.0 ** rng.integers(-4, 5, (2000, 3))
    text = "\n".join(" ".join(fmt % v for v in row) for row in values)
    fast = parse_numeric_bytes(text.encode(), (3,))
    assert fast is not None
    np.testing.assert_array_equal(fast, np.array([float(v) for v in text.split()]).reshape(-1, 3))


def test_comments_blank_lines_signs_and_exponents() -> None:
    data = b"# header\n1e3 -2.5E-2 .5\r\n\n  7. +8\t9  \n# end"
    np.testing.assert_array_equal(parse_numeric_bytes(data, (3,)), [[1000.0, -0.025, 0.5], [7.0, 8.0, 9.0]])
    assert parse_numeric_bytes(b"", (3,)).shape == (0, 3)


@pytest.mark.parametrize("data", [b"1 2 3\n4 5\n", b"nan 1 2\n", b"1 2 3x\n", b"1,2,3\n", b"1 2\n", b"- 1 2\n"])
def test_anything_unusual_is_left_to_the_general_parser(data: bytes) -> None:
    assert parse_numeric_bytes(data, (3,)) is None


def test_general_parser_still_reads_nan_and_names_the_bad_line() -> None:
    rows = parse_numeric_rows(Path("a.xyz"), "1 2 3\nnan 4 5\n", (3,))
    assert np.isnan(rows[1, 0]) and rows[1, 2] == 5.0
    with pytest.raises(FormatError, match=r"a\.xyz:2: expected 3 numbers"):
        parse_numeric_rows(Path("a.xyz"), "1 2 3\n4 5\n", (3,))


@pytest.mark.parametrize("separator", ["\r", "\x0b", "\x0c"])
def test_a_lone_carriage_return_ends_a_row_on_both_paths(separator: str) -> None:
    """Lines are what ``str.splitlines`` says (old Mac files end lines with ``\\r``), so the fast
    path's rows and the line numbers readers give in their messages count the same lines."""
    text = f"1 2 3{separator}4 5 6\n"
    fast = parse_numeric_bytes(text.encode(), (3, 6))
    np.testing.assert_array_equal(fast, [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    np.testing.assert_array_equal(parse_numeric_rows(Path("a.xyz"), text.replace("1", "nan"), (3, 6))[1], [4, 5, 6])
    with pytest.raises(FormatError, match=r"a\.xyz:2: expected 3 numbers"):
        parse_numeric_rows(Path("a.xyz"), f"1 2 3\n4 5{separator}6\n", (3,))
