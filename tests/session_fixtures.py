"""Small synthetic uos sessions for the session-store, API and browser tests.

A corridor of boxes seen from a few poses along a path, written with the real uos writer, so
reading goes through the same code as real data.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from slam6d.geometry import UOS, pose_from_xyzrpy
from slam6d.io.uos import write_uos_scan


def corridor_points(rng: np.random.Generator, count: int) -> np.ndarray:
    """Points on the walls and floor of a 20 m x 4 m corridor with a few pillars (canonical, metres)."""
    kind = rng.integers(0, 4, count)
    x = rng.uniform(-2.0, 22.0, count)
    y = np.where(kind == 0, -2.0, np.where(kind == 1, 2.0, rng.uniform(-2.0, 2.0, count)))
    z = np.where(kind == 2, 0.0, rng.uniform(0.0, 2.5, count))
    pillar = kind == 3
    px = np.round(x[pillar] / 4.0) * 4.0
    angle = rng.uniform(0, 2 * np.pi, pillar.sum())
    x[pillar] = px + 0.2 * np.cos(angle)
    y[pillar] = 0.2 * np.sin(angle)
    return np.column_stack([x, y, z])


def true_poses(scans: int) -> list[np.ndarray]:
    return [pose_from_xyzrpy(2.0 * k, 0.1 * np.sin(k), 0.0, 0.0, 0.0, 0.05 * k) for k in range(scans)]


def write_corridor_scans(
    folder: Path, scans: int = 4, points: int = 3000, seed: int = 0, odometry_noise: float = 0.0
) -> None:
    """Write ``scans`` uos scans of the corridor; odometry poses are the true ones plus noise."""
    rng = np.random.default_rng(seed)
    world = corridor_points(rng, points * scans)
    for k, pose in enumerate(true_poses(scans)):
        chosen = world[rng.choice(len(world), points, replace=False)]
        local = (chosen - pose[:3, 3]) @ pose[:3, :3]
        odometry = pose.copy()
        odometry[:2, 3] += rng.normal(0.0, odometry_noise, 2)
        write_uos_scan(folder, k, UOS.points_to_native(local), UOS.pose_to_native(odometry))


def corridor_session(
    sessions_root: Path, scans: int, points: int, odometry_noise: float = 0.0, engine: dict | None = None
) -> Path:
    """A ``corridor`` session folder in ``sessions_root`` over freshly written corridor scans."""
    from slam6d.session import Session

    folder = sessions_root / "corridor"
    write_corridor_scans(folder / "scans", scans=scans, points=points, odometry_noise=odometry_noise)
    Session.create(folder, "Corridor", "scans", engine=engine)
    return folder


def write_loop_scans(folder: Path, scans: int = 8, points: int = 6000, seed: int = 1) -> list[np.ndarray]:
    """A small simulated loop (drifting odometry as the files' poses); returns the true poses.

    The robot comes back to its start, so the last scans are loop hypotheses against the first.
    """
    from tests.simulated_loop import simulated_loop

    sim = simulated_loop(scans=scans, points=points, seed=seed, loop_length=16.0, loop_width=10.0)
    for k, scan in enumerate(sim.sequence.scans):
        write_uos_scan(folder, k, UOS.points_to_native(scan.points), UOS.pose_to_native(scan.pose))
    return sim.truth
