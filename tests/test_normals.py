"""Plane normals on multi-beam ring scans: the ground a spinning lidar sees must give level normals.

A VLP-16 on a car sees the ground as rings 1-3 m apart (its lowest beam meets the ground ~7 m
out), so a 0.4 m cube of the ground holds a single ring: a line. With range noise (3 cm) the line
widens along the beams and passed the planarity test; its "plane" contains the beam, so its normal
leaned by the beam's depression angle (5-15°) and pulled the registrations' roll and pitch
(slam6d.normals, docs/scale.md "Roll and pitch on the campus").
"""

from __future__ import annotations

import numpy as np
import pytest

from slam6d.geometry import invert, rotation_angle
from slam6d.icp import ICPConfig, icp
from slam6d.model import ModelIndex
from slam6d.normals import cell_normals
from slam6d.octree import reduce_points
from slam6d.simulate import SimulationConfig, simulated_scans

SENSOR_HEIGHT = 1.8  # metres, a car's roof


def ring_ground(noise: float, seed: int = 0) -> np.ndarray:
    """The flat ground as a VLP-16's lower beams (-15° to -1°, every 2°, 0.2° apart in azimuth)
    see it from ``SENSOR_HEIGHT``, with Gaussian range noise, reduced to 0.1 m as the pipeline does."""
    rng = np.random.default_rng(seed)
    elevation, azimuth = np.meshgrid(np.radians(np.arange(-15.0, -0.9, 2.0)), np.radians(np.arange(0, 360, 0.2)))
    directions = np.stack(
        [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)], axis=-1
    ).reshape(-1, 3)
    ranges = SENSOR_HEIGHT / -directions[:, 2]
    keep = ranges < 40.0
    points = directions[keep] * (ranges[keep] + rng.normal(0.0, noise, int(keep.sum())))[:, None]
    return points[reduce_points(points, 0.1)]


def test_ring_ground_gives_level_cube_normals() -> None:
    """Every usable normal of the ring-sampled ground is level, and a useful share of it has one
    (the larger cubes span two rings); a single noisy ring gives none."""
    for noise in (0.0, 0.03):
        normals, usable = cell_normals(ring_ground(noise), 0.4)
        tilt = np.degrees(np.arccos(np.clip(np.abs(normals[usable, 2]), 0.0, 1.0)))
        assert usable.mean() > 0.2, usable.mean()
        assert np.percentile(tilt, 95) < 1.0, np.percentile(tilt, 95)
    ring = ring_ground(0.03)
    one_ring = ring[np.abs(np.linalg.norm(ring[:, :2], axis=1) - 12.0) < 0.5]  # the ring ~12 m out
    assert not cell_normals(one_ring, 0.4)[1].any()


@pytest.mark.slow  # 25 simulated campus scans and 24 matches: about a minute on a loaded machine
@pytest.mark.xfail(
    strict=True,
    reason="the k-NN fallback normals along single rings still tilt the match (0.06° with true surface normals)",
)
def test_ring_scan_registration_keeps_roll_and_pitch() -> None:
    """Consecutive VLP-16 scans of the simulated campus matched from their true relative pose, as
    sequential registration matches them (0.1 m model, 0.2 m plane sample, 0.4 m cubes, 0.35 m data
    points): the match should stay level. With single 0.4 m cubes and the k-NN fallback the steps
    tilted by 0.37° RMS over these pairs; the larger cubes alone change little, since the fallback
    serves half the pairs; without the fallback they tilt under 0.25°, with the simulator's true
    surface normals 0.06°. Expected to fail until the fallback is replaced."""
    simulation = simulated_scans(SimulationConfig(seed=3, scans=25, points_per_scan=20000, world="campus"))
    clouds = [cloud[reduce_points(cloud, 0.1)] for cloud in simulation.scans()]
    config = ICPConfig(data_voxel_size=0.35, epsilon=1e-3)
    tilts = []
    for k in range(1, len(clouds)):
        model = ModelIndex(clouds[k - 1], normal_voxel_size=0.2, normal_cell=0.4)
        truth = invert(simulation.truth[k - 1]) @ simulation.truth[k]
        error = invert(truth) @ icp(model, clouds[k], truth, config).transform
        tilts.append(np.degrees(rotation_angle(error[:3, :3])))
    rms = float(np.sqrt(np.mean(np.square(tilts))))
    assert rms < 0.25, (rms, tilts)
