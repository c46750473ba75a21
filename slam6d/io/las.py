"""ASPRS LAS/LAZ point clouds (via laspy, LAZ through lazrs).

Coordinates are the scaled ones (``X * scale + offset``), assumed metres in a right-handed, z-up
frame - true for projected CRSs (UTM etc.); a file in feet would need converting first. Intensity
is the 16-bit LAS intensity. Points flagged withheld are still read: the flag is advisory and
scanners use it inconsistently.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.geometry import CANONICAL
from slam6d.io.registry import CloudData, ScanFormat, register_format


def read_las(path: Path) -> CloudData:
    import laspy

    try:
        las = laspy.read(path)
        points = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1).astype(np.float64)
        intensity = np.asarray(las.intensity, dtype=np.float32)
    except (laspy.errors.LaspyException, RuntimeError, ValueError, OSError) as exc:
        raise FormatError(path, f"cannot read as LAS/LAZ: {exc}") from None
    return CloudData(points.reshape(-1, 3), intensity.reshape(-1))


def _intensity_u16(intensity: NDArray[np.floating]) -> NDArray[np.uint16]:
    """LAS intensity is 16-bit: values in [0, 1] (KITTI style) are stretched, larger ones clipped."""
    values = np.nan_to_num(np.asarray(intensity, dtype=np.float64).reshape(-1))
    if values.size and values.max() <= 1.0:
        values = values * 65535.0
    return np.clip(np.rint(values), 0, 65535).astype(np.uint16)


def write_las(
    path: Path | str,
    points: NDArray[np.float64],
    colors: NDArray[np.uint8] | None = None,
    intensity: NDArray[np.floating] | None = None,
    scale: float = 0.0001,
) -> None:
    """LAS or LAZ (compressed when the suffix is ``.laz``) with 0.1 mm resolution by default.

    The offset is the cloud's minimum corner, so large georeferenced coordinates keep full resolution
    in LAS's 32-bit integers (a cloud may span up to 2^31 * scale = 214 km per axis).
    """
    import laspy

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    header = laspy.LasHeader(point_format=2 if colors is not None else 0, version="1.2")
    header.offsets = np.floor(points.min(axis=0)) if len(points) else np.zeros(3)
    header.scales = np.full(3, scale)
    if len(points) and np.any((points.max(axis=0) - header.offsets) / scale >= 2**31):
        raise ValueError(f"cloud too large for LAS at scale {scale} m; use a coarser scale")
    las = laspy.LasData(header)
    las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
    if intensity is not None:
        las.intensity = _intensity_u16(intensity)
    if colors is not None:
        rgb = np.asarray(colors, dtype=np.uint16).reshape(-1, 3) * 257  # 8 -> 16 bit, 255 -> 65535
        las.red, las.green, las.blue = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    las.write(str(path))


LAS_FORMAT = register_format(
    ScanFormat(
        name="las",
        suffixes=(".las", ".laz"),
        convention=CANONICAL,
        read=read_las,
        description="ASPRS LAS/LAZ, scaled coordinates (m, z up) + intensity",
    )
)
