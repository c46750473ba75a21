"""Plain text point lists: ``x y z [more columns]`` per line (``.xyz``, ``.txt``, ``.pts``, ``.asc``).

Columns may be separated by spaces or commas. A fourth column is taken as intensity when there
are 4 or 7 columns (``x y z i`` and the Leica/Faro ``x y z i r g b`` layout); 6 columns are read
as ``x y z r g b`` or normals and only x y z are kept. A ``.pts`` file may start with a point-count
line, which is skipped. Metres, canonical frame.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.text import parse_numeric_rows, read_text_file

MAX_COLUMNS = 32


def _first_data_line(lines: list[str]) -> int | None:
    for index, line in enumerate(lines):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            return index
    return None


def read_xyz(path: Path) -> CloudData:
    """text x y z [intensity ...] per line, space or comma separated, metres"""
    text = read_text_file(path, "'x y z' per line")
    lines = text.splitlines()
    first = _first_data_line(lines)
    if first is None:
        return CloudData(np.empty((0, 3)))
    first_line = 1
    if len(lines[first].split()) == 1 and lines[first].strip().isdigit():  # .pts point-count line
        lines = lines[first + 1 :]
        first_line = first + 2
    data_start = _first_data_line(lines)
    if data_start is None:
        return CloudData(np.empty((0, 3)))
    delimiter = "," if "," in lines[data_start] else None
    rows = parse_numeric_rows(
        path, "\n".join(lines), tuple(range(3, MAX_COLUMNS + 1)), delimiter=delimiter, first_line=first_line
    )
    if rows.shape[0] == 0:
        return CloudData(np.empty((0, 3)))
    intensity = rows[:, 3].astype(np.float32) if rows.shape[1] in (4, 7) else None
    return CloudData(rows[:, :3].copy(), intensity)


def write_xyz(path: Path | str, points: np.ndarray, intensity: np.ndarray | None = None) -> None:
    columns = [np.asarray(points, dtype=np.float64).reshape(-1, 3)]
    if intensity is not None:
        columns.append(np.asarray(intensity, dtype=np.float64).reshape(-1, 1))
    np.savetxt(Path(path), np.hstack(columns), fmt="%.9g")


XYZ_FORMAT = register_format(ScanFormat("xyz", read_xyz, suffixes=(".xyz", ".txt", ".pts", ".asc")))
