"""Nearest-neighbour search behind one small interface, so ICP never depends on a kd-tree library.

Three backends are available because their speed depends on the query: ``benchmarks/pair.py``
measures them on a real 88k-point scan (2 cores). pykdtree is the default: its pruned k=1 query with
a distance bound is the fastest for the ICP correspondence search, which is where ICP spends its
time, and it builds a tree in under 10 ms. scipy's cKDTree is the portable fallback.

Every backend answers in the same form: float64 distances and int64 indices, with ``-1`` (and an
infinite distance) where no neighbour lies within the bound.

pykdtree parallelises with OpenMP, whose threads by default spin while waiting for work. On a
2-core machine shared with the web server, the viewer or other programs, spinning threads steal the
cores they wait for: the same 20k-point query measured 18 ms with passive waiting and 50-110 ms
(median) with spinning under load, and equal when idle. So unless the user chose otherwise,
``OMP_WAIT_POLICY`` is set to ``PASSIVE`` here, before any OpenMP runtime is loaded by this package.
pykdtree's thread count follows ``OMP_NUM_THREADS`` (default: all cores).
"""

from __future__ import annotations

import os
from abc import ABC, abstractmethod

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

DEFAULT_BACKEND = "pykdtree"

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


class NeighbourIndex(ABC):
    """A static kd-tree over (N, 3) float64 points."""

    name: str

    def __init__(self, points: FloatArray, threads: int) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        if self.points.ndim != 2 or self.points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {self.points.shape}")
        if len(self.points) == 0:
            raise ValueError("cannot build a neighbour index over zero points")
        self.threads = max(1, int(threads))

    def __len__(self) -> int:
        return len(self.points)

    @abstractmethod
    def nearest(self, queries: FloatArray, max_distance: float) -> tuple[FloatArray, IndexArray]:
        """Closest point to each query within ``max_distance``: (distances, indices), ``-1`` when none."""

    @abstractmethod
    def knn(self, queries: FloatArray, k: int) -> tuple[FloatArray, IndexArray]:
        """The ``k`` closest points to each query, nearest first: (N, k) distances and indices."""


def _queries(queries: FloatArray) -> FloatArray:
    q = np.ascontiguousarray(queries, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"queries must have shape (M, 3), got {q.shape}")
    return q


def _missing_to_minus_one(distances: FloatArray, indices: NDArray, size: int) -> tuple[FloatArray, IndexArray]:
    idx = indices.astype(np.int64, copy=False)
    missing = (idx >= size) | (idx < 0) | ~np.isfinite(distances)
    if missing.any():
        idx = np.where(missing, -1, idx)
        distances = np.where(missing, np.inf, distances)
    return distances.astype(np.float64, copy=False), idx


class PykdtreeIndex(NeighbourIndex):
    """pykdtree: OpenMP-parallel queries (thread count from ``OMP_NUM_THREADS``, default all cores)."""

    name = "pykdtree"

    def __init__(self, points: FloatArray, threads: int = 2) -> None:
        from pykdtree.kdtree import KDTree

        super().__init__(points, threads)
        self._tree = KDTree(self.points, leafsize=16)

    def nearest(self, queries: FloatArray, max_distance: float) -> tuple[FloatArray, IndexArray]:
        d, i = self._tree.query(_queries(queries), k=1, distance_upper_bound=float(max_distance))
        return _missing_to_minus_one(d, i, len(self.points))

    def knn(self, queries: FloatArray, k: int) -> tuple[FloatArray, IndexArray]:
        k = min(int(k), len(self.points))
        d, i = self._tree.query(_queries(queries), k=k)
        return _missing_to_minus_one(d.reshape(-1, k), i.reshape(-1, k), len(self.points))


class SmallGicpIndex(NeighbourIndex):
    """small_gicp's KdTree (nanoflann-style, TBB/OpenMP threads per call)."""

    name = "small_gicp"

    def __init__(self, points: FloatArray, threads: int = 2) -> None:
        import small_gicp

        super().__init__(points, threads)
        self._tree = small_gicp.KdTree(self.points, num_threads=self.threads)

    def nearest(self, queries: FloatArray, max_distance: float) -> tuple[FloatArray, IndexArray]:
        idx, sq = self._tree.batch_knn_search(_queries(queries), 1, num_threads=self.threads)
        d = np.sqrt(sq[:, 0])
        i = idx[:, 0].astype(np.int64)
        d[d > max_distance] = np.inf
        return _missing_to_minus_one(d, i, len(self.points))

    def knn(self, queries: FloatArray, k: int) -> tuple[FloatArray, IndexArray]:
        k = min(int(k), len(self.points))
        idx, sq = self._tree.batch_knn_search(_queries(queries), k, num_threads=self.threads)
        return _missing_to_minus_one(np.sqrt(sq), idx.astype(np.int64), len(self.points))


