"""Writing the merged map: binary PLY for viewers (CloudCompare, MeshLab, Open3D), LAS/LAZ for GIS tools.

The suffix picks the format so a user states the output once (``--out map.laz``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.io.las import write_las
from slam6d.io.ply import write_ply

MAP_SUFFIXES = (".ply", ".las", ".laz")


def write_map(
    path: Path | str,
    points: NDArray[np.float64],
    colors: NDArray[np.uint8] | None = None,
    intensity: NDArray[np.floating] | None = None,
) -> Path:
    """Write canonical-frame points (metres) with optional 8-bit RGB colours and intensity."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MAP_SUFFIXES:
        raise FormatError(path, f"cannot write a map as '{suffix}'; use one of {', '.join(MAP_SUFFIXES)}")
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    for name, values, width in (("colors", colors, 3), ("intensity", intensity, 1)):
        if values is not None and np.asarray(values).reshape(len(points), -1).shape[1] != width:
            raise ValueError(f"{name} must have {width} value(s) per point")
    finite = np.isfinite(points).all(axis=1)
    if not finite.all():  # never write NaN into a map file: viewers and LAS cannot cope
        points = points[finite]
        colors = None if colors is None else np.asarray(colors)[finite]
        intensity = None if intensity is None else np.asarray(intensity)[finite]
    path.parent.mkdir(parents=True, exist_ok=True)
    if suffix == ".ply":
        write_ply(path, points, colors=colors, intensity=intensity, binary=True)
    else:
        write_las(path, points, colors=colors, intensity=intensity)
    return path
