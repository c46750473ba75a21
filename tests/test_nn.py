"""Every nearest-neighbour backend must give the exact answers of a brute-force search."""

from __future__ import annotations

import numpy as np
import pytest

from slam6d import nn


@pytest.fixture(scope="module")
def cloud() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(7)
    return rng.uniform(-2.0, 2.0, (3000, 3)), rng.uniform(-2.5, 2.5, (400, 3))


def brute_force(points: np.ndarray, queries: np.ndarray) -> np.ndarray:
    return np.linalg.norm(queries[:, None, :] - points[None, :, :], axis=2)


@pytest.mark.parametrize("backend", nn.available_backends())
def test_nearest_within_bound_matches_brute_force(backend: str, cloud: tuple[np.ndarray, np.ndarray]) -> None:
    points, queries = cloud
    index = nn.build_index(points, backend, threads=2)
    distances, indices = index.nearest(queries, 0.15)
    full = brute_force(points, queries)
    best = full.min(axis=1)
    inside = best <= 0.15
    assert inside.any() and (~inside).any()  # the bound must matter for this test to mean anything
    np.testing.assert_array_equal(indices[~inside], -1)
    assert np.isinf(distances[~inside]).all()
    np.testing.assert_allclose(distances[inside], best[inside], rtol=1e-12)
    np.testing.assert_array_equal(indices[inside], full.argmin(axis=1)[inside])
    assert indices.dtype == np.int64 and distances.dtype == np.float64


@pytest.mark.parametrize("backend", nn.available_backends())
def test_knn_matches_brute_force(backend: str, cloud: tuple[np.ndarray, np.ndarray]) -> None:
    points, queries = cloud
    index = nn.build_index(points, backend, threads=2)
    distances, indices = index.knn(queries, 8)
    expected = np.sort(brute_force(points, queries), axis=1)[:, :8]
    assert distances.shape == indices.shape == (len(queries), 8)
    np.testing.assert_allclose(distances, expected, rtol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(points[indices] - queries[:, None, :], axis=2), expected, rtol=1e-12)


def test_knn_with_more_neighbours_than_points_returns_all() -> None:
    points = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]])
    distances, indices = nn.build_index(points).knn(np.zeros((1, 3)), 10)
    np.testing.assert_array_equal(indices[0], [0, 1, 2])
    np.testing.assert_allclose(distances[0], [0.0, 1.0, 2.0])


@pytest.mark.parametrize("radius", [0.0, 0.3, 1.5, 10.0])
def test_radius_index_matches_brute_force(radius: float, cloud: tuple[np.ndarray, np.ndarray]) -> None:
    """The ball query of loop candidates and relaxation's neighbour graph: every point in the ball,
    from an empty ball (a centre off the points) to one holding the whole cloud."""
    points, queries = cloud
    index = nn.RadiusIndex(points)
    assert len(index) == len(points)
    for centre in queries[:50]:
        found = index.within(centre, radius)
        assert found.dtype == np.int64
        np.testing.assert_array_equal(found, np.flatnonzero(brute_force(points, centre[None])[0] <= radius))
    assert len(index.within(points[5], 10.0)) == len(points)


def test_radius_index_includes_the_boundary_and_follows_the_widest_axis() -> None:
    positions = np.array([[0.0, 0.0, 0.0], [0.0, 3.0, 0.0], [4.0, 0.0, 0.0], [4.0, 3.0, 0.0], [0.0, 9.0, 0.0]])
    index = nn.RadiusIndex(positions)
    assert index.axis == 1  # y spreads 9 m, x 4 m
    np.testing.assert_array_equal(index.within(np.zeros(3), 4.0), [0, 1, 2])
    np.testing.assert_array_equal(index.within(np.zeros(3), 5.0), [0, 1, 2, 3])
    np.testing.assert_array_equal(index.within(np.array([0.0, 0.0, 1.0]), 0.5), np.zeros(0, dtype=np.int64))
    assert len(nn.RadiusIndex(np.zeros((0, 3)))) == 0


def test_bad_input_is_refused_clearly() -> None:
    with pytest.raises(ValueError, match="unknown nearest-neighbour backend"):
        nn.build_index(np.zeros((3, 3)), "flann")
    with pytest.raises(ValueError, match="zero points"):
        nn.build_index(np.zeros((0, 3)))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        nn.build_index(np.zeros((5, 2)))
    with pytest.raises(ValueError, match=r"\(M, 3\)"):
        nn.build_index(np.zeros((5, 3))).nearest(np.zeros(3), 1.0)
