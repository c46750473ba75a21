"""Pairwise registration by ICP: closest points within a max distance, then the rigid motion that fits them.

Two error metrics are offered. ``point_to_point`` is the paper's: the closed-form least-squares
rotation from the SVD of the cross-covariance of the paired points (Arun, Huang and Blostein 1987).
It is robust but converges linearly, so near the optimum it needs many iterations. ``point_to_plane``
minimises the distance of each data point to the tangent plane of its model partner (normals from
the model's k nearest neighbours, estimated on demand and cached in the :class:`ModelIndex`),
linearised for small rotations; it slides along walls and floors instead of being held back by the sampling of the model,
and converges in a few iterations. It is the default because it is 3-6x faster in
``benchmarks/pair.py`` at the same useful accuracy (about 0.1 mm on an exact 100k-point copy, and
within the reference's own uncertainty on a real pair).

Everything here works with ``transform`` = ``model_from_data``: ``model ≈ transform_points(T, data)``.
:func:`icp_iterations` yields one :class:`ICPIteration` per step so the workbench can show each
correspondence set; :func:`icp` runs it to the end.

Convergence rule: an iteration's update is ``Δ = T_k · T_{k-1}⁻¹``; a distance stage has converged
when ``|t(Δ)| <= epsilon`` (metres) and ``angle(R(Δ)) <= epsilon`` (radians), or when ``T_k`` is that
close to one of the stage's previous three poses: with a hard max distance the pair set can flip
between two or three states forever (one point entering and leaving), and such a cycle cannot
improve any further. The stages of a coarse-to-fine ``distance_schedule`` before the last use
``max(epsilon, stage_epsilon)`` instead, because they only need to bring the scans within reach of
the next, tighter distance. After the last stage (``max_distance``) the run is converged.
``max_iterations`` caps the iterations of all stages together.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field

import numba
import numpy as np
from numpy.typing import NDArray

from slam6d import nn
from slam6d.errors import RegistrationError
from slam6d.geometry import axis_angle_to_rotation, invert, make_pose, rotation_angle, transform_points
from slam6d.octree import reduce_points

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

METHODS = ("point_to_plane", "point_to_point")
_CYCLE = 4  # the convergence test compares with the previous pose and the three before it (cycles)


@dataclass(frozen=True)
class ICPConfig:
    """How a pair is registered. Distances in metres; the defaults suit robot scans of rooms,
    buildings and streets (scale them down for small objects such as the Stanford bunny).

    ``data_voxel_size`` > 0 reduces the data scan to one real point per voxel before matching (the
    model keeps full resolution, so accuracy is kept while the per-iteration search shrinks; 10 cm is
    3DTK's usual ``-r 10``); 0 matches every data point. Point-to-plane matches against the model
    reduced to ``normal_voxel_size`` voxels and estimates normals there from ``normal_neighbours``
    neighbours (see :class:`ModelIndex` for why).
    ``threads`` bounds the worker threads of the search and the numba kernels.

    ``epsilon`` (see the module docstring for the exact rule) defaults to 0.1 mm / 0.006°: on real
    scans the update does not shrink below that, because single pairs keep entering and leaving the
    max distance, and iterating on changes nothing measurable. Point-to-point converges linearly: its
    updates shrink slowly while it still creeps towards the optimum, so give it 1e-5 or less (on the
    BALM pair 1e-4 stops it 0.1° short, 1e-5 within 0.07° of the reference).
    """

    max_distance: float = 0.25
    max_iterations: int = 50
    epsilon: float = 1e-4
    method: str = "point_to_plane"
    distance_schedule: tuple[float, ...] = ()
    stage_epsilon: float = 1e-4
    min_pairs: int = 20
    normal_neighbours: int = 12
    normal_voxel_size: float = 0.05
    data_voxel_size: float = 0.1
    threads: int = 2
    nn_backend: str = nn.DEFAULT_BACKEND

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown ICP method {self.method!r}; choose from {METHODS}")
        if not (self.max_distance > 0 and math.isfinite(self.max_distance)):
            raise ValueError(f"max_distance must be a positive number of metres, got {self.max_distance}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be at least 1, got {self.max_iterations}")
        if self.epsilon < 0:
            raise ValueError(f"epsilon must not be negative, got {self.epsilon}")
        if self.min_pairs < 6:
            raise ValueError(f"min_pairs must be at least 6 (a rigid motion has 6 unknowns), got {self.min_pairs}")
        if self.normal_neighbours < 3:
            raise ValueError(f"normal_neighbours must be at least 3, got {self.normal_neighbours}")
        if self.normal_voxel_size < 0:
            raise ValueError(f"normal_voxel_size must be >= 0 (0 = raw points), got {self.normal_voxel_size}")
        if self.data_voxel_size < 0:
            raise ValueError(f"data_voxel_size must be >= 0 (0 = full resolution), got {self.data_voxel_size}")
        schedule = self.distance_schedule
        if any(not (d > 0 and math.isfinite(d)) for d in schedule):
            raise ValueError(f"distance_schedule entries must be positive, got {schedule}")
        if any(b > a for a, b in itertools.pairwise(schedule)):
            raise ValueError(f"distance_schedule must go from coarse to fine (non-increasing), got {schedule}")
        if schedule and schedule[-1] < self.max_distance:
            raise ValueError(f"distance_schedule {schedule} goes below max_distance {self.max_distance}")

    def stages(self) -> tuple[float, ...]:
        """The max distances used in order: the schedule, always ending at ``max_distance``."""
        schedule = tuple(float(d) for d in self.distance_schedule)
        if not schedule or schedule[-1] != self.max_distance:
            schedule = (*schedule, float(self.max_distance))
        return schedule


@dataclass
class ICPIteration:
    """One ICP step. ``pairs``/``rms`` describe the correspondences found at the start of the step
    (Euclidean pair distances, for either method); ``transform`` is model_from_data after the step."""

    index: int
    transform: FloatArray
    pairs: int
    rms: float
    max_distance: float
    step_translation: float = 0.0  # |t(Δ)| of this step's update, metres
    step_rotation: float = 0.0  # angle(R(Δ)) of this step's update, radians
    converged: bool = False  # True on the step that met the convergence rule of the last stage


@dataclass
class ICPResult:
    """Outcome of :func:`icp`. ``pairs``/``rms`` are those of the last iteration (measured at its start,
    so within one update of ``transform``; within ``epsilon`` when converged). ``fitness`` is the
    fraction of the (reduced) data points that found a partner."""

    transform: FloatArray
    iterations: list[ICPIteration]
    converged: bool
    pairs: int
    rms: float
    fitness: float
    data_points: int
    method: str
    max_distance: float = field(default=0.0)

    @classmethod
    def from_iterations(
        cls, iterations: list[ICPIteration], data_points: int, method: str, frame: FloatArray | None = None
    ) -> ICPResult:
        """The result a finished iteration trace amounts to; ``frame`` (e.g. world_from_model) is
        applied to the last transform when the model was matched in a frame of its own."""
        last = iterations[-1]
        return cls(
            transform=last.transform if frame is None else frame @ last.transform,
            iterations=iterations,
            converged=last.converged,
            pairs=last.pairs,
            rms=last.rms,
            fitness=last.pairs / max(data_points, 1),
            data_points=data_points,
            method=method,
            max_distance=last.max_distance,
        )


# ---------------------------------------------------------------- normals (numba)


@numba.njit(cache=True, inline="always")
def _smallest_eigenvector(c00, c01, c02, c11, c12, c22):  # type: ignore[no-untyped-def]
    """Eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix (closed form), plus the
    three eigenvalues in ascending order. Closed form because LAPACK per 3x3 costs microseconds each."""
    p1 = c01 * c01 + c02 * c02 + c12 * c12
    q = (c00 + c11 + c22) / 3.0
    d0, d1, d2 = c00 - q, c11 - q, c22 - q
    p2 = d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * p1
    p = math.sqrt(p2 / 6.0)
    if p <= 1e-300:
        return 0.0, 0.0, 0.0, q, q, q
    inv = 1.0 / p
    b00, b11, b22 = d0 * inv, d1 * inv, d2 * inv
    b01, b02, b12 = c01 * inv, c02 * inv, c12 * inv
    det = b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    r = min(1.0, max(-1.0, det / 2.0))
    phi = math.acos(r) / 3.0
    large = q + 2.0 * p * math.cos(phi)
    small = q + 2.0 * p * math.cos(phi + 2.0 * math.pi / 3.0)
    middle = 3.0 * q - large - small
    # rows of (C - small*I); their pairwise cross products all point along the wanted eigenvector
    a0, a1, a2 = c00 - small, c01, c02
    e0, e1, e2 = c01, c11 - small, c12
    f0, f1, f2 = c02, c12, c22 - small
    x0, x1, x2 = a1 * e2 - a2 * e1, a2 * e0 - a0 * e2, a0 * e1 - a1 * e0
    y0, y1, y2 = a1 * f2 - a2 * f1, a2 * f0 - a0 * f2, a0 * f1 - a1 * f0
    z0, z1, z2 = e1 * f2 - e2 * f1, e2 * f0 - e0 * f2, e0 * f1 - e1 * f0
    nx, ny, nz = x0 * x0 + x1 * x1 + x2 * x2, y0 * y0 + y1 * y1 + y2 * y2, z0 * z0 + z1 * z1 + z2 * z2
    if nx >= ny and nx >= nz:
        s = 1.0 / math.sqrt(nx) if nx > 0 else 0.0
        return x0 * s, x1 * s, x2 * s, small, middle, large
    if ny >= nz:
        s = 1.0 / math.sqrt(ny) if ny > 0 else 0.0
        return y0 * s, y1 * s, y2 * s, small, middle, large
    s = 1.0 / math.sqrt(nz) if nz > 0 else 0.0
    return z0 * s, z1 * s, z2 * s, small, middle, large


@numba.njit(cache=True, inline="always")
def _store_plane_normal(normals, valid, row, c00, c01, c02, c11, c12, c22, min_planarity):  # type: ignore[no-untyped-def]
    """Normal of a covariance into ``normals[row]`` when the points form a plane. A neighbourhood
    along a single scan line is a line, not a plane (middle eigenvalue ~0): its "normal" is arbitrary,
    so it is left invalid - one rule for every normal estimator."""
    x, y, z, _small, middle, large = _smallest_eigenvector(c00, c01, c02, c11, c12, c22)
    if large > 0.0 and middle > min_planarity * large and (x != 0.0 or y != 0.0 or z != 0.0):
        normals[row, 0] = x
        normals[row, 1] = y
        normals[row, 2] = z
        valid[row] = True


@numba.njit(cache=True, parallel=True, nogil=True)
def _normals_kernel(points, neighbours, min_planarity):  # type: ignore[no-untyped-def]
    n = neighbours.shape[0]
    k = neighbours.shape[1]
    normals = np.zeros((n, 3))
    valid = np.zeros(n, dtype=np.bool_)
    for i in numba.prange(n):
        count = 0
        mx = 0.0
        my = 0.0
        mz = 0.0
        for j in range(k):
            idx = neighbours[i, j]
            if idx >= 0:
                mx += points[idx, 0]
                my += points[idx, 1]
                mz += points[idx, 2]
                count += 1
        if count < 3:
            continue
        mx /= count
        my /= count
        mz /= count
        c00 = 0.0
        c01 = 0.0
        c02 = 0.0
        c11 = 0.0
        c12 = 0.0
        c22 = 0.0
        for j in range(k):
            idx = neighbours[i, j]
            if idx >= 0:
                dx = points[idx, 0] - mx
                dy = points[idx, 1] - my
                dz = points[idx, 2] - mz
                c00 += dx * dx
                c01 += dx * dy
                c02 += dx * dz
                c11 += dy * dy
                c12 += dy * dz
                c22 += dz * dz
        _store_plane_normal(normals, valid, i, c00, c01, c02, c11, c12, c22, min_planarity)
    return normals, valid


def estimate_normals(
    source: nn.NeighbourIndex, queries: FloatArray, k: int, threads: int = 2, min_planarity: float = 0.05
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Unit normal at each query point from a PCA of its k nearest points in ``source``, and which are usable.

    A normal is unusable when its neighbourhood is degenerate (fewer than 3 points) or line-like
    (second eigenvalue below ``min_planarity`` times the largest).
    """
    _, neighbours = source.knn(queries, k)
    with _numba_threads(threads):
        return _normals_kernel(source.points, np.ascontiguousarray(neighbours), float(min_planarity))


@numba.njit(cache=True, nogil=True)
def _cell_moments(points, cell_of, cells):  # type: ignore[no-untyped-def]
    """Per cell: count, sum and sum of outer products of its points (one pass, no neighbour search)."""
    moments = np.zeros((cells, 10))
    for i in range(points.shape[0]):
        c = cell_of[i]
        x = points[i, 0]
        y = points[i, 1]
        z = points[i, 2]
        m = moments[c]
        m[0] += 1.0
        m[1] += x
        m[2] += y
        m[3] += z
        m[4] += x * x
        m[5] += x * y
        m[6] += x * z
        m[7] += y * y
        m[8] += y * z
        m[9] += z * z
    return moments


@numba.njit(cache=True, nogil=True)
def _cell_normals_kernel(moments, min_points, min_planarity):  # type: ignore[no-untyped-def]
    n = moments.shape[0]
    normals = np.zeros((n, 3))
    valid = np.zeros(n, dtype=np.bool_)
    for c in range(n):
        count = moments[c, 0]
        if count < min_points:
            continue
        mx = moments[c, 1] / count
        my = moments[c, 2] / count
        mz = moments[c, 3] / count
        c00 = moments[c, 4] / count - mx * mx
        c01 = moments[c, 5] / count - mx * my
        c02 = moments[c, 6] / count - mx * mz
        c11 = moments[c, 7] / count - my * my
        c12 = moments[c, 8] / count - my * mz
        c22 = moments[c, 9] / count - mz * mz
        _store_plane_normal(normals, valid, c, c00, c01, c02, c11, c12, c22, min_planarity)
    return normals, valid


def cell_normals(
    points: FloatArray, cell_size: float, min_points: int = 4, min_planarity: float = 0.05
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Unit normal at every point from a PCA of the points sharing its ``cell_size`` cube, and which are usable.

    About ten times cheaper than :func:`estimate_normals` on a reduced scan (no k-nearest-neighbour
    query: one pass accumulates each cube's moments), at the price of fewer usable normals (cubes
    across an edge or with fewer than ``min_points`` points are unusable) and cruder ones near
    edges. Sequential registration, which re-estimates nothing and only needs the planes to slide
    along, uses these; relaxation keeps the k-NN normals.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.bool_)
    local = points - points.mean(axis=0)  # moments about a nearby origin keep the covariance exact
    cells = np.floor(local / float(cell_size)).astype(np.int64)
    keys = (cells[:, 0] << 42) + (cells[:, 1] << 21) + cells[:, 2]
    _, cell_of = np.unique(keys, return_inverse=True)
    cell_of = cell_of.ravel()
    moments = _cell_moments(local, cell_of, int(cell_of.max()) + 1)
    normals, valid = _cell_normals_kernel(moments, float(min_points), float(min_planarity))
    return normals[cell_of], valid[cell_of]


class _numba_threads:  # noqa: N801 - used like a function in a with-statement
    """Bound numba's parallel kernels to ``threads`` for the duration of a block (thread-local in numba)."""

    def __init__(self, threads: int) -> None:
        self.threads = max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]

    def __enter__(self) -> None:
        self.previous = numba.get_num_threads()
        numba.set_num_threads(self.threads)

    def __exit__(self, *exc: object) -> None:
        numba.set_num_threads(self.previous)


