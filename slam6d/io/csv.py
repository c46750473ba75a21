"""Comma-separated point clouds as libpointmatcher writes them, and its list files.

A cloud file has a header row naming the columns (``x,y,z,nx,ny,nz``; ``intensity`` is picked up
when present) or no header, in which case the columns are ``x,y,z[,intensity]``. Fields are
separated by commas or, as in some libpointmatcher data, by whitespace. Metres, canonical frame.

A *list file* (first column ``reading``, e.g. ``carCloudList.csv``) names the clouds of a sequence
in order, optionally with ground-truth poses ``gT00 … gT33`` (row-major 4x4 ``world_from_scan``).
When a folder holds exactly one list naming its clouds of a format, that list fixes their order
and supplies their poses; the VTK format uses the same rule.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from slam6d.errors import FormatError
from slam6d.geometry import Matrix
from slam6d.io.order import sort_scan_files
from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.source import check_regular_file
from slam6d.io.text import parse_numeric_rows, read_text_file

_GT_COLUMNS = [f"gt{r}{c}" for r in range(4) for c in range(4)]


def _first_row(text: str) -> tuple[int, list[str], str | None]:
    """0-based index, fields and delimiter (comma, or None for whitespace) of the first non-blank line.

    libpointmatcher itself writes some "csv" clouds whitespace-separated, so both are accepted.
    """
    for index, line in enumerate(text.splitlines()):
        if line.strip():
            delimiter = "," if "," in line else None
            return index, [f.strip() for f in line.split(delimiter)], delimiter
    return -1, [], None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def is_list_file(path: Path) -> bool:
    try:
        check_regular_file(path)  # a FIFO named *.csv must not block the folder listing
        with path.open() as fh:
            first = fh.readline(4096)
    except (OSError, UnicodeDecodeError, FormatError):
        return False
    return first.split(",")[0].strip().lower() == "reading"


def read_pointmatcher_list(path: Path) -> list[tuple[Path, Matrix | None]]:
    """(cloud path, ground-truth pose or None) for each row of a libpointmatcher list file."""
    text = read_text_file(path)
    header_index, header, _ = _first_row(text)
    names = [h.lower() for h in header]
    if not names or names[0] != "reading":
        raise FormatError(path, "not a libpointmatcher list file (first column must be 'reading')", header_index + 1)
    gt = [names.index(c) for c in _GT_COLUMNS] if all(c in names for c in _GT_COLUMNS) else None
    entries: list[tuple[Path, Matrix | None]] = []
    for line_no, line in enumerate(text.splitlines()[header_index + 1 :], start=header_index + 2):
        if not line.strip():
            continue
        fields = [f.strip() for f in line.split(",")]
        if len(fields) != len(names):
            raise FormatError(path, f"expected {len(names)} columns like the header, found {len(fields)}", line_no)
        pose = None
        if gt is not None:
            try:
                pose = np.array([float(fields[i]) for i in gt]).reshape(4, 4)
            except ValueError:
                raise FormatError(path, "ground-truth pose column is not a number", line_no) from None
        entries.append((path.parent / fields[0], pose))
    return entries


def find_list_for(directory: Path, suffix: str) -> list[tuple[Path, Matrix | None]] | None:
    """The entries of the one list file in ``directory`` naming existing ``suffix`` clouds, if exactly one does."""
    matches = []
    for candidate in sorted(directory.glob("*.csv")):
        if not is_list_file(candidate):
            continue
        entries = read_pointmatcher_list(candidate)
        if entries and all(p.suffix.lower() == suffix and p.is_file() for p, _ in entries):
            matches.append(entries)
    return matches[0] if len(matches) == 1 else None


def read_csv_cloud(path: Path) -> CloudData:
    """comma-separated cloud with x,y,z[,intensity] header (libpointmatcher); list file = order+poses"""
    text = read_text_file(path)
    header_index, first, delimiter = _first_row(text)
    if header_index < 0:
        return CloudData(np.empty((0, 3)))
    if first and first[0].lower() == "reading":
        raise FormatError(path, "this is a list of clouds, not a cloud: read its folder instead")
    if all(_is_number(f) for f in first):
        columns = ["x", "y", "z", "intensity"][: len(first)] + [f"c{i}" for i in range(4, len(first))]
        body, first_line = text, 1
    else:
        columns = [c.lower() for c in first]
        body = "\n".join(text.splitlines()[header_index + 1 :])
        first_line = header_index + 2
    if missing := [a for a in "xyz" if a not in columns]:
        raise FormatError(path, f"no column(s) {missing} in the header line", header_index + 1)
    rows = parse_numeric_rows(path, body, (len(columns),), delimiter=delimiter, first_line=first_line)
    if rows.shape[0] == 0:
        return CloudData(np.empty((0, 3)))
    points = rows[:, [columns.index(a) for a in "xyz"]]
    intensity = rows[:, columns.index("intensity")].astype(np.float32) if "intensity" in columns else None
    return CloudData(points, intensity)


def write_csv_cloud(path: Path | str, points: np.ndarray, intensity: np.ndarray | None = None) -> None:
    columns = [np.asarray(points, dtype=np.float64).reshape(-1, 3)]
    header = "x,y,z"
    if intensity is not None:
        columns.append(np.asarray(intensity, dtype=np.float64).reshape(-1, 1))
        header += ",intensity"
    np.savetxt(Path(path), np.hstack(columns), fmt="%.9g", delimiter=",", header=header, comments="")


def discover_listed(suffix: str) -> Callable[[Path], list[Path]]:
    """Discovery for list-aware formats: the list's order if one fits, else the clouds sorted by name."""

    def discover(directory: Path) -> list[Path]:
        if directory.is_file():
            return []
        entries = find_list_for(directory, suffix)
        if entries is not None:
            return [p for p, _ in entries]
        return sort_scan_files(
            p for p in directory.iterdir() if p.is_file() and p.suffix.lower() == suffix and not is_list_file(p)
        )

    return discover


def list_file_ordering(suffix: str) -> Callable[[Path], str | None]:
    """For :attr:`ScanFormat.order_fixed_by`: the list file that orders a folder of ``suffix`` clouds, if any."""

    def fixed_by(directory: Path) -> str | None:
        if directory.is_file():
            return f"the list file {directory.name}"
        return "the list file naming the clouds" if find_list_for(directory, suffix) is not None else None

    return fixed_by


def listed_poses(suffix: str) -> Callable[[Path, list[Path]], list[Matrix] | None]:
    """Poses from the list file that :func:`discover_listed` used, when it has ``gT`` columns for every file."""

    def sequence_poses(directory: Path, files: list[Path]) -> list[Matrix] | None:
        entries = find_list_for(directory, suffix)
        if entries is None or any(pose is None for _, pose in entries):
            return None
        by_file = {p.resolve(): pose for p, pose in entries if pose is not None}
        if not all(f.resolve() in by_file for f in files):
            return None
        return [by_file[f.resolve()] for f in files]

    return sequence_poses


def listed_format(name: str, read: Callable[[Path], CloudData]) -> ScanFormat:
    """A format of ``.<name>`` clouds that a list file (libpointmatcher's ``cloudList.csv``) may order and
    pose: csv and vtk clouds come with the same list files, so they share how a folder is read."""
    suffix = f".{name}"
    return ScanFormat(
        name,
        read,
        discover=discover_listed(suffix),
        order_fixed_by=list_file_ordering(suffix),
        sequence_poses=listed_poses(suffix),
    )


CSV_FORMAT = register_format(listed_format("csv", read_csv_cloud))
