"""An in-memory simulated loop (the project's own simulator, no files) for fast pipeline tests."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from slam6d.geometry import Matrix
from slam6d.scan import Scan, ScanSequence
from slam6d.simulate import (
    SimulationConfig,
    build_scene,
    drifting_odometry,
    ground_truth_poses,
    scan_pattern,
    simulate_scan,
)


@dataclass
class SimulatedLoop:
    sequence: ScanSequence  # scans carry the drifting odometry as their poses
    truth: list[Matrix]
    odometry: list[Matrix]


def simulated_loop(
    scans: int = 12, points: int = 8000, seed: int = 3, first: int | None = None, **overrides: float
) -> SimulatedLoop:
    """``first`` keeps only the first scans of the loop (the path still has ``scans`` stops)."""
    config = SimulationConfig(seed=seed, scans=scans, points_per_scan=points, **overrides)  # type: ignore[arg-type]
    rng = np.random.default_rng(config.seed)
    scene = build_scene(config, rng)
    truth = ground_truth_poses(config, scene)
    odometry = drifting_odometry(config, truth, rng)
    truth, odometry = truth[:first], odometry[:first]
    directions = scan_pattern(config)
    clouds = [simulate_scan(config, scene, pose, directions, rng) for pose in truth]
    sequence = ScanSequence(
        [
            Scan(c, o.copy(), name=f"scan{k:03d}", has_pose=True)
            for k, (c, o) in enumerate(zip(clouds, odometry, strict=True))
        ]
    )
    return SimulatedLoop(sequence, truth, odometry)
