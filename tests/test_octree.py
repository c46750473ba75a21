"""Voxel reduction and octree occupancy."""

from __future__ import annotations

import numpy as np
import pytest

from slam6d.errors import EmptyScanError
from slam6d.octree import KeySet, Octree, pack_cells, reduce_points, unpack_keys


def _cells(points: np.ndarray, size: float) -> np.ndarray:
    return np.floor((points - points.min(axis=0)) / size).astype(np.int64)


def test_reduce_points_keeps_one_original_point_per_occupied_voxel() -> None:
    rng = np.random.default_rng(1)
    points = rng.normal(scale=2.0, size=(20_000, 3))
    size = 0.5
    kept = reduce_points(points, size)
    assert kept.dtype == np.int64
    assert np.all(np.diff(kept) > 0), "indices are ascending and unique"
    cells = _cells(points, size)
    occupied = {tuple(c) for c in cells}
    kept_cells = [tuple(c) for c in cells[kept]]
    assert len(kept_cells) == len(set(kept_cells)) == len(occupied)


def test_reduce_points_picks_the_point_nearest_the_voxel_centre() -> None:
    rng = np.random.default_rng(2)
    points = rng.uniform(0.0, 3.0, size=(5_000, 3))
    points[0] = 0.0  # anchor the grid at the origin so centres are (i + 0.5) * size
    size = 1.0
    kept = set(reduce_points(points, size).tolist())
    cells = np.floor(points / size)
    dist = np.linalg.norm(points - (cells + 0.5) * size, axis=1)
    for cell in np.unique(cells, axis=0):
        members = np.flatnonzero(np.all(cells == cell, axis=1))
        best = members[np.argmin(dist[members])]
        assert best in kept


def test_reduce_points_is_deterministic_and_independent_of_point_order() -> None:
    rng = np.random.default_rng(3)
    points = rng.uniform(-10.0, 10.0, size=(30_000, 3))
    first = reduce_points(points, 0.7)
    np.testing.assert_array_equal(first, reduce_points(points, 0.7))
    order = rng.permutation(len(points))
    shuffled = reduce_points(points[order], 0.7)
    np.testing.assert_array_equal(np.sort(order[shuffled]), first)


def test_reduce_points_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="voxel_size"):
        reduce_points(np.zeros((3, 3)), 0.0)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        reduce_points(np.zeros((3, 2)), 0.1)
    with pytest.raises(EmptyScanError):
        reduce_points(np.zeros((0, 3)), 0.1)
    with pytest.raises(ValueError, match="too small"):
        reduce_points(np.array([[0.0, 0.0, 0.0], [1e4, 0.0, 0.0]]), 1e-3)


def test_pack_and_unpack_round_trip_and_out_of_range_cells_never_match() -> None:
    cells = np.array([[0, 0, 0], [1, 2, 3], [2**21 - 1, 5, 2**20]])
    np.testing.assert_array_equal(unpack_keys(pack_cells(cells)), cells)
    keys = pack_cells(np.array([[-1, 0, 0], [0, 2**21, 0]]))
    assert np.all(keys == -1)
    key_set = KeySet(pack_cells(cells))
    np.testing.assert_array_equal(key_set.contains(np.r_[pack_cells(cells), keys, [12345]]), [1, 1, 1, 0, 0, 0])


def test_octree_occupancy_counts_points_per_cube_at_every_depth() -> None:
    # 8 clusters at the corners of a 4 m cube, 10/20/.../80 points each, leaf 0.5 m
    rng = np.random.default_rng(5)
    corners = np.array([[x, y, z] for x in (0.0, 4.0) for y in (0.0, 4.0) for z in (0.0, 4.0)])
    points = np.concatenate([c + rng.uniform(0.01, 0.24, size=(10 * (i + 1), 3)) for i, c in enumerate(corners)])
    tree = Octree(points, leaf_size=0.5)
    assert tree.depth == 4 and tree.root_size == pytest.approx(8.0)
    np.testing.assert_allclose(tree.origin, 0.0)
    leaves = tree.occupancy_at_depth(tree.depth)
    assert len(leaves) == 8 and leaves.cube_size == pytest.approx(0.5)
    assert sorted(leaves.counts.tolist()) == [10, 20, 30, 40, 50, 60, 70, 80]
    np.testing.assert_allclose(np.sort(leaves.centres, axis=0), np.sort(corners + 0.25, axis=0))
    # depth 1 (4 m cubes): each corner falls in its own octant
    assert len(tree.occupancy_at_depth(1)) == 8
    # depth 0: the root cube holds everything
    root = tree.occupancy_at_depth(0)
    assert len(root) == 1 and root.counts.tolist() == [360]
    # a size that is not a depth is still answered, anchored at the same origin
    odd = tree.occupancy(3.0)
    assert odd.counts.sum() == 360 and len(odd) == 8
    centres = tree.occupied_cubes(4.0)
    np.testing.assert_allclose(np.sort(centres, axis=0), np.sort(corners + 2.0, axis=0))


