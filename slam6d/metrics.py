"""Trajectory accuracy against a reference: absolute (ATE) and relative (RPE) pose error.

ATE says how far the estimated positions are from the reference after the best rigid alignment
(Horn/Umeyama without scale): SLAM output lives in its own world frame, so without alignment a
perfect trajectory anchored differently would look wrong. RPE compares motions between scans
``delta`` apart and so measures local drift independently of where errors accumulated. Lengths
come out in the units of the inputs (metres in the canonical frame, cm for native uos poses).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import FormatError, Slam6dError
from slam6d.geometry import Matrix, invert, make_pose, pose_difference

Poses = Sequence[Matrix] | NDArray[np.float64]


class TrajectoryMismatchError(Slam6dError):
    """Two trajectories cannot be compared pose by pose (different lengths, too few poses)."""


@dataclass
class AbsoluteTrajectoryError:
    """Position error statistics after (optional) rigid alignment of estimate onto reference."""

    rmse: float
    mean: float
    median: float
    max: float
    count: int
    aligned: bool
    # reference_from_estimate: the rigid transform applied to the estimate before comparing.
    alignment: Matrix = field(default_factory=lambda: np.eye(4))
    errors: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))  # per pose, for plots


@dataclass
class RelativePoseError:
    """Error of the motion between poses ``delta`` apart (translation in input units, rotation in degrees)."""

    delta: int
    count: int
    translation_rmse: float
    translation_mean: float
    translation_max: float
    rotation_rmse_deg: float
    rotation_mean_deg: float
    rotation_max_deg: float


@dataclass
class TrajectoryEvaluation:
    ate: AbsoluteTrajectoryError
    rpe: RelativePoseError


def _as_pose_array(poses: Poses, name: str) -> NDArray[np.float64]:
    array = np.asarray(poses, dtype=np.float64)
    if array.ndim != 3 or array.shape[1:] != (4, 4):
        raise TrajectoryMismatchError(f"{name}: expected a sequence of 4x4 poses, got shape {array.shape}")
    return array


def _check_pair(estimate: Poses, reference: Poses) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    est = _as_pose_array(estimate, "estimate")
    ref = _as_pose_array(reference, "reference")
    if len(est) != len(ref):
        raise TrajectoryMismatchError(f"estimate has {len(est)} poses but reference has {len(ref)}")
    if len(est) == 0:
        raise TrajectoryMismatchError("no poses to compare")
    return est, ref


def rigid_alignment(source: NDArray[np.float64], target: NDArray[np.float64]) -> Matrix:
    """Rigid transform T minimising sum |T·source_i - target_i|² (Umeyama without scale).

    With fewer than three non-collinear points the rotation is not determined; the SVD then still
    returns a valid rotation (one of the minimisers), which is what a comparison needs.
    """
    source = np.asarray(source, dtype=np.float64).reshape(-1, 3)
    target = np.asarray(target, dtype=np.float64).reshape(-1, 3)
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    covariance = (target - mu_t).T @ (source - mu_s)
    u, _, vt = np.linalg.svd(covariance)
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(u @ vt)) or 1.0  # keep a proper rotation, never a reflection
    rotation = u @ d @ vt
    return make_pose(rotation, mu_t - rotation @ mu_s)


def absolute_trajectory_error(estimate: Poses, reference: Poses, align: bool = True) -> AbsoluteTrajectoryError:
    est, ref = _check_pair(estimate, reference)
    est_t, ref_t = est[:, :3, 3], ref[:, :3, 3]
    alignment = rigid_alignment(est_t, ref_t) if align else np.eye(4)
    moved = est_t @ alignment[:3, :3].T + alignment[:3, 3]
    errors = np.linalg.norm(moved - ref_t, axis=1)
    return AbsoluteTrajectoryError(
        rmse=float(np.sqrt(np.mean(errors**2))),
        mean=float(errors.mean()),
        median=float(np.median(errors)),
        max=float(errors.max()),
        count=len(errors),
        aligned=align,
        alignment=alignment,
        errors=errors,
    )


def relative_pose_error(estimate: Poses, reference: Poses, delta: int = 1) -> RelativePoseError:
    est, ref = _check_pair(estimate, reference)
    if delta < 1:
        raise TrajectoryMismatchError(f"RPE delta must be at least 1, got {delta}")
    if len(est) <= delta:
        raise TrajectoryMismatchError(f"RPE with delta {delta} needs more than {delta} poses, got {len(est)}")
    translations, angles = [], []
    for i in range(len(est) - delta):
        est_motion = invert(est[i]) @ est[i + delta]
        ref_motion = invert(ref[i]) @ ref[i + delta]
        dt, dr = pose_difference(est_motion, ref_motion)
        translations.append(dt)
        angles.append(np.degrees(dr))
    t, r = np.array(translations), np.array(angles)
    return RelativePoseError(
        delta=delta,
        count=len(t),
        translation_rmse=float(np.sqrt(np.mean(t**2))),
        translation_mean=float(t.mean()),
        translation_max=float(t.max()),
        rotation_rmse_deg=float(np.sqrt(np.mean(r**2))),
        rotation_mean_deg=float(r.mean()),
        rotation_max_deg=float(r.max()),
    )


def evaluate_trajectory(estimate: Poses, reference: Poses, align: bool = True, delta: int = 1) -> TrajectoryEvaluation:
    return TrajectoryEvaluation(
        absolute_trajectory_error(estimate, reference, align), relative_pose_error(estimate, reference, delta)
    )


def evaluate_pose_files(
    estimate_path: Path, reference_path: Path, align: bool = True, delta: int = 1
) -> TrajectoryEvaluation:
    """Compare two KITTI pose files (3x4 row-major per line) scan by scan, in the files' own units."""
    from slam6d.io.poses import read_kitti_poses

    estimate = read_kitti_poses(Path(estimate_path))
    reference = read_kitti_poses(Path(reference_path))
    if len(estimate) != len(reference):
        raise FormatError(
            estimate_path,
            f"{len(estimate)} poses, but the reference {reference_path} has {len(reference)}; "
            "both files need one line per scan",
        )
    if len(estimate) <= delta:
        raise FormatError(estimate_path, f"{len(estimate)} poses: RPE with delta {delta} needs at least {delta + 1}")
    return evaluate_trajectory(estimate, reference, align, delta)