# ---------------------------------------------------------------- model index


class ModelIndex:
    """Model points with their search structures built once and reused, e.g. for a metascan (the
    union of registered scans) against which many data scans are registered.

    Point-to-point pairs each data point with its closest raw model point. Point-to-plane pairs it
    with the closest point of the *plane sample*, the model reduced to one real point per
    ``normal_voxel_size`` voxel, and takes the plane normal there from the sample's k nearest
    neighbours. The reduction is needed for the normals: scanners sample densely along each scan
    line and sparsely across lines, so the k nearest raw points mostly lie on one line and give no
    plane, while on the reduced sample they spread across lines. Matching against the same sample
    costs nothing in accuracy (the plane, not the sample point, carries the residual) and is about
    30 % faster on the BALM pair. ``normal_voxel_size`` 0 uses the raw points. ``normal_cell`` > 0
    takes the normals from the cubes of that size instead (:func:`cell_normals` over all the model's
    points), so the sample only decides which points are paired.

    Everything is built on first use and cached: point-to-point never pays for normals, and normals
    are estimated only for sample points that actually get paired. One index may serve registrations
    running in several threads: filling the caches is locked.
    """

    def __init__(
        self,
        points: FloatArray,
        normal_neighbours: int = ICPConfig.normal_neighbours,
        normal_voxel_size: float = ICPConfig.normal_voxel_size,
        backend: str = nn.DEFAULT_BACKEND,
        threads: int = 2,
        normal_cell: float = 0.0,
        index: nn.NeighbourIndex | None = None,
    ) -> None:
        points = np.ascontiguousarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"model points must be an (N, 3) array, got shape {points.shape}")
        if len(points) < 3:
            raise RegistrationError(f"model has {len(points)} points; ICP needs at least 3")
        self.points = points
        self.normal_neighbours = int(normal_neighbours)
        self.normal_voxel_size = float(normal_voxel_size)
        self.backend = backend
        self.threads = int(threads)
        self.normal_cell = float(normal_cell)
        self._lock = threading.RLock()
        if index is not None and len(index) != len(points):
            raise ValueError(f"the shared neighbour index has {len(index)} points, the model {len(points)}")
        self._index: nn.NeighbourIndex | None = index
        self._plane_indices: IndexArray | None = None
        self._plane_index: nn.NeighbourIndex | None = None
        self._normals = np.zeros((0, 3))
        self._normal_state = np.zeros(0, dtype=np.int8)  # per sample point: 0 unknown, 1 usable, 2 unusable

    def __len__(self) -> int:
        return len(self.points)

    @property
    def index(self) -> nn.NeighbourIndex:
        """kd-tree over the raw model points."""
        if self._index is None:
            with self._lock:
                if self._index is None:
                    self._index = nn.build_index(self.points, backend=self.backend, threads=self.threads)
        return self._index

    def nearest(self, points: FloatArray, max_distance: float) -> tuple[FloatArray, IndexArray]:
        """Closest raw model point within ``max_distance`` (index -1 where none)."""
        return self.index.nearest(points, max_distance)

    @property
    def plane_indices(self) -> IndexArray:
        """Indices (into ``points``) of the plane sample."""
        self._ensure_plane_sample()
        assert self._plane_indices is not None
        return self._plane_indices

    @property
    def plane_index(self) -> nn.NeighbourIndex:
        """kd-tree over the plane sample (its ``points`` are the sample's coordinates)."""
        self._ensure_plane_sample()
        assert self._plane_index is not None
        return self._plane_index

    def _ensure_plane_sample(self) -> None:
        if self._plane_index is not None:
            return
        with self._lock:
            if self._plane_index is not None:
                return
            if self.normal_voxel_size > 0:
                indices = reduce_points(self.points, self.normal_voxel_size)
            else:
                indices = np.arange(len(self.points), dtype=np.int64)
            self._normals = np.zeros((len(indices), 3))
            self._normal_state = np.zeros(len(indices), dtype=np.int8)
            if self.normal_cell > 0:
                # all cube normals at once (cheaper than any k-NN estimate), from all the model's points;
                # where a cube gives none (too few points, an edge) the k-NN estimate is made on demand
                normals, usable = cell_normals(self.points, self.normal_cell)
                self._normals = normals[indices]
                self._normal_state = usable[indices].astype(np.int8)
            self._plane_indices = indices
            self._plane_index = (
                self.index
                if len(indices) == len(self.points)
                else nn.build_index(self.points[indices], self.backend, self.threads)
            )

    def plane_normals_for(self, sample: IndexArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        """Normals at the given plane-sample points (indices into the sample) and whether each is usable."""
        source = self.plane_index
        sample = np.asarray(sample, dtype=np.int64)
        if (self._normal_state[sample] == 0).any():
            with self._lock:
                missing = np.unique(sample[self._normal_state[sample] == 0])
                if len(missing):
                    normals, usable = estimate_normals(
                        source, source.points[missing], self.normal_neighbours, self.threads
                    )
                    self._normals[missing] = normals
                    self._normal_state[missing] = np.where(usable, 1, 2)
        return self._normals[sample], self._normal_state[sample] == 1

    def plane_normals(self) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """(points, normals, usable) of the whole plane sample, e.g. for drawing the model's normals."""
        normals, usable = self.plane_normals_for(np.arange(len(self.plane_indices)))
        return self.plane_index.points, normals, usable

    def sample_points(self, sample: IndexArray) -> FloatArray:
        """Coordinates of plane-sample points (indices into the sample), in the model's frame."""
        return self.plane_index.points[sample]

    def plane_pairs(
        self, points: FloatArray, max_distance: float
    ) -> tuple[IndexArray, FloatArray, FloatArray, FloatArray]:
        """Point-to-plane pairs of ``points`` (model frame) with the plane sample within ``max_distance``:
        (indices into ``points``, paired sample points, their distances, the sample's normals there).

        Points whose partner has no usable normal (a line, too few neighbours) are left out: what
        ICP, loop verification and the workbench's edge residuals all pair with.
        """
        dist, idx = self.plane_index.nearest(points, max_distance)
        found = np.flatnonzero(idx >= 0)
        normals, usable = self.plane_normals_for(idx[found])
        found = found[usable]
        return found, self.sample_points(idx[found]), dist[found], normals[usable]

    def plane_residuals(self, points: FloatArray, max_distance: float) -> FloatArray:
        """Signed point-to-plane distances of the :meth:`plane_pairs` of ``points``: how far the
        points that pair lie off the model's surface, whatever the scans' point spacing."""
        found, partners, _, normals = self.plane_pairs(points, max_distance)
        return np.einsum("ij,ij->i", points[found] - partners, normals)


class StackedModel(ModelIndex):
    """Several scans, each with its own kd-trees and normals in its own frame, placed by poses: a
    metascan that costs nothing to build.

    A metascan rebuilt as one union for every registered scan (a kd-tree over all points, normals
    moved into the world) cost more than the matching itself. Here each data point is looked up in
    every member (moved into that member's frame) and keeps the closest hit; the members' trees and
    normals were built once, when their scans were added. The model frame is the world. Indices
    number the members' raw points (``nearest``) or plane samples (``plane_index``) one member
    after the other.
    """

    def __init__(self, members: Sequence[ModelIndex], poses: Sequence[FloatArray]) -> None:
        if not members or len(members) != len(poses):
            raise ValueError("a stacked model needs one pose per member and at least one member")
        self.members = list(members)
        self._poses = [np.asarray(p, dtype=np.float64) for p in poses]
        self._inverse = [invert(p) for p in self._poses]
        self.normal_neighbours = self.members[0].normal_neighbours
        self.normal_voxel_size = self.members[0].normal_voxel_size
        self.normal_cell = self.members[0].normal_cell
        self.backend = self.members[0].backend
        self.threads = self.members[0].threads
        self._lock = threading.RLock()
        self._points: FloatArray | None = None
        self._raw = _StackedSearch(self, plane=False)
        self._sample = _StackedSearch(self, plane=True)

    @property
    def points(self) -> FloatArray:  # type: ignore[override]
        """All members' points in the world frame (assembled on first use: point-to-plane never needs it)."""
        if self._points is None:
            self._points = np.concatenate(
                [transform_points(p, m.points) for m, p in zip(self.members, self._poses, strict=True)]
            )
        return self._points

    def __len__(self) -> int:
        return len(self._raw)

    @property
    def index(self) -> nn.NeighbourIndex:
        return self._raw

    def nearest(self, points: FloatArray, max_distance: float) -> tuple[FloatArray, IndexArray]:
        return self._raw.nearest(points, max_distance)

    @property
    def plane_indices(self) -> IndexArray:
        return np.concatenate([o + m.plane_indices for o, m in zip(self._raw.offsets[:-1], self.members, strict=True)])

    @property
    def plane_index(self) -> nn.NeighbourIndex:
        return self._sample

    def sample_points(self, sample: IndexArray) -> FloatArray:
        """World coordinates of plane-sample points, without assembling the whole stack."""
        out = np.empty((len(sample), 3))
        for k, chosen, local in self._sample.split(sample):
            out[chosen] = transform_points(self._poses[k], self.members[k].plane_index.points[local])
        return out

    def plane_normals_for(self, sample: IndexArray) -> tuple[FloatArray, NDArray[np.bool_]]:
        sample = np.asarray(sample, dtype=np.int64)
        normals = np.zeros((len(sample), 3))
        usable = np.zeros(len(sample), dtype=np.bool_)
        for k, chosen, local in self._sample.split(sample):
            part, ok = self.members[k].plane_normals_for(local)
            normals[chosen] = part @ self._poses[k][:3, :3].T
            usable[chosen] = ok
        return normals, usable

    def plane_normals(self) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        sample = np.arange(len(self._sample), dtype=np.int64)
        normals, usable = self.plane_normals_for(sample)
        return self.sample_points(sample), normals, usable


class _StackedSearch(nn.NeighbourIndex):
    """Closest point over a :class:`StackedModel`'s members (raw points or plane samples): each
    member's own tree, the closest hit wins."""

    name = "stacked"

    def __init__(self, model: StackedModel, plane: bool) -> None:  # no tree of its own
        self.model = model
        self.plane = plane
        self.threads = model.threads
        sizes = [len(m.plane_indices) if plane else len(m.points) for m in model.members]
        self.offsets = np.cumsum([0, *sizes])

    def __len__(self) -> int:
        return int(self.offsets[-1])

    @property
    def points(self) -> FloatArray:  # type: ignore[override]
        if self.plane:
            return self.model.sample_points(np.arange(len(self), dtype=np.int64))
        return self.model.points

    def split(self, indices: IndexArray) -> Iterator[tuple[int, NDArray[np.bool_] | slice, IndexArray]]:
        """(member, which of ``indices`` are its (a mask, or all of them), their indices within it) for each member hit."""
        if len(self.model.members) == 1:  # the usual metascan of one scan: no search, no masks
            if len(indices):
                yield 0, slice(None), indices
            return
        member = np.searchsorted(self.offsets, indices, side="right") - 1
        for k in range(len(self.model.members)):
            chosen = member == k
            if chosen.any():
                yield k, chosen, indices[chosen] - self.offsets[k]

    def nearest(self, queries: FloatArray, max_distance: float) -> tuple[FloatArray, IndexArray]:
        if len(self.model.members) == 1:
            member = self.model.members[0]
            tree = member.plane_index if self.plane else member.index
            return tree.nearest(transform_points(self.model._inverse[0], queries), max_distance)
        best_d = np.full(len(queries), np.inf)
        best_i = np.full(len(queries), -1, dtype=np.int64)
        for k, m in enumerate(self.model.members):
            tree = m.plane_index if self.plane else m.index
            d, i = tree.nearest(transform_points(self.model._inverse[k], queries), max_distance)
            closer = d < best_d
            best_d[closer] = d[closer]
            best_i[closer] = i[closer] + self.offsets[k]
        return best_d, best_i

    def knn(self, queries: FloatArray, k: int) -> tuple[FloatArray, IndexArray]:
        raise NotImplementedError("a stacked model answers closest-point queries only")


def _as_model(model: ModelIndex | FloatArray, config: ICPConfig) -> ModelIndex:
    if isinstance(model, ModelIndex):
        return model
    return ModelIndex(
        model,
        normal_neighbours=config.normal_neighbours,
        normal_voxel_size=config.normal_voxel_size,
        backend=config.nn_backend,
        threads=config.threads,
    )


def _as_data(data: FloatArray) -> FloatArray:
    data = np.ascontiguousarray(data, dtype=np.float64)
    if data.ndim != 2 or data.shape[1] != 3:
        raise ValueError(f"data points must be an (N, 3) array, got shape {data.shape}")
    return data


def _as_transform(transform: FloatArray) -> FloatArray:
    """A float64 copy; a rotation that is not quite orthonormal (poses stored with few digits) is
    replaced by the nearest rotation, so that the result stays a rigid motion."""
    t = np.array(transform, dtype=np.float64)
    if t.shape != (4, 4):
        raise ValueError(f"transform must be 4x4, got shape {t.shape}")
    r = t[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-12:
        u, _, vt = np.linalg.svd(r)
        if np.linalg.det(u @ vt) < 0:
            raise ValueError("transform's 3x3 part is a reflection, not a rotation")
        t[:3, :3] = u @ vt
    return t


# ---------------------------------------------------------------- the two error metrics


def point_to_point_step(data: FloatArray, model: FloatArray) -> FloatArray:
    """Rigid motion minimising sum |R d + t - m|² over paired points (Arun et al.: SVD of the cross-covariance)."""
    dc = data.mean(axis=0)
    mc = model.mean(axis=0)
    h = (data - dc).T @ (model - mc)
    u, _, vt = np.linalg.svd(h)
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0  # guard against a reflection on degenerate sets
    rotation = vt.T @ d @ u.T
    return make_pose(rotation, mc - rotation @ dc)


def point_to_plane_step(data: FloatArray, model: FloatArray, normals: FloatArray) -> FloatArray:
    """Small rigid motion minimising sum ((R d + t - m)·n)², linearised (R ≈ I + [ω]×) and solved in one go.

    Solved about the centroid of the data pairs, which keeps the 6x6 system well conditioned when the
    scan sits far from the origin (a metascan in world coordinates).
    """
    centre = data.mean(axis=0)
    p = data - centre
    q = model - centre
    residual = np.einsum("ij,ij->i", p - q, normals)
    jac = np.empty((len(p), 6))
    jac[:, :3] = np.cross(p, normals)
    jac[:, 3:] = normals
    a = jac.T @ jac
    b = -(jac.T @ residual)
    try:
        x = np.linalg.solve(a, b)
    except np.linalg.LinAlgError:
        x = np.linalg.lstsq(a, b, rcond=None)[0]
    rotation = axis_angle_to_rotation(x[:3])
    # the update is about `centre`: p' = R (p - c) + c + t
    return make_pose(rotation, centre + x[3:] - rotation @ centre)


# ---------------------------------------------------------------- ICP


def _pairs(
    model: ModelIndex, moved: FloatArray, max_distance: float, point_to_plane: bool
) -> tuple[IndexArray, FloatArray, FloatArray, FloatArray | None]:
    """(data_idx, paired model points, distances, model normals or None).

    Point-to-plane pairs with the plane sample and drops pairs whose normal is unusable.
    """
    if not point_to_plane:
        dist, idx = model.nearest(moved, max_distance)
        data_idx = np.flatnonzero(idx >= 0)
        return data_idx, model.points[idx[data_idx]], dist[data_idx], None
    return model.plane_pairs(moved, max_distance)


def icp_iterations(
    model: ModelIndex | FloatArray,
    data: FloatArray,
    initial: FloatArray = np.eye(4),
    config: ICPConfig = ICPConfig(),
) -> Iterator[ICPIteration]:
    """Run ICP one step at a time (see the module docstring for the convergence rule).

    Raises :class:`RegistrationError` when a step finds fewer than ``config.min_pairs`` pairs.
    """
    return _iterate(_as_model(model, config), _prepare_data(data, config), _as_transform(initial), config)


def _prepare_data(data: FloatArray, config: ICPConfig) -> FloatArray:
    data = _as_data(data)
    if config.data_voxel_size > 0 and len(data):
        data = data[reduce_points(data, config.data_voxel_size)]
    return data


def _small(motion: FloatArray, tolerance: float) -> bool:
    return float(np.linalg.norm(motion[:3, 3])) <= tolerance and rotation_angle(motion[:3, :3]) <= tolerance


def _settled(steps: list[FloatArray], tolerance: float) -> bool:
    """Whether the newest pose is within ``tolerance`` of one of the previous ``_CYCLE`` poses of the stage.

    The motion from ``T_{k-m}`` to ``T_k`` is the product of the last m steps. Composing the steps
    (always exact rotations) rather than comparing poses keeps the test exact even when the initial
    pose came from a file with a slightly non-orthonormal rotation.
    """
    motion = np.eye(4)
    for step in reversed(steps[-_CYCLE:]):
        motion = motion @ step
        if _small(motion, tolerance):
            return True
    return False


def _iterate(model: ModelIndex, data: FloatArray, transform: FloatArray, config: ICPConfig) -> Iterator[ICPIteration]:
    point_to_plane = config.method == "point_to_plane"
    stages = config.stages()
    stage = 0
    steps: list[FloatArray] = []  # updates of the current stage, newest last
    for index in range(config.max_iterations):
        max_distance = stages[stage]
        last_stage = stage == len(stages) - 1
        tolerance = config.epsilon if last_stage else max(config.epsilon, config.stage_epsilon)
        moved = transform_points(transform, data)
        data_idx, paired_model, dist, normals = _pairs(model, moved, max_distance, point_to_plane)
        if len(data_idx) < config.min_pairs:
            usable = " with a usable model normal" if point_to_plane else ""
            raise RegistrationError(
                f"ICP iteration {index}: only {len(data_idx)} of {len(data)} data points have a model point"
                f"{usable} within {max_distance:g} m (need {config.min_pairs}); the scans do not overlap"
                " enough or the initial pose is too far off"
            )
        rms = float(np.sqrt(np.mean(dist * dist)))
        if normals is not None:
            step = point_to_plane_step(moved[data_idx], paired_model, normals)
        else:
            step = point_to_point_step(moved[data_idx], paired_model)
        transform = step @ transform
        step_t = float(np.linalg.norm(step[:3, 3]))
        step_r = rotation_angle(step[:3, :3])
        steps.append(step)
        stage_done = _settled(steps, tolerance)
        finished = stage_done and last_stage
        yield ICPIteration(
            index=index,
            transform=transform.copy(),
            pairs=len(data_idx),
            rms=rms,
            max_distance=max_distance,
            step_translation=step_t,
            step_rotation=step_r,
            converged=finished,
        )
        if finished:
            return
        if stage_done:
            stage += 1
            steps = []


def icp(
    model: ModelIndex | FloatArray,
    data: FloatArray,
    initial: FloatArray = np.eye(4),
    config: ICPConfig = ICPConfig(),
) -> ICPResult:
    """Register ``data`` to ``model``: returns model_from_data and the per-iteration trace."""
    data = _prepare_data(data, config)
    iterations = list(_iterate(_as_model(model, config), data, _as_transform(initial), config))
    return ICPResult.from_iterations(iterations, len(data), config.method)


def count_pairs(model: ModelIndex | FloatArray, data: FloatArray, transform: FloatArray, max_distance: float) -> int:
    """How many data points, placed by ``transform``, have a model point within ``max_distance``."""
    model = model if isinstance(model, ModelIndex) else ModelIndex(model)
    _, idx = model.nearest(transform_points(_as_transform(transform), _as_data(data)), max_distance)
    return int(np.count_nonzero(idx >= 0))


def correspondences(
    model: ModelIndex | FloatArray, data: FloatArray, transform: FloatArray, max_distance: float, limit: int = 2000
) -> tuple[IndexArray, IndexArray]:
    """Closest-point pairs (data_idx, model_idx) within ``max_distance``, at most ``limit`` of them,
    spread evenly over the data so a drawing of them shows the whole overlap."""
    model = model if isinstance(model, ModelIndex) else ModelIndex(model)
    _, idx = model.nearest(transform_points(_as_transform(transform), _as_data(data)), max_distance)
    data_idx = np.flatnonzero(idx >= 0)
    if limit >= 0 and len(data_idx) > limit:
        data_idx = data_idx[np.linspace(0, len(data_idx) - 1, limit).round().astype(np.int64)]
    return data_idx, idx[data_idx]
