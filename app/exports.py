"""Files a user downloads from a session: trajectories for evaluation tools, the merged map.

Everything is produced into memory (the server streams it back) by the engine's own writers, so
a download is byte-for-byte what ``slam6d`` would write on the command line.
"""

from __future__ import annotations

import io
import tempfile
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from app.editing.graph import graph_edge_list
from slam6d.geometry import FrameConvention, Matrix
from slam6d.io.frames import FrameType, write_sequence_frames
from slam6d.io.ply import write_ply
from slam6d.io.poses import write_g2o, write_kitti_poses, write_tum_poses
from slam6d.octree import reduce_points
from slam6d.posegraph import relative_pose
from slam6d.scan import ScanSequence

POSE_FORMATS = ("kitti", "tum", "frames", "g2o")
MAP_FORMATS = ("ply", "laz")


def _written(write: Callable[[Path], Any], suffix: str) -> bytes:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"out{suffix}"
        write(path)
        return path.read_bytes()


def export_poses(
    poses: Sequence[Matrix],
    format_name: str,
    convention: FrameConvention | None,
    graph: dict[str, Any] | None = None,
    names: Sequence[str] | None = None,
) -> tuple[bytes, str, str]:
    """(content, media type, file name). ``convention`` converts to the input's frame; None keeps canonical."""
    native = [convention.pose_to_native(p) for p in poses] if convention is not None else [np.asarray(p) for p in poses]
    if format_name == "kitti":
        return _written(lambda p: write_kitti_poses(p, native), ".txt"), "text/plain", "poses_kitti.txt"
    if format_name == "tum":
        return _written(lambda p: write_tum_poses(p, native), ".txt"), "text/plain", "poses_tum.txt"
    if format_name == "g2o":
        edges = [
            (e["i"], e["j"], relative_pose(native[e["i"]], native[e["j"]]), np.eye(6))
            for e in graph_edge_list(len(native), graph or {})
        ]
        return _written(lambda p: write_g2o(p, native, edges), ".g2o"), "text/plain", "graph.g2o"
    if format_name == "frames":
        if convention is None:
            raise ValueError("3DTK .frames are always in the input's own frame")
        buffer = io.BytesIO()
        with tempfile.TemporaryDirectory() as tmp, zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
            histories = [[(p, FrameType.ICP)] for p in poses]
            for path in write_sequence_frames(tmp, histories, convention, names):
                archive.write(path, path.name)
        return buffer.getvalue(), "application/zip", "frames.zip"
    raise ValueError(f"unknown pose format '{format_name}'; known: {', '.join(POSE_FORMATS)}")


def merged_points(sequence: ScanSequence, voxel_size: float = 0.0) -> np.ndarray:
    """All scans in world coordinates (float64), each reduced to one point per voxel first."""
    parts = []
    for scan in sequence.scans:
        local = scan.points if voxel_size <= 0 else scan.points[reduce_points(scan.points, voxel_size)]
        parts.append(local @ scan.pose[:3, :3].T + scan.pose[:3, 3])
    return np.concatenate(parts)


def export_map(sequence: ScanSequence, format_name: str, voxel_size: float = 0.0) -> tuple[bytes, str, str]:
    points = merged_points(sequence, voxel_size)
    if format_name == "ply":
        return _written(lambda p: write_ply(p, points), ".ply"), "application/octet-stream", "map.ply"
    if format_name == "laz":
        import laspy

        def write_laz(path: Path) -> None:
            header = laspy.LasHeader(point_format=0, version="1.2")
            header.offsets = points.min(axis=0)
            header.scales = np.array([0.001, 0.001, 0.001])  # millimetres, as survey LAS files use
            las = laspy.LasData(header)
            las.x, las.y, las.z = points[:, 0], points[:, 1], points[:, 2]
            las.write(str(path))

        return _written(write_laz, ".laz"), "application/octet-stream", "map.laz"
    raise ValueError(f"unknown map format '{format_name}'; known: {', '.join(MAP_FORMATS)}")
