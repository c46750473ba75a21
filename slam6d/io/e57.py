"""ASTM E57 files (via pye57): each file becomes one scan.

A file holding several scans (a terrestrial scanner's station set) is merged into the frame of its
first scan, using each scan's stored pose; the first scan's pose becomes the scan's pose. That
keeps the one-file-one-scan model of the rest of the pipeline while losing no points. Spherical
records are converted to Cartesian; points flagged invalid are dropped. Metres, right-handed, z up.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.geometry import Matrix, invert, make_pose, rotation_to_quaternion, transform_points
from slam6d.io.registry import CloudData, ScanFormat, register_format
from slam6d.io.source import check_regular_file


def _scan_points(e57, index: int) -> tuple[NDArray[np.float64], NDArray[np.float32] | None]:  # type: ignore[no-untyped-def]
    data = e57.read_scan(index, intensity=True, transform=False, ignore_missing_fields=True)
    if "cartesianX" in data:
        points = np.stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]], axis=1)
    elif "sphericalRange" in data:
        r, az, el = data["sphericalRange"], data["sphericalAzimuth"], data["sphericalElevation"]
        points = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], axis=1)
    else:
        raise ValueError(f"scan {index} has neither Cartesian nor spherical coordinates")
    intensity = np.asarray(data["intensity"], dtype=np.float32) if "intensity" in data else None
    return np.asarray(points, dtype=np.float64).reshape(-1, 3), intensity


def _scan_pose(header) -> Matrix | None:  # type: ignore[no-untyped-def]
    if not header.has_pose():
        return None
    return make_pose(np.asarray(header.rotation_matrix, dtype=np.float64), np.asarray(header.translation))


def read_e57(path: Path) -> CloudData:
    """ASTM E57 (all scans of a file merged into the first's frame; stored pose used), metres"""
    import pye57

    check_regular_file(path)
    try:
        e57 = pye57.E57(str(path))
        try:
            count = e57.scan_count
            if count == 0:
                return CloudData(np.empty((0, 3)))
            poses = [_scan_pose(e57.get_header(i)) for i in range(count)]
            clouds = [_scan_points(e57, i) for i in range(count)]
        finally:
            e57.close()
    except (pye57.libe57.E57Exception, RuntimeError, ValueError, KeyError, OSError) as exc:
        raise FormatError(path, f"cannot read as E57 ({type(exc).__name__})") from None
    reference = poses[0]
    to_first = invert(reference if reference is not None else np.eye(4))
    parts: list[NDArray[np.float64]] = []
    intensities: list[NDArray[np.float32] | None] = []
    for index, ((points, intensity), pose) in enumerate(zip(clouds, poses, strict=True)):
        if index > 0:  # a scan without a pose sits at the file's origin
            points = transform_points(to_first @ (pose if pose is not None else np.eye(4)), points)
        parts.append(points)
        intensities.append(intensity)
    known = [i for i in intensities if i is not None]
    merged_intensity = np.concatenate(known) if len(known) == len(intensities) else None
    return CloudData(np.concatenate(parts), merged_intensity, reference)


def write_e57(
    path: Path | str,
    points: NDArray[np.float64],
    intensity: NDArray[np.floating] | None = None,
    pose: Matrix | None = None,
) -> None:
    """One Cartesian scan, with its pose when given (what laser-scanning software imports as a station)."""
    import pye57

    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0 or not np.isfinite(points).all():
        raise ValueError("E57 scans written here need at least one point and finite coordinates")
    data: dict[str, NDArray] = {"cartesianX": points[:, 0], "cartesianY": points[:, 1], "cartesianZ": points[:, 2]}
    if intensity is not None:
        data["intensity"] = np.asarray(intensity, dtype=np.float64).reshape(-1)
    kwargs = {}
    if pose is not None:
        kwargs = {"rotation": rotation_to_quaternion(pose[:3, :3]), "translation": np.asarray(pose[:3, 3])}
    e57 = pye57.E57(str(path), mode="w")
    try:
        e57.write_scan_raw(data, **kwargs)
    finally:
        e57.close()


E57_FORMAT = register_format(ScanFormat("e57", read_e57))
