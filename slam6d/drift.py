"""Drifting odometry made from a reference trajectory, for testing the pipeline on real scans.

Real sequences come with a good reference but no independent odometry. Chaining the reference's
relative motions with per-step noise gives the kind of start a robot's dead reckoning gives: each
step's translation is perturbed by a fraction of its length per axis and its yaw by a small
angle, so the error grows with distance travelled. The generator is seeded, so a test and a
benchmark see the same odometry.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise

import numpy as np

from slam6d.geometry import Matrix, invert, make_pose, rot_z


def drifted_odometry(
    reference: Sequence[Matrix],
    seed: int = 1,
    translation_fraction: float = 0.01,
    yaw_deg: float = 0.3,
) -> list[Matrix]:
    """Chain the reference's steps from its first pose, each with noise: N(0, fraction·|step|) per
    axis on the translation and N(0, yaw_deg) on the yaw, applied in the step's own frame."""
    rng = np.random.default_rng(seed)
    odometry = [np.array(reference[0], dtype=np.float64)]
    for previous, current in pairwise(reference):
        step = invert(previous) @ current
        length = float(np.linalg.norm(step[:3, 3]))
        noise_t = rng.normal(0.0, translation_fraction * length, 3)
        noise_yaw = np.radians(rng.normal(0.0, yaw_deg))
        noisy = make_pose(step[:3, :3] @ rot_z(noise_yaw), step[:3, 3] + noise_t)
        odometry.append(odometry[-1] @ noisy)
    return odometry
