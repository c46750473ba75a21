"""KITTI velodyne ``.bin`` scans: raw float32 ``x y z intensity`` records, metres, sensor frame.

The KITTI sensor frame (x forward, y left, z up) is already the canonical frame. A directory is read
as ``NNNNNN.bin`` files in name order, either directly or from its single subfolder holding bins
(so both ``balm_hall/`` and ``balm_hall/velodyne_style_bin/`` work).

Poses come from a KITTI poses file found by this rule: a ``*.txt`` file whose name contains
``pose``, in the bins' folder or its parent, with exactly one 3x4 line per bin file. If exactly one
file qualifies it is used; if several do, none is (a warning says so) and ``--poses`` must choose.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from slam6d.errors import FormatError
from slam6d.geometry import Matrix
from slam6d.io.order import sort_scan_files
from slam6d.io.poses import read_kitti_poses
from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.source import read_file_bytes

RECORD = np.dtype([("xyz", "<f4", (3,)), ("intensity", "<f4")])


class AmbiguousPosesWarning(UserWarning):
    """Several poses files fit a scan folder, so none was used."""


def read_kitti_bin(path: Path) -> CloudData:
    """KITTI velodyne .bin: float32 x y z intensity (m, x forward, z up); poses from a *pose*.txt"""
    raw = read_file_bytes(path)
    if len(raw) % RECORD.itemsize:
        raise FormatError(
            path,
            f"size {len(raw)} bytes is not a multiple of {RECORD.itemsize} (float32 x y z intensity per point); "
            "truncated or not a KITTI velodyne file",
        )
    records = np.frombuffer(raw, dtype=RECORD)
    return CloudData(records["xyz"].astype(np.float64), records["intensity"].copy())


def write_kitti_bin(path: Path, points: np.ndarray, intensity: np.ndarray | None = None) -> None:
    records = np.zeros(len(points), dtype=RECORD)
    records["xyz"] = points
    if intensity is not None:
        records["intensity"] = intensity
    records.tofile(path)


def _bins(directory: Path) -> list[Path]:
    return sort_scan_files(p for p in directory.iterdir() if p.is_file() and p.suffix.lower() == ".bin")


def discover_kitti(directory: Path) -> list[Path]:
    files = _bins(directory)
    if files:
        return files
    subfolders = [d for d in sort_scan_files(directory.iterdir()) if d.is_dir() and _bins(d)]
    return _bins(subfolders[0]) if len(subfolders) == 1 else []


def _count_rows(path: Path) -> int:
    try:
        data = read_file_bytes(path, limit=256 << 20)  # a poses file of 256 MB would be 2 M poses
    except FormatError:
        return -1
    return sum(1 for line in data.splitlines() if line.strip() and not line.lstrip().startswith(b"#"))


def find_kitti_poses_file(files: list[Path]) -> Path | None:
    """The one poses file matching the rule in this module's docstring, or None."""
    if not files:
        return None
    folder = files[0].parent
    candidates = [
        p
        for d in (folder, folder.parent)
        for p in sorted(d.glob("*.txt"))
        if "pose" in p.name.lower() and _count_rows(p) == len(files)
    ]
    if len(candidates) > 1:
        warnings.warn(
            f"{folder}: several poses files fit ({', '.join(p.name for p in candidates)}); "
            "none used - pass --poses to choose",
            AmbiguousPosesWarning,
            stacklevel=2,
        )
        return None
    return candidates[0] if candidates else None


def kitti_sequence_poses(directory: Path, files: list[Path]) -> list[Matrix] | None:
    path = find_kitti_poses_file(files)
    return read_kitti_poses(path) if path is not None else None


KITTI_FORMAT = register_format(
    ScanFormat(
        "kitti", read_kitti_bin, suffixes=(".bin",), discover=discover_kitti, sequence_poses=kitti_sequence_poses
    )
)
