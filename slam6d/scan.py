"""The unit of work: one 3D scan with its pose, and a sequence of them.

Points are held in the canonical frame (right-handed, metres, z up) in the scanner's own
coordinates; ``pose`` is ``world_from_scan``. The :class:`~slam6d.geometry.FrameConvention` of the
source travels with the sequence so results can be written back in the input's units and frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.geometry import CANONICAL, FrameConvention, Matrix, transform_points


@dataclass
class Scan:
    """One scan: points in its own frame plus the current estimate of where it sits in the world."""

    points: NDArray[np.float64]
    pose: Matrix = field(default_factory=lambda: np.eye(4))
    name: str = ""
    source: Path | None = None
    intensity: NDArray[np.float32] | None = None
    has_pose: bool = False  # False when the file carried no pose/odometry: the initial guess must search

    def __post_init__(self) -> None:
        self.points = np.ascontiguousarray(self.points, dtype=np.float64).reshape(-1, 3)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def world_points(self) -> NDArray[np.float64]:
        return transform_points(self.pose, self.points)


@dataclass
class ScanSequence:
    """Scans in acquisition order, as read from one source."""

    scans: list[Scan]
    convention: FrameConvention = CANONICAL
    source: Path | None = None
    format_name: str = ""

    def __len__(self) -> int:
        return len(self.scans)

    def __iter__(self):  # type: ignore[no-untyped-def]
        return iter(self.scans)

    def __getitem__(self, index: int) -> Scan:
        return self.scans[index]

    def poses(self) -> list[Matrix]:
        return [scan.pose.copy() for scan in self.scans]

    def native_poses(self) -> list[Matrix]:
        """Poses in the input's own units and frame, for writing results back."""
        return [self.convention.pose_to_native(scan.pose) for scan in self.scans]
