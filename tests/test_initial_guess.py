"""Initial guesses: odometry extrapolation and the octree coarse-to-fine search."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from benchmarks.initial_guess import BUNNY_ICP
from slam6d.geometry import invert, pose_difference, pose_from_xyzrpy, transform_points
from slam6d.icp import ICPConfig, icp
from slam6d.initial_guess import (
    CandidateGrid,
    GuessResult,
    OctreeSearchConfig,
    cloud_extent,
    config_for,
    extrapolate_odometry,
    level_surfaces,
    octree_guess,
    offset_transform,
    search_pivot,
)
from slam6d.io import read_sequence
from slam6d.octree import Octree
from slam6d.trace import to_jsonable

DEG = math.pi / 180.0


# ---------------------------------------------------------------- odometry extrapolation


def test_extrapolate_odometry_carries_the_previous_correction_forward() -> None:
    prev_odometry = pose_from_xyzrpy(4.0, 1.0, 0.2, 0.02, -0.03, 0.7)
    motion = pose_from_xyzrpy(1.5, -0.2, 0.1, 0.05, 0.04, -0.3)  # measured by odometry, in the scan frame
    current_odometry = prev_odometry @ motion
    correction = pose_from_xyzrpy(0.3, -0.4, 0.05, 0.01, 0.02, 0.1)  # what registration fixed last time
    prev_registered = correction @ prev_odometry
    guess = extrapolate_odometry(prev_odometry, prev_registered, current_odometry)
    np.testing.assert_allclose(guess, correction @ current_odometry, atol=1e-12)
    np.testing.assert_allclose(guess, prev_registered @ motion, atol=1e-12)
    # no correction so far: the guess is the odometry itself
    np.testing.assert_allclose(extrapolate_odometry(prev_odometry, prev_odometry, current_odometry), current_odometry)


# ---------------------------------------------------------------- synthetic scene


def _box_surface(rng: np.random.Generator, lower: np.ndarray, upper: np.ndarray, density: float) -> np.ndarray:
    """Points on the faces of an axis-aligned box, ``density`` per square metre."""
    lower, upper = np.asarray(lower, float), np.asarray(upper, float)
    size = upper - lower
    faces = []
    for axis in range(3):
        u, v = [a for a in range(3) if a != axis]
        count = max(1, int(density * size[u] * size[v]))
        for side in (lower[axis], upper[axis]):
            pts = lower + rng.uniform(0.0, 1.0, (count, 3)) * size
            pts[:, axis] = side
            faces.append(pts)
    return np.concatenate(faces)


def _hall(rng: np.random.Generator, density: float = 120.0) -> np.ndarray:
    """An asymmetric 24 x 14 m hall without a ceiling, with pillars and boxes (world frame, z up).

    Dense enough (~1 point per 0.1 m cube face) that the finest search level sees filled cubes, as in
    a real scan at short range."""
    room = _box_surface(rng, [-12, -7, 0], [12, 7, 4], density)
    parts = [room[room[:, 2] < 3.99]]
    for x, y, w, d, h in [
        (-8, -4, 0.6, 0.6, 4),
        (-2, 3, 0.6, 0.6, 4),
        (5, -2, 0.6, 0.6, 4),
        (9, 4, 2.5, 1.2, 1.5),
        (-6, 4, 1.5, 3.0, 1.0),
        (2, -5, 3.0, 1.0, 2.2),
        (-10, -1, 1.0, 1.0, 0.8),
    ]:
        parts.append(_box_surface(rng, [x, y, 0], [x + w, y + d, h], density))
    points = np.concatenate(parts)
    return points + rng.normal(scale=0.01, size=points.shape)  # range noise of a real scanner


@pytest.fixture(scope="module")
def hall_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(model points, data points, true data->model transform): two samplings of the hall seen from
    two sensor poses, the data cropped to 15 m around its sensor so the overlap is partial."""
    rng = np.random.default_rng(11)
    model_pose = pose_from_xyzrpy(-3.0, 0.5, 1.33, 0.0, 0.0, 0.3)
    data_pose = pose_from_xyzrpy(-1.2, 0.0, 1.25, 0.01, -0.02, 0.55)
    model = transform_points(invert(model_pose), _hall(rng))
    data = transform_points(invert(data_pose), _hall(rng))
    data = data[np.linalg.norm(data, axis=1) < 15.0]
    return model, data, invert(model_pose) @ data_pose


