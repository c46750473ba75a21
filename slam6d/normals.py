"""Surface normals of a point cloud, for point-to-plane matching: two estimators of one idea.

Both fit a plane to a neighbourhood by PCA (the normal is the eigenvector of the smallest eigenvalue
of the points' covariance, in closed form) and mark a normal unusable where the neighbourhood is
degenerate or line-like, since a scan line alone gives no plane. :func:`estimate_normals` takes each
point's k nearest neighbours; :func:`cell_normals` the points sharing its cube, about ten times
cheaper (one pass of moments, no neighbour query), for the registration of many scans in a row.

Why the cubes grow (multi-beam lidar). A VLP-16 on a car meets the ground with its lowest beam ~7 m
out and its rings lie 1-3 m apart there; on walls 10-20 m away its rings are 0.35-0.7 m apart. A
0.4 m cube therefore holds one ring: a line. Without range noise a line fails the planarity test;
with the sensor's 3 cm of noise along the beams it passes (middle / large eigenvalue ~0.07 > 0.05),
and the "plane" it gives contains the beam, so a ground normal leans by the beam's depression angle
(median 11°, the ring-sampled ground of ``tests/test_normals.py``: 9°). Where the cube gave
nothing, the registration model's k-NN fallback on the 0.2 m plane sample takes 12 neighbours along
the same ring and fails the same way. This is the cause of the simulated campus's roll/pitch drift,
measured by ``benchmarks/scale.py --per-step 100``: ICP started at the *true* relative pose of each
consecutive pair moves away from it by 0.25° roll and 0.25° pitch RMS per step (1.6 cm in height)
with these normals, 62 % of which are more than 5° off the true surface; with the simulator's exact
surface normals at the same pairs it moves 0.05° and 0.03° (0.4 cm). The pairing, the data
reduction and the distance stages are not it (each changed moves the per-step error by < 0.05°).

So a cube holds a plane only when its points spread across it in a second direction by more than a
scan line's noise does (``CELL_MIN_SPREAD``) and lie on one surface (``CELL_MAX_THICKNESS``), and a
point whose 0.4 m cube holds no plane takes the plane of the cube twice, four or eight times as
large, which spans two rings: the cube normals of the ring-sampled ground are level (95 % within
0.3°, was 9° off). That alone barely moves the campus's per-step error (0.24° / 0.23°), because the
k-NN fallback still serves half the pairs; without the fallback the error from the truth drops to
0.18° / 0.18°, but the pairs lost on walls double the yaw error and the 100-scan registration ends
51 cm off instead of 9-13 cm, so the fallback stays. What the cubes and the fallback still get
wrong is mostly on crowns, poles and corners, where one or two rings are fitted; sequential
registration now takes such scans' normals (and pairs) from the last three scans fused into one
model, whose rings interleave (:func:`slam6d.model.fused_model`; per-step tilt 0.24° -> 0.10°;
docs/scale.md, "The rings' own planes"). Dense scanners (the seed's SICK fan, BALM's hall) find
their plane in the smallest cube, as before, and are not fused.

What the cubes cannot fix (dense scanners, short steps). Far from a rotating SICK its scan lines
lie 0.4-0.8 m apart, and a cube there spans lines of different surfaces or of a curved one; on the
dense simulated loop scanned 400 times such normals help pull every 24 cm step short, towards zero
motion. Measured on its first 80 scans, each matched from the truth: 0.35 cm short per step with
these normals, still 0.25 cm with the simulator's exact surface normals at the same points, since
a data point between two of the model's lines pairs with a closest point on another surface. A
test for cubes holding two lines (their points' kurtosis along the middle eigenvector: 1.0 for two
lines) changed nothing; an absolute cap on a cube's thickness (1 cm RMS) left 0.19 cm, and
0.06 cm only without the k-NN fallback, which lost 45 % of the pairs. The residuals are the handle
instead (``ICPConfig.residual_gate`` and ``robust_scale``; docs/scale.md, "Short steps").
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numpy.typing import NDArray

from slam6d import nn

FloatArray = NDArray[np.float64]

CELL_LEVELS = 4  # cube sizes tried per point by cell_normals: 1, 2, 4, 8 x the cell size
CELL_MIN_SPREAD = 0.25  # middle eigenvalue >= this x a fully covered cube's (size**2 / 12)
CELL_MAX_THICKNESS = 0.1  # small eigenvalue <= this x the middle one
# a cube's plane that passes within this many of its own RMS thicknesses of the scanner is no surface
THROUGH_SCANNER = 3.0


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
def _store_plane_normal(normals, valid, row, c00, c01, c02, c11, c12, c22, min_planarity, min_middle, max_thickness):  # type: ignore[no-untyped-def]
    """Normal of a covariance into ``normals[row]`` when the points form a plane. A neighbourhood
    along a single scan line is a line, not a plane (middle eigenvalue ~0): its "normal" is arbitrary,
    so it is left invalid - one rule for every normal estimator. ``min_middle`` (an absolute floor
    of the middle eigenvalue) and ``max_thickness`` (of small / middle) are the cubes' further tests
    (:func:`cell_normals`); the k-NN estimate passes 0 and 1, which test nothing."""
    x, y, z, small, middle, large = _smallest_eigenvector(c00, c01, c02, c11, c12, c22)
    planar = large > 0.0 and middle > min_planarity * large and middle >= min_middle
    if planar and small <= max_thickness * middle and (x != 0.0 or y != 0.0 or z != 0.0):
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
        _store_plane_normal(normals, valid, i, c00, c01, c02, c11, c12, c22, min_planarity, 0.0, 1.0)
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
def _cell_normals_kernel(moments, min_points, min_planarity, min_middle, max_thickness):  # type: ignore[no-untyped-def]
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
        _store_plane_normal(normals, valid, c, c00, c01, c02, c11, c12, c22, min_planarity, min_middle, max_thickness)
    return normals, valid


def cell_normals(
    points: FloatArray,
    cell_size: float,
    min_points: int = 4,
    min_planarity: float = 0.05,
    levels: int = CELL_LEVELS,
    min_spread: float = CELL_MIN_SPREAD,
    max_thickness: float = CELL_MAX_THICKNESS,
    level_out: NDArray[np.int8] | None = None,
    viewpoint: FloatArray | None = None,
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """Unit normal at every point from a PCA of the points sharing its cube, and which are usable.

    About ten times cheaper than :func:`estimate_normals` on a reduced scan (no k-nearest-neighbour
    query: one pass accumulates each cube's moments per level). Sequential registration, which
    re-estimates nothing and only needs the planes to slide along, uses these; relaxation keeps the
    k-NN normals.

    A point takes the normal of its ``cell_size`` cube when that cube holds a plane, else of the
    cube twice as large, up to ``levels`` sizes (see the module docstring for why multi-beam scans
    need the larger ones). A cube holds a plane when (eigenvalues of its points' covariance
    ``small <= middle <= large``) ``middle > min_planarity * large`` (not a line),
    ``middle >= min_spread * size**2 / 12`` (the points spread across the cube in a second direction
    by more than a scan line's range noise does: a whole cube covered has ``size**2 / 12``) and
    ``small <= max_thickness * middle`` (one flat surface, not two meeting in an edge). Points
    whose cubes are unusable at every level are marked unusable. ``level_out`` (one per point), when
    given, receives the level each normal came from: 1 for ``cell_size``, 2 for twice that, ...,
    0 for none.

    ``viewpoint``: where the scanner stood, in the points' frame (None: unknown, no test). A cube
    whose plane passes through it holds no plane at all: a scanner cannot see a surface it stands
    in, and what fits one is a band of rings. A multi-beam lidar sees nearby vertical surfaces only
    within its vertical field of view, a horizontal band at its own height (a VLP-16 held at 1.4 m:
    ±0.23 m at 0.85 m away); a 1.6 m cube holding that band across a corner or a cabinet's two sides
    is flat in height and wide both ways, so it passes the tests above as a level plane through the
    scanner, and its points on the vertical surfaces take a vertical normal. Those pairs tie the
    scan's height to the rings' height: ICP from the truth of indoor VLP-16 seed 2's scan 5 (30
    scans) slid to a second minimum 22 cm lower from any start 5-30 cm below the truth. Such cubes
    are left to the next level and the k-NN fallback.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    if len(points) == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.bool_)
    centre = points.mean(axis=0)
    local = points - centre  # moments about a nearby origin keep the covariance exact
    scanner = None if viewpoint is None else np.asarray(viewpoint, dtype=np.float64).reshape(3) - centre
    normals = np.zeros((len(points), 3))
    valid = np.zeros(len(points), dtype=np.bool_)
    size = float(cell_size)
    if level_out is not None:
        level_out[:] = 0
    for level in range(1, max(1, int(levels)) + 1):
        todo = np.flatnonzero(~valid)
        if len(todo) == 0:
            break
        cells = np.floor(local / size).astype(np.int64)  # every point counts, also those placed already
        keys = (cells[:, 0] << 42) + (cells[:, 1] << 21) + cells[:, 2]
        unique, cell_of = np.unique(keys, return_inverse=True)
        cell_of = cell_of.ravel()
        moments = _cell_moments(local, cell_of, len(unique))
        floor = float(min_spread) * size * size / 12.0
        cube_normals, cube_valid = _cell_normals_kernel(
            moments, float(min_points), float(min_planarity), floor, float(max_thickness)
        )
        if scanner is not None:
            cube_valid &= ~_through(moments, cube_normals, scanner)
        normals[todo] = cube_normals[cell_of[todo]]
        valid[todo] = cube_valid[cell_of[todo]]
        if level_out is not None:
            level_out[todo[valid[todo]]] = level
        size *= 2.0
    return normals, valid