class ScipyIndex(NeighbourIndex):
    """scipy's cKDTree with ``workers`` threads."""

    name = "scipy"

    def __init__(self, points: FloatArray, threads: int = 2) -> None:
        from scipy.spatial import cKDTree

        super().__init__(points, threads)
        self._tree = cKDTree(self.points, leafsize=16, balanced_tree=False, compact_nodes=False)

    def nearest(self, queries: FloatArray, max_distance: float) -> tuple[FloatArray, IndexArray]:
        d, i = self._tree.query(_queries(queries), k=1, distance_upper_bound=float(max_distance), workers=self.threads)
        return _missing_to_minus_one(d, i, len(self.points))

    def knn(self, queries: FloatArray, k: int) -> tuple[FloatArray, IndexArray]:
        k = min(int(k), len(self.points))
        d, i = self._tree.query(_queries(queries), k=k, workers=self.threads)
        return _missing_to_minus_one(d.reshape(-1, k), i.reshape(-1, k), len(self.points))


class RadiusIndex:
    """Every point within a radius of a centre, for the engine's ball queries over scan positions
    (loop candidates near a scan, scans whose reach overlaps another's): a few to tens of thousands
    of points, queried one centre at a time.

    The points are sorted along their widest axis; a query takes the slab of that axis the ball spans
    (two binary searches) and keeps the points of it inside the ball. On trajectories (a random walk
    of 1,000-10,000 positions, balls of 40-2,000 points) that measured within 1.7x of scipy's cKDTree
    ball query and keeps scipy.spatial, with the scipy.sparse and scipy.special it imports, out of the
    engine: 0.1-0.13 s of CPU in every ``slam6d run``'s start-up.
    """

    def __init__(self, points: FloatArray) -> None:
        self.points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        spread = np.ptp(self.points, axis=0) if len(self.points) else np.zeros(3)
        self.axis = int(np.argmax(spread))
        self._order = np.argsort(self.points[:, self.axis], kind="stable")
        self._keys = self.points[self._order, self.axis]

    def __len__(self) -> int:
        return len(self.points)

    def within(self, centre: FloatArray, radius: float) -> IndexArray:
        """Indices of the points within ``radius`` of ``centre`` (boundary included), ascending."""
        centre = np.asarray(centre, dtype=np.float64).reshape(3)
        lower = np.searchsorted(self._keys, centre[self.axis] - radius, side="left")
        upper = np.searchsorted(self._keys, centre[self.axis] + radius, side="right")
        slab = self._order[lower:upper]
        inside = np.sum((self.points[slab] - centre) ** 2, axis=1) <= radius * radius
        return np.sort(slab[inside]).astype(np.int64, copy=False)


BACKENDS: dict[str, type[NeighbourIndex]] = {
    "pykdtree": PykdtreeIndex,
    "small_gicp": SmallGicpIndex,
    "scipy": ScipyIndex,
}


def available_backends() -> list[str]:
    """Backends whose library imports here (scipy always does; the others are optional)."""
    names = []
    for name, module in (("pykdtree", "pykdtree.kdtree"), ("small_gicp", "small_gicp"), ("scipy", "scipy.spatial")):
        try:
            __import__(module)
        except ImportError:
            continue
        names.append(name)
    return names


def build_index(points: FloatArray, backend: str = DEFAULT_BACKEND, threads: int = 2) -> NeighbourIndex:
    """A kd-tree over ``points`` with the named backend, falling back to scipy if it is not installed."""
    if backend not in BACKENDS:
        raise ValueError(f"unknown nearest-neighbour backend {backend!r}; choose from {sorted(BACKENDS)}")
    try:
        return BACKENDS[backend](points, threads)
    except ImportError:
        return ScipyIndex(points, threads)