def test_search_recovers_a_large_offset_in_a_synthetic_hall(hall_pair) -> None:
    model, data, truth = hall_pair
    start = pose_from_xyzrpy(0.7, -0.6, 0.15, 4 * DEG, -5 * DEG, 28 * DEG) @ truth
    before = pose_difference(start, truth)
    assert before[0] > 0.7 and before[1] > 25 * DEG
    result = octree_guess(model, data, start)
    metres, radians = pose_difference(result.transform, truth)
    assert metres < 0.1 and radians < 0.5 * DEG, (metres, radians / DEG)


def test_search_leaves_a_correct_start_where_it_is(hall_pair) -> None:
    model, data, truth = hall_pair
    result = octree_guess(model, data, truth)
    metres, radians = pose_difference(result.transform, truth)
    assert metres < 0.05 and radians < 0.3 * DEG


def test_trace_lists_every_candidate_of_every_level_and_the_winner(hall_pair) -> None:
    model, data, truth = hall_pair
    config = OctreeSearchConfig(cube_sizes=(0.8, 0.4, 0.2), yaw_range=12 * DEG)
    start = pose_from_xyzrpy(0.5, 0.3, 0.0, 0.0, 0.0, 8 * DEG) @ truth
    calls: list[tuple[int, int]] = []
    result = octree_guess(model, data, start, config, progress=lambda done, total: calls.append((done, total)))
    assert isinstance(result, GuessResult)
    assert calls == [(1, 3), (2, 3), (3, 3)]
    assert [level.cube_size for level in result.levels] == [0.8, 0.4, 0.2]
    np.testing.assert_allclose(result.levels[0].candidates.start, start)
    for number, level in enumerate(result.levels):
        grid = level.candidates
        assert isinstance(grid, CandidateGrid)
        assert len(grid) == grid.scores.size == math.prod(len(axis) for axis in grid.axes)
        assert grid.scores.shape == tuple(len(axis) for axis in grid.axes)
        # every axis is symmetric about zero, so the start itself was evaluated
        for axis in grid.axes:
            np.testing.assert_allclose(axis, -axis[::-1], atol=1e-12)
        assert level.winner.score == grid.scores.max()
        assert 0 < level.winner.score <= level.data_points
        np.testing.assert_allclose(
            level.winner.transform, offset_transform(grid.start, grid.pivot, level.winner.offsets)
        )
        assert level.winner.score == grid[int(np.argmax(grid.score_list()))].score
        # the candidates read as a sequence of Candidate and agree with the flat arrays
        offsets = grid.offsets()
        assert offsets.shape == (len(grid), 6)
        for index in (0, len(grid) // 2, len(grid) - 1):
            candidate = grid[index]
            np.testing.assert_allclose(candidate.offsets, offsets[index])
            assert candidate.score == grid.score_list()[index]
        assert sum(1 for _ in grid) == len(grid)
        if number > 0:  # each level starts where the previous one ended
            np.testing.assert_allclose(grid.start, result.levels[number - 1].winner.transform)
    coarse = result.levels[0].candidates.axes
    assert coarse[0].max() >= 1.6 and coarse[5].max() >= 12 * DEG - 1e-9
    np.testing.assert_allclose(result.transform, result.levels[-1].winner.transform)
    assert result.score == result.levels[-1].winner.score
    # the whole trace is plain JSON (and the candidate scores survive as a grid)
    encoded = json.loads(json.dumps(to_jsonable(result)))
    assert len(encoded["levels"]) == 3
    first = encoded["levels"][0]["candidates"]
    assert np.asarray(first["scores"]).shape == result.levels[0].candidates.scores.shape
    assert encoded["levels"][0]["winner"]["score"] == result.levels[0].winner.score


def test_candidate_scores_are_the_cube_overlap_counts(hall_pair) -> None:
    """A candidate's score recomputed from scratch: reduced data points placed by its transform that
    fall in occupied model cubes."""
    model, data, truth = hall_pair
    config = OctreeSearchConfig(
        cube_sizes=(0.5,),
        yaw_range=6 * DEG,
        tilt_range=0.0,
        translation_range=(0.5, 0.5, 0.0),
        max_points=10**6,
        skip_level_surfaces=False,
    )
    result = octree_guess(model, data, truth, config)
    level = result.levels[0]
    occupancy = Octree(model, 0.5).occupancy(0.5)
    from slam6d.octree import reduce_points

    reduced = data[reduce_points(data, 0.5)]
    assert len(reduced) == level.data_points
    grid = level.candidates
    for index in np.linspace(0, len(grid) - 1, 7).astype(int):
        candidate = grid[int(index)]
        expected = int(occupancy.contains(transform_points(candidate.transform, reduced)).sum())
        assert abs(candidate.score - expected) <= 1  # a point exactly on a cube face may round either way


def test_config_scales_to_small_clouds_and_validates() -> None:
    base = OctreeSearchConfig()
    scaled = base.for_extent(0.25)
    factor = 0.25 / base.reference_extent
    np.testing.assert_allclose(scaled.cube_sizes, np.array(base.cube_sizes) * factor)
    np.testing.assert_allclose(scaled.translation_range, np.array(base.translation_range) * factor)
    assert scaled.yaw_range == base.yaw_range and scaled.tilt_range == base.tilt_range
    rng = np.random.default_rng(3)
    small = rng.normal(scale=0.05, size=(2000, 3))
    assert cloud_extent(small) == pytest.approx(2 * 0.05 * 2.5, rel=0.15)  # chi(3) 90th percentile ~ 2.5 sigma
    assert config_for(small).cube_sizes[0] < 0.05
    large = rng.normal(scale=10.0, size=(2000, 3))
    assert config_for(large) == base
    with pytest.raises(ValueError, match="coarse to fine"):
        OctreeSearchConfig(cube_sizes=(0.1, 0.8))
    with pytest.raises(ValueError, match="cube_sizes"):
        OctreeSearchConfig(cube_sizes=())
    with pytest.raises(ValueError, match="initial"):
        octree_guess(small, small, np.eye(3))


def test_small_objects_get_a_scaled_search_automatically() -> None:
    rng = np.random.default_rng(8)
    # a 20 cm "object": an open box with a post, sampled densely
    scene = np.concatenate(
        [
            _box_surface(rng, [0, 0, 0], [0.2, 0.12, 0.08], 2e5),
            _box_surface(rng, [0.05, 0.02, 0.08], [0.08, 0.05, 0.18], 2e5),
        ]
    )
    truth = pose_from_xyzrpy(0.01, -0.005, 0.0, 0.0, 0.0, 0.2)
    data = transform_points(invert(truth), _box_surface(rng, [0, 0, 0], [0.2, 0.12, 0.08], 2e5))
    data = np.concatenate(
        [data, transform_points(invert(truth), _box_surface(rng, [0.05, 0.02, 0.08], [0.08, 0.05, 0.18], 2e5))]
    )
    start = _perturbed(truth, data, (0.008, 0.006, 0.0, 3 * DEG, -3 * DEG, 25 * DEG))
    result = octree_guess(scene, data, start)
    assert result.config.cube_sizes[0] < 0.02
    metres, radians = pose_difference(result.transform, truth)
    assert metres < 0.003 and radians < 1.0 * DEG


# ---------------------------------------------------------------- real data: search + ICP vs plain ICP


def _perturbed(reference: np.ndarray, data: np.ndarray, offsets: tuple[float, ...]) -> np.ndarray:
    """``reference`` disturbed by (dx, dy, dz, roll, pitch, yaw) about the data centroid, in model axes."""
    pivot = transform_points(reference, data).mean(axis=0)
    return offset_transform(reference, pivot, offsets)


@pytest.mark.slow
def test_balm_consecutive_scans_recovered_from_1m_30deg_where_plain_icp_fails(shared_data: Path) -> None:
    sequence = read_sequence(shared_data / "balm_hall", first=20, last=21)
    model, data = sequence.scans
    reference = invert(model.pose) @ data.pose
    start = _perturbed(reference, data.points, (0.8, -0.6, 0.0, 5 * DEG, -5 * DEG, 30 * DEG))
    config = ICPConfig()

    plain = icp(model.points, data.points, start, config)
    plain_error = pose_difference(plain.transform, reference)
    assert plain_error[0] > 0.2 or plain_error[1] > 5 * DEG, "plain ICP should fail from this start"

    guess = octree_guess(model.points, data.points, start)
    refined = icp(model.points, data.points, guess.transform, config)
    metres, radians = pose_difference(refined.transform, reference)
    assert metres < 0.02 and radians < 0.5 * DEG, (metres, radians / DEG)


@pytest.mark.slow
@pytest.mark.parametrize(("model_name", "data_name"), [("bun000", "bun045"), ("bun045", "bun090")])
def test_bunny_neighbours_recovered_from_30deg_where_plain_icp_fails(
    shared_data: Path, model_name: str, data_name: str
) -> None:
    scans = {scan.name: scan for scan in read_sequence(shared_data / "stanford_bunny").scans}
    model, data = scans[model_name], scans[data_name]
    reference = invert(model.pose) @ data.pose
    # 1 m in a 20 m hall is ~5 % of the scene: the same relative shift for a ~16 cm object
    shift = 0.05 * cloud_extent(model.points)
    start = _perturbed(reference, data.points, (-0.6 * shift, 0.8 * shift, 0.0, 5 * DEG, 5 * DEG, 30 * DEG))
    config = BUNNY_ICP  # object scale: full-resolution data, 3 mm pairing distance, 1 µm convergence
    plain = icp(model.points, data.points, start, config)
    plain_error = pose_difference(plain.transform, reference)
    assert plain_error[0] > 0.003 or plain_error[1] > 5 * DEG, "plain ICP should fail from this start"

    guess = octree_guess(model.points, data.points, start)
    assert guess.config.cube_sizes[0] < 0.02  # scaled to the object automatically
    refined = icp(model.points, data.points, guess.transform, config)
    metres, radians = pose_difference(refined.transform, reference)
    assert metres < 0.001 and radians < 0.5 * DEG, (metres, radians / DEG)


def test_without_overlap_the_start_is_kept_and_scores_are_zero(hall_pair) -> None:
    model, data, truth = hall_pair
    far = pose_from_xyzrpy(500.0, 0.0, 0.0, 0.0, 0.0, 0.0) @ truth
    result = octree_guess(model, data, far, OctreeSearchConfig(cube_sizes=(0.8, 0.4)))
    assert result.score == 0
    assert all(level.candidates.scores.max() == 0 for level in result.levels)
    np.testing.assert_allclose(result.transform, far)


def test_empty_clouds_are_rejected() -> None:
    from slam6d.errors import EmptyScanError

    with pytest.raises(EmptyScanError, match="data points"):
        octree_guess(np.ones((10, 3)), np.zeros((0, 3)))
    with pytest.raises(EmptyScanError, match="model points"):
        octree_guess(np.zeros((0, 3)), np.ones((10, 3)))


def test_a_prebuilt_octree_gives_the_same_search(hall_pair) -> None:
    model, data, truth = hall_pair
    config = OctreeSearchConfig(cube_sizes=(0.8, 0.4), yaw_range=10 * DEG)
    start = pose_from_xyzrpy(0.4, 0.0, 0.0, 0.0, 0.0, 6 * DEG) @ truth
    from_points = octree_guess(model, data, start, config)
    # built once per scan (leaf = the finest search cube, as octree_guess would) and shared with the viewer
    tree = Octree(model, leaf_size=config.cube_sizes[-1])
    from_tree = octree_guess(tree, data, start, config)
    np.testing.assert_allclose(from_tree.transform, from_points.transform)
    for a, b in zip(from_tree.levels, from_points.levels, strict=True):
        np.testing.assert_array_equal(a.candidates.scores, b.candidates.scores)
    # a finer octree anchors the cubes differently, which changes the scores but not the answer much
    finer = octree_guess(Octree(model, leaf_size=0.1), data, start, config)
    metres, radians = pose_difference(finer.transform, from_points.transform)
    steps = from_points.levels[-1].steps  # at most one step of the finest level
    assert metres <= steps[0] + 1e-9 and radians <= max(steps[3:]) + 1e-9


def test_level_surfaces_flags_ground_and_ceiling_not_walls() -> None:
    """The ring-sampled level planes are left out of the score; the walls that fix the heading stay."""
    rng = np.random.default_rng(4)
    ground = np.column_stack([rng.uniform(-20, 20, (4000, 2)), rng.normal(-1.8, 0.01, 4000)])
    ceiling = np.column_stack([rng.uniform(-8, 8, (2000, 2)), rng.normal(2.5, 0.01, 2000)])
    wall = np.column_stack([rng.uniform(-20, 20, 1500), np.full(1500, 6.0), rng.uniform(-1.8, 2.5, 1500)])
    tilt = pose_from_xyzrpy(0, 0, 0, 4 * DEG, -3 * DEG, 0)  # a handheld scanner is not level
    points = transform_points(tilt, np.vstack([ground, ceiling, wall]))
    flagged = level_surfaces(points, tolerance=0.15, min_share=0.1)
    assert flagged[:4000].mean() > 0.98 and flagged[4000:6000].mean() > 0.98
    assert flagged[6000:].mean() < 0.15  # only the wall's strips at floor and ceiling height
    assert search_pivot(points).tolist() == [0.0, 0.0, 0.0]  # the scanner stands inside its scan
    assert np.allclose(search_pivot(points + 100.0), (points + 100.0).mean(axis=0))
