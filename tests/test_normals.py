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

from slam6d.geometry import invert, make_pose, rotation_angle
from slam6d.icp import ICPConfig, icp
from slam6d.model import ModelIndex, fused_model
from slam6d.normals import cell_normals
from slam6d.octree import reduce_points
from slam6d.pipeline import FUSE_BELOW_CUBE_SHARE, PipelineConfig
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
def test_ring_scan_registration_keeps_roll_and_pitch() -> None:
    """Consecutive VLP-16 scans of the simulated campus matched from their true relative pose, as
    sequential registration matches them (the metascan of the last scans fused into one model:
    0.1 m points, 0.2 m plane sample, 0.4-3.2 m cubes with the k-NN fallback; 0.35 m data points):
    the match must stay level. Against the previous scan alone the steps tilted by 0.37° RMS over
    these pairs (0.06° with the simulator's true surface normals): most pairs lie on crowns, poles
    and corners, whose normals fitted to one or two rings are tens of degrees off, and pair across
    rings (slam6d.model.fused_model)."""
    simulation = simulated_scans(SimulationConfig(seed=3, scans=25, points_per_scan=20000, world="campus"))
    clouds = [cloud[reduce_points(cloud, 0.1)] for cloud in simulation.scans()]
    pipeline = PipelineConfig()
    assert pipeline.matching == "metascan" and pipeline.fused_scans == 3
    config = ICPConfig(data_voxel_size=0.35, epsilon=1e-3)
    tilts = []
    for k in range(1, len(clouds)):
        members = range(max(0, k - pipeline.fused_scans), k)
        model = fused_model(
            [clouds[j] for j in members],
            [simulation.truth[j] for j in members],
            normal_voxel_size=0.2,
            normal_cell=0.4,
            voxel_size=0.1,
        )
        truth = invert(simulation.truth[k - 1]) @ simulation.truth[k]
        error = invert(truth) @ icp(model, clouds[k], truth, config).transform
        tilts.append(np.degrees(rotation_angle(error[:3, :3])))
    rms = float(np.sqrt(np.mean(np.square(tilts))))
    assert rms < 0.2, (rms, tilts)


def test_fused_scans_interleave_their_rings_into_level_planes() -> None:
    """Two ring-sampled grounds taken 1.5 m apart, fused in the later scan's frame: the later scan's
    points stay where they were, the earlier one's are moved by the poses, and over the union the
    0.4-3.2 m cubes find level planes for far more of the points than over one scan (its rings lie
    1-3 m apart; the other scan's fall between them)."""
    first, second = ring_ground(0.03, seed=1), ring_ground(0.03, seed=2)
    poses = [np.eye(4), make_pose(np.eye(3), np.array([1.5, 0.0, 0.0]))]
    joined = fused_model([first, second], poses, normal_cell=0.4)
    np.testing.assert_allclose(joined.points[len(first) :], second)
    np.testing.assert_allclose(joined.points[: len(first)], first - [1.5, 0.0, 0.0])
    fused = fused_model([first, second], poses, normal_cell=0.4, voxel_size=0.1)
    shares = []
    for points in (second, fused.points):
        normals, usable = cell_normals(points, 0.4)
        tilt = np.degrees(np.arccos(np.clip(np.abs(normals[usable, 2]), 0.0, 1.0)))
        assert np.percentile(tilt, 95) < 1.5, np.percentile(tilt, 95)
        shares.append(usable.mean())
    assert shares[1] > 2.0 * shares[0], shares
    with pytest.raises(ValueError, match="one pose per scan"):
        fused_model([first, second], poses[:1])


def test_the_smallest_cube_share_tells_ring_scans_from_dense_ones() -> None:
    """What decides whether sequential registration fuses the metascan: on the ring-sampled ground
    hardly any 0.4 m cube holds a plane (the rings lie 1-3 m apart), on a densely sampled floor
    nearly every one does; ``level_out`` says which cube each normal came from."""
    ring = ModelIndex(ring_ground(0.03), normal_voxel_size=0.2, normal_cell=0.4)
    share = ring.smallest_cube_share
    assert share is not None and share < FUSE_BELOW_CUBE_SHARE / 2, share
    x, y = np.meshgrid(np.arange(-5.0, 5.0, 0.05), np.arange(-5.0, 5.0, 0.05))
    floor = np.c_[x.ravel(), y.ravel(), np.full(x.size, -1.8)]
    dense = ModelIndex(floor, normal_voxel_size=0.2, normal_cell=0.4).smallest_cube_share
    assert dense is not None and dense > 0.9, dense
    assert ModelIndex(floor).smallest_cube_share is None  # k-NN normals only: nothing to tell
    level = np.zeros(len(floor), dtype=np.int8)
    _, usable = cell_normals(floor, 0.4, level_out=level)
    assert usable.all() and np.mean(level == 1) > 0.9  # the cubes cut at the floor's edge need larger ones
    assert np.array_equal(level > 0, usable)
