"""3DTK "uos" format: ``scanNNN.3d`` (x y z [reflectance], cm) with ``scanNNN.pose`` beside it.

Frame: left-handed, x right, y up, z forward, centimetres; the ``.pose`` file holds the
translation (cm) on line 1 and the Euler angles (degrees, R = Rx·Ry·Rz) on line 2. Readings at
the sensor's maximum (3276.7 cm) mean "no echo" and are dropped here, since no range filter the
user picks should be needed to get rid of them.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from slam6d.errors import FormatError
from slam6d.geometry import UOS, Matrix, rotation_to_euler, uos_pose
from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.source import read_file_bytes
from slam6d.io.text import parse_numeric_bytes, parse_numeric_rows, read_text_file

NO_ECHO_RANGE_CM = 3276.0
_SCAN_NAME = re.compile(r"^scan(\d{3,})\.3d$")  # 3DTK writes %03d: scan1000.3d follows scan999.3d


def read_pose_file(path: Path) -> Matrix:
    """Native pose (cm, left-handed) from a ``.pose`` file."""
    text = read_text_file(path, "2 lines: x y z, then θx θy θz")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if len(lines) < 2:
        raise FormatError(
            path, f"a .pose file needs 2 lines (x y z in cm, then θx θy θz in degrees), found {len(lines)}"
        )
    rows = []
    for line_no, line in enumerate(lines[:2], start=1):
        fields = line.split()
        if len(fields) != 3:
            raise FormatError(path, f"expected 3 numbers, found {len(fields)}", line_no)
        try:
            rows.append([float(f) for f in fields])
        except ValueError:
            raise FormatError(path, "not a number in the line", line_no) from None
    values = np.array(rows)
    if not np.isfinite(values).all():
        raise FormatError(path, "pose contains NaN or infinity")
    return uos_pose(values[0], values[1])


def write_pose_file(path: Path, native_pose: Matrix) -> None:
    angles = np.degrees(rotation_to_euler(native_pose[:3, :3]))
    t = native_pose[:3, 3]
    path.write_text(f"{t[0]:.6f} {t[1]:.6f} {t[2]:.6f}\n{angles[0]:.6f} {angles[1]:.6f} {angles[2]:.6f}\n")


def read_uos_scan(path: Path) -> CloudData:
    """3DTK uos: scanNNN.3d + scanNNN.pose (cm, degrees, left-handed, y up)"""
    columns = (3, 4, 6, 7)
    data = read_file_bytes(path)
    rows = parse_numeric_bytes(data, columns)
    if rows is None:  # not plain numbers: the general parser reads it or names the bad line
        try:
            text = data.decode()
        except UnicodeDecodeError:
            raise FormatError(path, "not a text file (uos scans are ASCII 'x y z' lines)") from None
        rows = parse_numeric_rows(path, text, allowed_columns=columns)
    points = rows[:, :3]
    intensity = rows[:, 3].astype(np.float32) if rows.shape[1] in (4, 7) else None
    squared = np.einsum("ij,ij->i", points, points)  # row norms without numpy's slow short-axis reductions
    echo = squared < NO_ECHO_RANGE_CM**2
    if not np.isfinite(squared).all():
        echo |= ~np.isfinite(points).all(axis=1)  # keep NaNs so the registry can warn about them
    if not echo.all():
        points = points[echo]
        intensity = intensity[echo] if intensity is not None else None
    pose_path = path.with_suffix(".pose")
    pose = read_pose_file(pose_path) if pose_path.exists() else None
    return CloudData(points, intensity, pose)


def write_uos_scan(
    directory: Path, index: int, native_points: np.ndarray, native_pose: Matrix | None, decimals: int = 3
) -> Path:
    """Write ``scanNNN.3d`` (and ``.pose`` when a pose is given) in 3DTK's layout.

    ``decimals`` of a centimetre: 2 (0.1 mm) is far below any scanner's noise and keeps files small.
    """
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"scan{index:03d}.3d"
    xyz = np.asarray(native_points, dtype=np.float64)[:, :3]
    # One %-format over all rows: the bytes np.savetxt writes, three times faster (campus sessions
    # write thousands of scans).
    line = " ".join([f"%.{decimals}f"] * 3) + "\n"
    path.write_text((line * len(xyz)) % tuple(xyz.ravel().tolist()))
    if native_pose is not None:
        write_pose_file(path.with_suffix(".pose"), native_pose)
    return path


def discover_uos(directory: Path) -> list[Path]:
    """``scan000.3d``, ``scan001.3d``, … stopping at the first gap, as 3DTK does."""
    numbers = sorted(int(m.group(1)) for p in directory.iterdir() if (m := _SCAN_NAME.match(p.name)))
    files = []
    for expected, number in enumerate(numbers):
        if number != expected:
            break
        files.append(directory / f"scan{number:03d}.3d")
    return files


UOS_FORMAT = register_format(
    ScanFormat(
        "uos",
        read_uos_scan,
        UOS,
        suffixes=(".3d",),
        discover=discover_uos,
        order_fixed_by=lambda _directory: "3DTK's scanNNN numbering",
    )
)
