"""Files a user downloads from a session: trajectories for evaluation tools, the merged map.

Every file is written by the engine's own writers (:mod:`slam6d.io`) into a temporary file and
returned as bytes, so a download is byte-for-byte what ``slam6d`` writes on the command line:
maps through :func:`slam6d.io.map.write_map` (PLY, or LAS/LAZ at 0.1 mm with the overflow check
and the scans' intensity), poses through the KITTI/TUM/g2o/.frames writers. A g2o graph carries
each edge's information matrix from the scans' overlap (LUM's, as relaxation weighs the edge).
"""

from __future__ import annotations

import io
import tempfile
import zipfile
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from slam6d.errors import Slam6dError
from slam6d.geometry import FrameConvention, Matrix
from slam6d.io.frames import FrameType, write_sequence_frames
from slam6d.io.map import write_map
from slam6d.io.poses import write_g2o, write_kitti_poses, write_tum_poses
from slam6d.octree import reduce_points
from slam6d.posegraph import relative_pose
from slam6d.scan import ScanSequence
from slam6d.session_graph import graph_edge_list

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
    information: Sequence[Matrix] | None = None,
) -> tuple[bytes, str, str]:
    """(content, media type, file name). ``convention`` converts to the input's frame; None keeps canonical.

    ``information`` (g2o only): per edge of ``graph`` in :func:`slam6d.session_graph.graph_edge_list`'s
    order, the canonical-frame information matrix; identity where it is not given.
    """
    native = [convention.pose_to_native(p) for p in poses] if convention is not None else [np.asarray(p) for p in poses]
    if format_name == "kitti":
        return _written(lambda p: write_kitti_poses(p, native), ".txt"), "text/plain", "poses_kitti.txt"
    if format_name == "tum":
        return _written(lambda p: write_tum_poses(p, native), ".txt"), "text/plain", "poses_tum.txt"
    if format_name == "g2o":
        listed = graph_edge_list(len(native), graph or {})
        infos = list(information) if information is not None else [np.eye(6)] * len(listed)
        if convention is not None:
            infos = [convention.information_to_native(info) for info in infos]
        edges = [
            (e["i"], e["j"], relative_pose(native[e["i"]], native[e["j"]]), info)
            for e, info in zip(listed, infos, strict=True)
        ]
        return _written(lambda p: write_g2o(p, native, edges), ".g2o"), "text/plain", "graph.g2o"
    if format_name == "frames":
        if convention is None:
            raise Slam6dError("3DTK .frames are always in the input's own frame")
        buffer = io.BytesIO()
        with tempfile.TemporaryDirectory() as tmp, zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
            histories = [[(p, FrameType.ICP)] for p in poses]
            for path in write_sequence_frames(tmp, histories, convention, names):
                archive.write(path, path.name)
        return buffer.getvalue(), "application/zip", "frames.zip"
    raise Slam6dError(f"unknown pose format '{format_name}'; known: {', '.join(POSE_FORMATS)}")


def merged_points(sequence: ScanSequence, voxel_size: float = 0.0) -> tuple[np.ndarray, np.ndarray | None]:
    """All scans in world coordinates (float64), each reduced to one point per voxel first, with their
    intensity when every scan has one (else None)."""
    parts, intensities = [], []
    for scan in sequence.scans:
        keep = np.arange(len(scan.points)) if voxel_size <= 0 else reduce_points(scan.points, voxel_size)
        parts.append(scan.points[keep] @ scan.pose[:3, :3].T + scan.pose[:3, 3])
        intensities.append(None if scan.intensity is None else np.asarray(scan.intensity)[keep])
    points = np.concatenate(parts)
    if any(i is None for i in intensities):
        return points, None
    return points, np.concatenate([i for i in intensities if i is not None])


def export_map(
    sequence: ScanSequence, format_name: str, folder: Path, voxel_size: float = 0.0
) -> tuple[Path, str, str]:
    """(file in ``folder``, media type, download name) of the merged map, written by
    :func:`slam6d.io.map.write_map`. A file, not bytes: a map of millions of points is streamed
    from disk rather than held in memory once more for the answer."""
    if format_name not in MAP_FORMATS:
        raise Slam6dError(f"unknown map format '{format_name}'; known: {', '.join(MAP_FORMATS)}")
    points, intensity = merged_points(sequence, voxel_size)
    path = Path(folder) / f"map.{format_name}"
    write_map(path, points, intensity=intensity)
    return path, "application/octet-stream", path.name