def test_octree_parent_cubes_contain_exactly_the_children() -> None:
    rng = np.random.default_rng(6)
    points = rng.uniform(-5.0, 5.0, size=(5_000, 3)) * np.array([1.0, 1.0, 0.2])
    tree = Octree(points, leaf_size=0.1)
    for depth in range(1, tree.depth + 1):
        fine = tree.occupancy_at_depth(depth)
        coarse = tree.occupancy_at_depth(depth - 1)
        parents = np.unique(pack_cells(fine.cells >> 1))
        np.testing.assert_array_equal(parents, coarse.keys)
        assert coarse.counts.sum() == fine.counts.sum() == len(points)
    occupied = tree.occupancy(0.4)
    assert np.all(occupied.contains(points))
    assert not np.any(occupied.contains(points + np.array([0.0, 0.0, 50.0])))


def test_count_hits_matches_a_brute_force_count() -> None:
    from slam6d.geometry import rot_x, rot_z

    rng = np.random.default_rng(7)
    model = rng.uniform(0.0, 6.0, size=(3_000, 3)) * np.array([1.0, 1.0, 0.3])
    occupancy = Octree(model, leaf_size=0.25).occupancy(0.5)
    points = rng.uniform(0.5, 5.5, size=(400, 3)) * np.array([1.0, 1.0, 0.3])
    pivot = points.mean(axis=0)
    rotations = np.stack([np.eye(3), rot_z(0.2), rot_x(-0.1) @ rot_z(0.4)])
    shifts = np.array([[0, 0, 0], [1, 0, 0], [-2, 1, 1], [0, -1, 0]])
    hits = occupancy.count_hits(points, rotations, pivot, shifts)
    assert hits.shape == (3, 4)
    for r, rotation in enumerate(rotations):
        moved = (points - pivot) @ rotation.T + pivot
        for s, shift in enumerate(shifts):
            expected = occupancy.contains(moved + shift * 0.5).sum()
            assert abs(int(hits[r, s]) - int(expected)) <= 1  # a point on a cube face may round either way
    assert hits[0, 0] > 0
    # the search's own shifts: a full 5 x 5 x 3 box in C order, scored as a whole
    box = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3), np.arange(-1, 2), indexing="ij"), -1).reshape(-1, 3)
    hits = occupancy.count_hits(points, rotations, pivot, box)
    for r, rotation in enumerate(rotations):
        moved = (points - pivot) @ rotation.T + pivot
        expected = np.array([occupancy.contains(moved + shift * 0.5).sum() for shift in box])
        assert np.abs(hits[r] - expected).max() <= 1
        assert hits[r].sum() > 0


def test_octree_of_degenerate_clouds() -> None:
    single = Octree(np.array([[1.0, 2.0, 3.0]]), leaf_size=0.5)
    assert single.depth == 0 and len(single.occupancy_at_depth(0)) == 1
    # a point exactly on the far face of the leaf grid still gets its own leaf, not a clipped one
    edge = Octree(np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]), leaf_size=0.5)
    assert edge.depth == 2 and edge.root_size == pytest.approx(2.0)
    np.testing.assert_allclose(edge.occupied_cubes(0.5)[:, 0], [0.25, 1.25])
    with pytest.raises(ValueError, match="depth"):
        edge.cube_size(3)
    with pytest.raises(ValueError, match="leaf_size"):
        Octree(np.zeros((2, 3)), leaf_size=-1.0)
