"""Legacy VTK files (``# vtk DataFile Version …``), ASCII or BINARY, as libpointmatcher writes them.

Only the ``POINTS`` section is read (any dataset type that has one); cells such as ``VERTICES``
and attribute data are skipped. In ASCII files the coordinates may wrap across lines arbitrarily,
so errors are traced back to the exact line. BINARY data is big-endian, as the legacy format
prescribes. Metres, canonical frame. In a folder, a libpointmatcher list file (``cloudList.csv``)
fixes the order, and its ``gT`` columns the poses (see :mod:`slam6d.io.csv`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.io.csv import listed_format
from slam6d.io.registry import CloudData, register_format
from slam6d.io.source import read_file_bytes

_TYPES = {"float": "f4", "double": "f8", "int": "i4", "unsigned_int": "u4", "short": "i2", "long": "i8"}


def _lines_with_offsets(raw: bytes, start: int, limit: int) -> list[tuple[int, int, str]]:
    """(line number, byte offset of the next line, text) of up to ``limit`` header lines."""
    out = []
    offset = start
    for line_no in range(1, limit + 1):
        newline = raw.find(b"\n", offset)
        end = len(raw) if newline < 0 else newline
        out.append((line_no, end + 1, raw[offset:end].decode("ascii", errors="replace").strip()))
        if newline < 0:
            break
        offset = end + 1
    return out


def _points_header(path: Path, raw: bytes) -> tuple[str, int, str, int, int]:
    """(encoding, point count, numpy type, byte offset of the data, line number of the POINTS line)."""
    head = _lines_with_offsets(raw, 0, 64)
    if not head or not head[0][2].lower().startswith("# vtk datafile"):
        raise FormatError(path, "not a legacy VTK file (first line must be '# vtk DataFile Version …')", 1)
    if len(head) < 4:
        raise FormatError(path, "VTK header is shorter than 4 lines", len(head))
    encoding = head[2][2].upper()
    if encoding not in ("ASCII", "BINARY"):
        raise FormatError(path, "third line must be ASCII or BINARY", 3)
    if not head[3][2].upper().startswith("DATASET"):
        raise FormatError(path, "fourth line must be 'DATASET …'", 4)
    for line_no, next_offset, text in head[4:]:
        words = text.split()
        if not words:
            continue
        if words[0].upper() != "POINTS":
            raise FormatError(path, "expected a POINTS section", line_no)
        if len(words) != 3 or not words[1].isdigit() or words[2].lower() not in _TYPES:
            raise FormatError(path, "bad POINTS line (expected: POINTS N float|double)", line_no)
        return encoding, int(words[1]), _TYPES[words[2].lower()], next_offset, line_no
    raise FormatError(path, "no POINTS section in the VTK header")


def _ascii_points(path: Path, text: str, count: int, first_line: int) -> NDArray[np.float64]:
    lines = text.splitlines()
    needed = 3 * count
    taken = 0
    end = 0
    while taken < needed and end < len(lines):
        taken += len(lines[end].split())
        end += 1
    if taken < needed:
        raise FormatError(path, f"truncated: POINTS promises {count} points, file ends", first_line + end)
    if taken > needed:
        raise FormatError(path, f"the {count} points of POINTS end in the middle of a line", first_line + end - 1)
    block = lines[:end]
    try:
        return np.array(" ".join(block).split(), dtype=np.float64).reshape(-1, 3)
    except ValueError:
        for offset, line in enumerate(block):
            for column, word in enumerate(line.split(), start=1):
                try:
                    float(word)
                except ValueError:
                    raise FormatError(path, f"field {column} is not a number", first_line + offset) from None
        raise


def read_vtk(path: Path) -> CloudData:
    """legacy VTK (ASCII or BINARY) POINTS, metres; cloudList.csv gives order and gT poses"""
    raw = read_file_bytes(path)
    encoding, count, dtype, offset, line_no = _points_header(path, raw)
    if encoding == "BINARY":
        needed = 3 * count * np.dtype(dtype).itemsize
        if len(raw) - offset < needed:
            raise FormatError(path, f"truncated: {count} points need {needed} bytes, {len(raw) - offset} follow")
        values = np.frombuffer(raw, dtype=">" + dtype, count=3 * count, offset=offset)
        return CloudData(values.astype(np.float64).reshape(-1, 3))
    try:
        text = raw[offset:].decode("ascii")
    except UnicodeDecodeError:
        raise FormatError(path, "ASCII VTK file contains non-ASCII bytes") from None
    return CloudData(_ascii_points(path, text, count, line_no + 1))


def write_vtk(path: Path | str, points: NDArray[np.float64], binary: bool = False) -> None:
    """Polydata with one vertex cell per point, the layout libpointmatcher and ParaView read."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(points)
    encoding = "BINARY" if binary else "ASCII"
    with Path(path).open("wb") as fh:
        fh.write(f"# vtk DataFile Version 3.0\nslam6d\n{encoding}\nDATASET POLYDATA\nPOINTS {n} double\n".encode())
        cells = np.column_stack([np.ones(n, dtype=np.int64), np.arange(n, dtype=np.int64)])
        if binary:
            fh.write(points.astype(">f8").tobytes())
            fh.write(f"\nVERTICES {n} {2 * n}\n".encode())
            fh.write(cells.astype(">i4").tobytes())
            fh.write(b"\n")
        else:
            np.savetxt(fh, points, fmt="%.17g")
            fh.write(f"VERTICES {n} {2 * n}\n".encode())
            np.savetxt(fh, cells, fmt="%d")


VTK_FORMAT = register_format(listed_format("vtk", read_vtk))