def _through(moments: FloatArray, normals: FloatArray, scanner: FloatArray) -> NDArray[np.bool_]:
    """Whether each cube's plane (its points' ``moments``, its ``normals``) passes through the
    ``scanner``: within ``THROUGH_SCANNER`` times the plane's own RMS thickness (the points' spread
    along the normal) of it. See :func:`cell_normals` for why such a plane is no surface."""
    count = np.maximum(moments[:, 0], 1.0)
    mean = moments[:, 1:4] / count[:, None]
    second = moments[:, [4, 5, 6, 5, 7, 8, 6, 8, 9]].reshape(-1, 3, 3) / count[:, None, None]
    covariance = second - mean[:, :, None] * mean[:, None, :]
    thickness = np.sqrt(np.maximum(np.einsum("ni,nij,nj->n", normals, covariance, normals), 0.0))
    return np.abs(np.einsum("ni,ni->n", mean - scanner, normals)) <= THROUGH_SCANNER * thickness


class _numba_threads:  # noqa: N801 - used like a function in a with-statement
    """Bound numba's parallel kernels to ``threads`` for the duration of a block (thread-local in numba)."""

    def __init__(self, threads: int) -> None:
        self.threads = max(1, min(int(threads), numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]

    def __enter__(self) -> None:
        self.previous = numba.get_num_threads()
        numba.set_num_threads(self.threads)

    def __exit__(self, *exc: object) -> None:
        numba.set_num_threads(self.previous)
