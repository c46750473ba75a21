"""Picking: which scan is under a click in the 3D view, tested on the points as displayed.

Closeness is measured as an angle from the camera, which is what "under the cursor" means on
screen whatever the distance; a scan in front hides the one behind it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from app.view.core import ShownScans, ViewContext
from slam6d.geometry import Matrix


def pick_scan(
    clouds: Sequence[NDArray[np.floating]],
    poses: Sequence[Matrix],
    origin: Sequence[float],
    direction: Sequence[float],
    tolerance: float = 0.02,
    slack: float = 0.004,
) -> int | None:
    """The scan a click ray hits: whose displayed points lie nearest the ray, in front of the camera.

    Closeness is the angle (radians) between the ray and the direction to a point as seen from the
    ray's origin, which is what "under the cursor" means on screen whatever the distance. Of the
    points within ``slack`` of the best angle (about a drawn point's size), the nearest to the camera
    wins, so a scan in front hides the one behind it. None when no point is within ``tolerance``.
    Each scan's ray is moved into the scan's own frame (the displayed points are stored there), so
    nothing is transformed per point.
    """
    ray_origin = np.asarray(origin, dtype=np.float64)
    ray_dir = np.asarray(direction, dtype=np.float64)
    ray_dir = ray_dir / np.linalg.norm(ray_dir)
    best: list[tuple[float, float, int]] = []  # per scan: (angle, depth) of its points near the best angle
    for k, (cloud, pose) in enumerate(zip(clouds, poses, strict=True)):
        if not len(cloud):
            continue
        rotation = pose[:3, :3]
        o = rotation.T @ (ray_origin - pose[:3, 3])
        d = rotation.T @ ray_dir
        rel = np.asarray(cloud, dtype=np.float64) - o
        depth = rel @ d
        across = np.sqrt(np.maximum(np.einsum("ij,ij->i", rel, rel) - depth**2, 0.0))
        angle = np.where(depth > 1e-6, np.arctan2(across, np.maximum(depth, 1e-6)), np.inf)
        nearest = float(angle.min())
        if nearest > tolerance:
            continue
        close = angle <= nearest + slack
        best.append((nearest, float(depth[close].min()), k))
    if not best:
        return None
    best_angle = min(b[0] for b in best)
    return min((b for b in best if b[0] <= best_angle + slack), key=lambda b: b[1])[2]


class Picking:
    def __init__(self, view: ViewContext, scans: ShownScans) -> None:
        self.view = view
        self.scans = scans

    def pick(self, ray_origin: Any, ray_direction: Any) -> int | None:
        """The scan under a click: tested on the displayed points at the poses shown."""
        with self.view.lock:
            return pick_scan(self.scans.local, self.scans.poses, ray_origin, ray_direction)
