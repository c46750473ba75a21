"""Whole-trajectory benchmark: `slam6d run` stages on a simulated loop and on BALM hall.

Prints wall times, ATE against ground truth (simulated), RPE against the reference and ICP
self-consistency on far-apart overlapping scan pairs (BALM hall, started from drifted odometry
made by :func:`slam6d.drift.drifted_odometry`). Peers (small_gicp, open3d, KISS-ICP) are not
wired in yet. Run: ``.venv/bin/python benchmarks/trajectory.py [--balm] [--sim DIR]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from slam6d.drift import drifted_odometry
from slam6d.geometry import UOS, invert, transform_points
from slam6d.icp import ICPConfig, ModelIndex, icp
from slam6d.io.poses import read_kitti_poses
from slam6d.io.registry import read_sequence
from slam6d.metrics import absolute_trajectory_error, relative_pose_error
from slam6d.octree import reduce_points
from slam6d.pipeline import Pipeline, PipelineConfig

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
CHECK_PAIRS = ((0, 88), (10, 88), (0, 60), (57, 88), (5, 80), (20, 70), (30, 60))


def self_consistency(sequence, poses, pairs=CHECK_PAIRS) -> dict[tuple[int, int], float]:  # type: ignore[no-untyped-def]
    """Mean point displacement when ICP re-matches far-apart scan pairs starting from ``poses`` (metres)."""
    moved = {}
    for i, j in pairs:
        model = sequence[i].points[reduce_points(sequence[i].points, 0.05)]
        data = sequence[j].points[reduce_points(sequence[j].points, 0.1)]
        start = invert(poses[i]) @ poses[j]
        result = icp(ModelIndex(model), data, start, ICPConfig(max_distance=0.3, max_iterations=60))
        moved[(i, j)] = float(
            np.linalg.norm(transform_points(result.transform, data) - transform_points(start, data), axis=1).mean()
        )
    return moved


def balm() -> None:
    began = time.perf_counter()
    sequence = read_sequence(DATA / "balm_hall" / "velodyne_style_bin", "kitti")
    reference = read_kitti_poses(DATA / "balm_hall" / "poses_subset_kitti3x4.txt")
    for scan, pose in zip(sequence, drifted_odometry(reference, seed=1), strict=True):
        scan.pose = pose
        scan.has_pose = True
    read = time.perf_counter() - began
    pipeline = Pipeline(sequence, PipelineConfig())
    report = pipeline.run()
    total = time.perf_counter() - began
    rpe = relative_pose_error(pipeline.poses, reference)
    moved = self_consistency(sequence, pipeline.poses)
    print(f"balm_hall: read {read:.2f}s, total {total:.2f}s, stages {report.stage_seconds}")
    print(f"  loops closed {report.loops_closed}, chi2 {report.chi2_before} -> {report.chi2_after}")
    print(f"  RPE {100 * rpe.translation_mean:.2f} cm / {rpe.rotation_mean_deg:.3f} deg (mean)")
    print("  self-consistency (cm): " + ", ".join(f"{i}-{j} {100 * v:.2f}" for (i, j), v in moved.items()))
    print(f"  mean {100 * np.mean(list(moved.values())):.2f} cm")


def simulated(directory: Path) -> None:
    began = time.perf_counter()
    sequence = read_sequence(directory, "uos")
    pipeline = Pipeline(sequence, PipelineConfig())
    report = pipeline.run()
    total = time.perf_counter() - began
    truth = [UOS.pose_to_canonical(p) for p in read_kitti_poses(directory / "ground_truth_kitti.txt")]
    ate = absolute_trajectory_error(pipeline.poses, truth)
    print(f"simulated {directory}: {len(sequence)} scans, total {total:.2f}s, stages {report.stage_seconds}")
    print(f"  ATE {100 * ate.rmse:.2f} cm, loops closed {report.loops_closed}")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--balm", action="store_true")
    parser.add_argument("--sim", type=Path)
    args = parser.parse_args()
    if args.sim:
        simulated(args.sim)
    if args.balm:
        balm()


if __name__ == "__main__":
    main()
