"""Trajectory files other tools read and write: KITTI 3x4, TUM, g2o pose graphs.

These are the hand-over points to evaluation tools (evo, KITTI devkit) and graph optimisers (g2o,
GTSAM), so the layouts follow those tools exactly. Poses are 4x4 ``world_from_scan`` in whatever
frame the caller passes; nothing here converts units or axes.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError
from slam6d.geometry import Matrix, make_pose, quaternion_to_rotation, rotation_to_quaternion
from slam6d.io.source import read_file_text
from slam6d.io.text import parse_numeric_rows, read_text_file

G2oEdge = tuple[int, int, Matrix, Matrix]  # (from, to, relative pose from->to, 6x6 information)


def _read_rows(path: Path, columns: tuple[int, ...]) -> tuple[NDArray[np.float64], str]:
    """Numeric rows and the raw text (kept to turn a row index back into a line number)."""
    path = Path(path)
    text = read_text_file(path, "pose lines")
    rows = parse_numeric_rows(path, text, allowed_columns=columns)
    if rows.shape[0] == 0:
        raise FormatError(path, "the file contains no poses")
    bad = np.flatnonzero(~np.isfinite(rows).all(axis=1))
    if bad.size:
        raise FormatError(path, "pose contains NaN or infinity", _line_of_row(path, text, int(bad[0])))
    return rows, text


def _line_of_row(path: Path, text: str, row: int) -> int:
    """1-based file line of the ``row``-th data row (blank and ``#`` lines do not count as rows)."""
    seen = -1
    for line_no, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            seen += 1
            if seen == row:
                return line_no
    raise FormatError(path, f"row {row} not found")


def _check_rotations(path: Path, text: str, rotations: NDArray[np.float64]) -> None:
    """Refuse matrices that are not rotations: a wrong column order would otherwise pass silently."""
    for index, rotation in enumerate(rotations):
        if np.abs(rotation @ rotation.T - np.eye(3)).max() > 1e-3 or np.linalg.det(rotation) < 0.0:
            raise FormatError(path, "the 3x3 part is not a rotation matrix", _line_of_row(path, text, index))


# ---------------------------------------------------------------- KITTI, TUM, 4x4


# a quaternion this short has no direction: normalising it would turn the pose into NaN
_MIN_QUATERNION_NORM = 1e-9
_ZERO_QUATERNION = "quaternion has zero length (no rotation)"


def _poses_from_rows(path: Path, text: str, rows: NDArray[np.float64]) -> list[Matrix]:
    """Interpret rows by their column count: 12 = KITTI 3x4, 8 = TUM, 16 = row-major 4x4."""
    if rows.shape[1] == 8:
        if (zero := np.flatnonzero(~(np.linalg.norm(rows[:, 4:8], axis=1) > _MIN_QUATERNION_NORM))).size:
            raise FormatError(path, _ZERO_QUATERNION, _line_of_row(path, text, int(zero[0])))
        return [make_pose(quaternion_to_rotation(r[[7, 4, 5, 6]]), r[1:4]) for r in rows]
    matrices = np.tile(np.eye(4), (rows.shape[0], 1, 1))
    if rows.shape[1] == 12:
        matrices[:, :3, :] = rows.reshape(-1, 3, 4)
    else:
        matrices = rows.reshape(-1, 4, 4).copy()
        for index, m in enumerate(matrices):
            if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
                raise FormatError(path, "last row of a 4x4 pose must be 0 0 0 1", _line_of_row(path, text, index))
    _check_rotations(path, text, matrices[:, :3, :3])
    return list(matrices)


def read_kitti_poses(path: Path | str) -> list[Matrix]:
    """KITTI odometry poses: one line per scan, 12 numbers = row-major 3x4 ``[R | t]``."""
    rows, text = _read_rows(Path(path), (12,))
    return _poses_from_rows(Path(path), text, rows)


def write_kitti_poses(path: Path | str, poses: Sequence[Matrix]) -> None:
    rows = np.array([np.asarray(p, dtype=np.float64)[:3, :].reshape(12) for p in poses]).reshape(-1, 12)
    np.savetxt(Path(path), rows, fmt="%.9e")


def read_tum(path: Path | str) -> tuple[NDArray[np.float64], list[Matrix]]:
    """TUM RGB-D trajectory: ``timestamp tx ty tz qx qy qz qw`` per line -> (timestamps, poses)."""
    rows, text = _read_rows(Path(path), (8,))
    return rows[:, 0].copy(), _poses_from_rows(Path(path), text, rows)


def write_tum_poses(
    path: Path | str, poses: Sequence[Matrix], timestamps: Sequence[float] | NDArray[np.float64] | None = None
) -> None:
    """Without timestamps the scan index stands in, which is what evo needs to associate by time."""
    stamps = np.arange(len(poses), dtype=np.float64) if timestamps is None else np.asarray(timestamps, np.float64)
    if stamps.shape != (len(poses),):
        raise ValueError(f"{len(stamps)} timestamps for {len(poses)} poses")
    with Path(path).open("w") as fh:
        for stamp, pose in zip(stamps, poses, strict=True):
            w, x, y, z = rotation_to_quaternion(np.asarray(pose)[:3, :3])
            t = pose[:3, 3]
            fh.write(f"{stamp:.6f} {t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {x:.12f} {y:.12f} {z:.12f} {w:.12f}\n")


def read_poses_file(path: Path | str) -> list[Matrix]:
    """Poses for ``--poses``: KITTI 3x4 (12 columns), TUM (8 columns) or row-major 4x4 (16 columns).

    The column count is unambiguous, so users can hand over whatever their odometry tool wrote.
    """
    rows, text = _read_rows(Path(path), (12, 8, 16))
    return _poses_from_rows(Path(path), text, rows)


# ---------------------------------------------------------------- g2o


def _se3_quat(pose: Matrix) -> str:
    w, x, y, z = rotation_to_quaternion(np.asarray(pose)[:3, :3])
    t = pose[:3, 3]
    return f"{t[0]:.9f} {t[1]:.9f} {t[2]:.9f} {x:.12f} {y:.12f} {z:.12f} {w:.12f}"


def write_g2o(path: Path | str, poses: Sequence[Matrix], edges: Sequence[G2oEdge], fixed: Sequence[int] = (0,)) -> None:
    """Pose graph as g2o's ``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT`` (what g2o_viewer and GTSAM's readG2o take).

    Information matrices are ordered (x, y, z, rx, ry, rz) - translation first - as g2o expects; only
    the upper triangle is written, row by row. ``fixed`` vertices get a ``FIX`` line (the gauge).
    """
    with Path(path).open("w") as fh:
        for index, pose in enumerate(poses):
            fh.write(f"VERTEX_SE3:QUAT {index} {_se3_quat(pose)}\n")
        for index in fixed:
            fh.write(f"FIX {index}\n")
        rows, cols = np.triu_indices(6)
        for i, j, relative, information in edges:
            info = np.asarray(information, dtype=np.float64)
            if info.shape != (6, 6):
                raise ValueError(f"edge {i}->{j}: information matrix must be 6x6, got {info.shape}")
            upper = " ".join(f"{v:.9g}" for v in info[rows, cols])
            fh.write(f"EDGE_SE3:QUAT {int(i)} {int(j)} {_se3_quat(relative)} {upper}\n")


def read_g2o(path: Path | str) -> tuple[list[Matrix], list[G2oEdge]]:
    """Vertices (in id order) and edges of a g2o SE3 file; other record types are ignored."""
    path = Path(path)
    lines = read_file_text(path, "g2o VERTEX_SE3:QUAT / EDGE_SE3:QUAT lines").splitlines()
    vertices: dict[int, Matrix] = {}
    edges: list[G2oEdge] = []
    rows, cols = np.triu_indices(6)
    for line_no, line in enumerate(lines, start=1):
        fields = line.split()
        if not fields or fields[0] not in ("VERTEX_SE3:QUAT", "EDGE_SE3:QUAT"):
            continue
        expected = 9 if fields[0] == "VERTEX_SE3:QUAT" else 31
        if len(fields) != expected:
            raise FormatError(path, f"{fields[0]} needs {expected - 1} values, found {len(fields) - 1}", line_no)
        id_count = 1 if fields[0] == "VERTEX_SE3:QUAT" else 2
        try:
            ids = [int(v) for v in fields[1 : 1 + id_count]]
        except ValueError:
            raise FormatError(path, "vertex ids must be integers", line_no) from None
        try:
            v = np.array([float(v) for v in fields[1 + id_count :]])
        except ValueError:
            raise FormatError(path, "not a number in the line", line_no) from None
        if not np.isfinite(v).all():
            raise FormatError(path, "NaN or infinity in the line", line_no)
        if not np.linalg.norm(v[3:7]) > _MIN_QUATERNION_NORM:
            raise FormatError(path, _ZERO_QUATERNION, line_no)
        pose = make_pose(quaternion_to_rotation(v[[6, 3, 4, 5]]), v[0:3])
        if id_count == 1:
            vertices[ids[0]] = pose
        else:
            info = np.zeros((6, 6))
            info[rows, cols] = v[7:]
            info[cols, rows] = v[7:]
            edges.append((ids[0], ids[1], pose, info))
    return [vertices[k] for k in sorted(vertices)], edges
