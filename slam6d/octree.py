"""Voxel reduction and a multi-resolution octree of occupied cubes.

Both ICP and the octree initial guess work on a cloud discretised into cubes: ICP wants one point
per cube so that dense regions near the scanner do not dominate the error, and the initial guess
scores a candidate pose by how many data cubes land in occupied model cubes. Cubes are addressed by
integer cell coordinates packed into one int64 (21 bits per axis), so set operations on cubes are
integer operations. Lookups use a small open-addressing hash table compiled with numba: a scan of
100k points is reduced in about a millisecond, and the search scores hundreds of millions of
(point, candidate) pairs per second.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numba
import numpy as np
from numpy.typing import NDArray

from slam6d.errors import EmptyScanError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

BITS_PER_AXIS = 21
CELLS_PER_AXIS = 1 << BITS_PER_AXIS
_EMPTY = np.int64(-1)


def as_points(points: FloatArray, what: str = "points") -> FloatArray:
    array = np.ascontiguousarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{what} must be an (N, 3) array, got shape {array.shape}")
    if len(array) == 0:
        raise EmptyScanError(f"{what}: no points")
    return array


def _check_size(size: float, what: str = "voxel_size") -> float:
    size = float(size)
    if not (math.isfinite(size) and size > 0.0):
        raise ValueError(f"{what} must be a positive finite number, got {size}")
    return size


def cell_coordinates(points: FloatArray, origin: FloatArray, cube_size: float) -> IntArray:
    """Integer cell of each point in a grid of ``cube_size`` cubes whose corner cell 0 sits at ``origin``."""
    return np.floor((points - origin) / cube_size).astype(np.int64)


def pack_cells(cells: IntArray) -> IntArray:
    """One int64 key per cell; cells outside ``[0, 2**21)`` on any axis get the key -1 (never occupied)."""
    cells = np.asarray(cells, dtype=np.int64)
    valid = np.all((cells >= 0) & (cells < CELLS_PER_AXIS), axis=1)
    keys = (cells[:, 0] << (2 * BITS_PER_AXIS)) | (cells[:, 1] << BITS_PER_AXIS) | cells[:, 2]
    return np.where(valid, keys, _EMPTY)


def unpack_keys(keys: IntArray) -> IntArray:
    mask = CELLS_PER_AXIS - 1
    keys = np.asarray(keys, dtype=np.int64)
    return np.stack([(keys >> (2 * BITS_PER_AXIS)) & mask, (keys >> BITS_PER_AXIS) & mask, keys & mask], axis=1)


# ---------------------------------------------------------------- hash table on packed keys (numba)


@numba.njit(cache=True, inline="always")
def _slot(key: np.int64, mask: np.int64) -> np.int64:
    # splitmix64 finaliser: cells of a coarse grid differ in a few low bits per axis, which a plain
    # multiplicative hash leaves clustered; full avalanche keeps the probe chains short
    z = np.uint64(key)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return np.int64(z ^ (z >> np.uint64(31))) & mask


def _table_size(count: int) -> int:
    """Power of two at least twice the number of keys, so linear probing stays short."""
    return 1 << max(4, math.ceil(math.log2(max(count, 1) * 2 + 1)))


@numba.njit(cache=True, nogil=True)
def _build_table(keys: IntArray, size: np.int64) -> IntArray:
    table = np.full(size, -1, dtype=np.int64)
    mask = size - 1
    for key in keys:
        slot = _slot(key, mask)
        while table[slot] != -1 and table[slot] != key:
            slot = (slot + 1) & mask
        table[slot] = key
    return table


@numba.njit(cache=True, inline="always")
def contains_key(table: IntArray, key: np.int64) -> bool:
    mask = np.int64(len(table) - 1)
    slot = _slot(key, mask)
    while True:
        entry = table[slot]
        if entry == key:
            return True
        if entry == -1:
            return False
        slot = (slot + 1) & mask


@numba.njit(cache=True, nogil=True)
def _contains_many(table: IntArray, keys: IntArray) -> NDArray[np.bool_]:
    out = np.zeros(len(keys), dtype=np.bool_)
    for i in range(len(keys)):
        if keys[i] >= 0:
            out[i] = contains_key(table, keys[i])
    return out


@numba.njit(cache=True, nogil=True)
def _closest_per_cell(points: FloatArray, lower: FloatArray, voxel_size: float, size: np.int64) -> NDArray[np.bool_]:
    """Mark, for every occupied voxel, the point nearest its centre (lowest index on ties).

    One fused pass (cell, key, distance, hash) instead of several numpy temporaries: this is what
    keeps a 100k-point scan at a few milliseconds.
    """
    slots = np.full((size, 2), -1, dtype=np.int64)  # (key, best index) side by side for cache locality
    best_dist = np.empty(size, dtype=np.float64)
    mask = size - 1
    inverse = 1.0 / voxel_size
    for i in range(points.shape[0]):
        key = np.int64(0)
        dist = 0.0
        for axis in range(3):
            scaled = (points[i, axis] - lower[axis]) * inverse
            cell = np.floor(scaled)
            offset = scaled - cell - 0.5
            dist += offset * offset
            key = (key << BITS_PER_AXIS) | np.int64(cell)
        slot = _slot(key, mask)
        while slots[slot, 0] != -1 and slots[slot, 0] != key:
            slot = (slot + 1) & mask
        if slots[slot, 0] == -1:
            slots[slot, 0] = key
            slots[slot, 1] = i
            best_dist[slot] = dist
        elif dist < best_dist[slot]:
            slots[slot, 1] = i
            best_dist[slot] = dist
    keep = np.zeros(points.shape[0], dtype=np.bool_)
    for kept in range(size):
        if slots[kept, 1] >= 0:
            keep[slots[kept, 1]] = True
    return keep


TILE_BITS = 2  # a tile is 4 x 4 x 4 cubes, one bit each in a 64-bit mask


@numba.njit(cache=True, nogil=True)
def _build_tiles(keys: IntArray, size: np.int64) -> tuple[IntArray, NDArray[np.uint64]]:
    """Hash map from a tile (the packed key of a cube's cell coordinates shifted right by
    ``TILE_BITS``) to the bit mask of the occupied cubes among its 4 x 4 x 4."""
    table = np.full(size, -1, dtype=np.int64)
    masks = np.zeros(size, dtype=np.uint64)
    mask = size - 1
    axis_mask = np.int64(CELLS_PER_AXIS - 1)
    low = np.int64((1 << TILE_BITS) - 1)
    for key in keys:
        i = (key >> (2 * BITS_PER_AXIS)) & axis_mask
        j = (key >> BITS_PER_AXIS) & axis_mask
        k = key & axis_mask
        tile = ((i >> TILE_BITS) << (2 * BITS_PER_AXIS)) | ((j >> TILE_BITS) << BITS_PER_AXIS) | (k >> TILE_BITS)
        bit = ((i & low) << (2 * TILE_BITS)) | ((j & low) << TILE_BITS) | (k & low)
        slot = _slot(tile, mask)
        while table[slot] != -1 and table[slot] != tile:
            slot = (slot + 1) & mask
        table[slot] = tile
        masks[slot] |= np.uint64(1) << np.uint64(bit)
    return table, masks


@numba.njit(cache=True, inline="always")
def _tile_mask(table: IntArray, masks: NDArray[np.uint64], tile: np.int64) -> np.uint64:
    mask = np.int64(len(table) - 1)
    slot = _slot(tile, mask)
    while True:
        entry = table[slot]
        if entry == tile:
            return masks[slot]
        if entry == -1:
            return np.uint64(0)
        slot = (slot + 1) & mask


def _bit_tables() -> tuple[NDArray[np.uint64], NDArray[np.uint64], NDArray[np.uint64], NDArray[np.int64]]:
    """Masks of a tile's bits whose x (resp. y, z) cell lies in ``lo..hi`` (``[lo, hi]`` indexes the
    tables), and the de Bruijn table that turns a tile's lowest set bit into its index."""
    side = 1 << TILE_BITS
    tables = [np.zeros((side, side), dtype=np.uint64) for _ in range(3)]
    for bit in range(side**3):
        cell = (bit >> (2 * TILE_BITS), (bit >> TILE_BITS) & (side - 1), bit & (side - 1))
        for axis in range(3):
            for lo in range(side):
                for hi in range(lo, side):
                    if lo <= cell[axis] <= hi:
                        tables[axis][lo, hi] |= np.uint64(1 << bit)
    de_bruijn = np.zeros(64, dtype=np.int64)
    for bit in range(64):
        de_bruijn[((1 << bit) * _DE_BRUIJN & 0xFFFFFFFFFFFFFFFF) >> 58] = bit
    return tables[0], tables[1], tables[2], de_bruijn


_DE_BRUIJN = 0x03F79D71B4CB0A89
_X_BITS, _Y_BITS, _Z_BITS, _BIT_INDEX = _bit_tables()


@numba.njit(cache=True, nogil=True)
def _count_hits(
    points: FloatArray,
    rotations: FloatArray,
    pivot: FloatArray,
    origin: FloatArray,
    cube_size: float,
    lo: NDArray[np.int64],
    dims: NDArray[np.int64],
    table: NDArray[np.int64],
    masks: NDArray[np.uint64],
    x_bits: NDArray[np.uint64],
    y_bits: NDArray[np.uint64],
    z_bits: NDArray[np.uint64],
    bit_index: NDArray[np.int64],
) -> NDArray[np.int32]:
    """scores[r, s] = how many ``R_r (p - pivot) + pivot`` moved by shift ``s`` are occupied, for every
    shift ``s`` of the box ``lo .. lo + dims - 1`` (flat C order over x, y, z).

    Counted from the model's side: per point, each tile that the box of its shifted cells touches is
    looked up once, its bits outside the box are masked off, and each occupied cube left adds one to
    the shift that lands the point on it. Surfaces fill a few dozen of a 5 x 5 x 5 box's 125 cubes,
    so this visits far fewer cubes than a test per shift would. Serial on purpose: a level is a few
    milliseconds of work, and a parallel region's thread start and barrier cost more than that
    whenever the other core is busy (the pipeline prepares the next scans on it meanwhile); on a
    loaded 2-core machine it made each call several times slower in wall time and 1.6x in CPU time.
    """
    n_rot = rotations.shape[0]
    dx, dy, dz = dims[0], dims[1], dims[2]
    scores = np.zeros((n_rot, dx * dy * dz), dtype=np.int32)
    inverse = 1.0 / cube_size
    tile_limit = CELLS_PER_AXIS >> TILE_BITS
    side = np.int64(1 << TILE_BITS)
    for r in range(n_rot):
        rot = rotations[r]
        row = scores[r]
        for p in range(points.shape[0]):
            x = points[p, 0] - pivot[0]
            y = points[p, 1] - pivot[1]
            z = points[p, 2] - pivot[2]
            # the box of this point's shifted cells, in global cells
            bx = np.int64(np.floor((rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + pivot[0] - origin[0]) * inverse))
            by = np.int64(np.floor((rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + pivot[1] - origin[1]) * inverse))
            bz = np.int64(np.floor((rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + pivot[2] - origin[2]) * inverse))
            bx += lo[0]
            by += lo[1]
            bz += lo[2]
            # arithmetic shifts floor negative cells too; tiles outside the grid hold nothing
            for ti in range(max(bx >> TILE_BITS, 0), min((bx + dx - 1) >> TILE_BITS, tile_limit - 1) + 1):
                gx = ti << TILE_BITS
                xm = x_bits[max(bx - gx, 0), min(bx + dx - 1 - gx, side - 1)]
                for tj in range(max(by >> TILE_BITS, 0), min((by + dy - 1) >> TILE_BITS, tile_limit - 1) + 1):
                    gy = tj << TILE_BITS
                    xym = xm & y_bits[max(by - gy, 0), min(by + dy - 1 - gy, side - 1)]
                    for tk in range(max(bz >> TILE_BITS, 0), min((bz + dz - 1) >> TILE_BITS, tile_limit - 1) + 1):
                        gz = tk << TILE_BITS
                        tile = np.int64((ti << (2 * BITS_PER_AXIS)) | (tj << BITS_PER_AXIS) | tk)
                        bits = _tile_mask(table, masks, tile)
                        bits &= xym & z_bits[max(bz - gz, 0), min(bz + dz - 1 - gz, side - 1)]
                        while bits:
                            lowest = bits & (~bits + np.uint64(1))
                            bit = bit_index[np.int64((lowest * np.uint64(_DE_BRUIJN)) >> np.uint64(58))]
                            sx = gx + (bit >> (2 * TILE_BITS)) - bx
                            sy = gy + ((bit >> TILE_BITS) & (side - 1)) - by
                            sz = gz + (bit & (side - 1)) - bz
                            row[(sx * dy + sy) * dz + sz] += 1
                            bits ^= lowest
    return scores


class KeySet:
    """Membership test for packed cube keys (a hash set that numba kernels can read directly)."""

    def __init__(self, keys: IntArray) -> None:
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        self.table = _build_table(keys, np.int64(_table_size(len(keys))))

    def contains(self, keys: IntArray) -> NDArray[np.bool_]:
        return _contains_many(self.table, np.ascontiguousarray(keys, dtype=np.int64))


# ---------------------------------------------------------------- voxel reduction


@numba.njit(cache=True, nogil=True)
def _bounds(points: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per-axis min and max in one pass (numpy's axis-0 reduction over 3-wide rows is ~10x slower)."""
    lower = points[0].copy()
    upper = points[0].copy()
    for i in range(1, points.shape[0]):
        for axis in range(3):
            value = points[i, axis]
            if value < lower[axis]:
                lower[axis] = value
            elif value > upper[axis]:
                upper[axis] = value
    return lower, upper


def reduce_points(points: FloatArray, voxel_size: float) -> IntArray:
    """Indices (ascending) of the real points kept: one per occupied voxel, the one closest to its centre.

    Voxel centres are never returned because a synthetic centre is up to half a voxel off the
    surface, which biases ICP correspondences. Picking the point nearest the centre rather than the
    first one makes the choice independent of point order (a reordered scan reduces to the same
    points) and spaces the kept points about one voxel apart, like a regular sample. Ties go to the
    lower index, so the result is deterministic. The grid is anchored at the cloud's minimum corner.
    """
    points = as_points(points)
    voxel_size = _check_size(voxel_size)
    lower, upper = _bounds(points)
    span = float((upper - lower).max())
    if span / voxel_size >= CELLS_PER_AXIS - 1:
        raise ValueError(
            f"voxel_size {voxel_size} is too small for a cloud spanning {span:.1f} (more than {CELLS_PER_AXIS} voxels"
            " per axis)"
        )
    keep = _closest_per_cell(points, lower, voxel_size, np.int64(_table_size(len(points))))
    return np.flatnonzero(keep).astype(np.int64)


# ---------------------------------------------------------------- octree


@dataclass(frozen=True)
class Occupancy:
    """Occupied cubes of one size: sorted packed keys with the number of points in each cube."""

    cube_size: float
    origin: FloatArray
    keys: IntArray
    counts: IntArray
    key_set: KeySet = field(repr=False, compare=False)

    @property
    def cells(self) -> IntArray:
        return unpack_keys(self.keys)

    @property
    def centres(self) -> FloatArray:
        return self.origin + (self.cells + 0.5) * self.cube_size

    def __len__(self) -> int:
        return len(self.keys)

    def keys_of(self, points: FloatArray) -> IntArray:
        """Keys of arbitrary points in this grid (-1 outside the addressable range)."""
        return pack_cells(cell_coordinates(np.asarray(points, dtype=np.float64), self.origin, self.cube_size))

    def contains(self, points: FloatArray) -> NDArray[np.bool_]:
        """Whether each point falls in an occupied cube."""
        return self.key_set.contains(self.keys_of(points))

    def count_hits(
        self, points: FloatArray, rotations: FloatArray, pivot: FloatArray, shifts: NDArray[np.int64]
    ) -> NDArray[np.int32]:
        """``hits[r, s]``: how many of ``R_r (p - pivot) + pivot``, moved by ``shifts[s]`` whole cubes, are occupied.

        The scoring core of the octree search. A shift of whole cubes moves a point's cell by exactly
        that many cells, so each rotated point is discretised once; the few tiles
        (:attr:`tile_masks`) around it are read once and every occupied cube among its shifted cells
        credits the shift that reaches it (the box spanned by ``shifts`` is scored, then the asked
        shifts are picked from it). A hash lookup per (point, shift) cost ~25 ns and made up 80 % of
        a search on a 100k-point street pair; a bit test per (point, shift) still half of it.
        """
        table, masks = self.tile_masks
        shifts = np.ascontiguousarray(shifts, dtype=np.int64).reshape(-1, 3)
        lo = shifts.min(axis=0) if len(shifts) else np.zeros(3, dtype=np.int64)
        dims = (shifts.max(axis=0) - lo + 1) if len(shifts) else np.ones(3, dtype=np.int64)
        box = _count_hits(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(rotations, dtype=np.float64).reshape(-1, 3, 3),
            np.ascontiguousarray(pivot, dtype=np.float64),
            self.origin,
            float(self.cube_size),
            lo,
            dims,
            table,
            masks,
            _X_BITS,
            _Y_BITS,
            _Z_BITS,
            _BIT_INDEX,
        )
        rel = shifts - lo
        return np.ascontiguousarray(box[:, (rel[:, 0] * dims[1] + rel[:, 1]) * dims[2] + rel[:, 2]])

    @cached_property
    def tile_masks(self) -> tuple[IntArray, NDArray[np.uint64]]:
        """The occupied cubes as 4 x 4 x 4 tiles with a 64-bit mask each (built on first use): the
        search reads the few tiles around a point once instead of a hash lookup per shift."""
        return _build_tiles(self.keys, np.int64(_table_size(len(self.keys))))


def _occupancy_from_keys(cube_size: float, origin: FloatArray, keys: IntArray, counts: IntArray) -> Occupancy:
    return Occupancy(cube_size, origin, keys, counts, KeySet(keys))


class Octree:
    """Occupied cubes of one scan at every depth, built once and shared by the search and the viewer.

    The root cube is anchored at the cloud's minimum corner (snapped to the leaf grid) with side
    ``leaf_size * 2**depth``, so the cubes at depth ``d`` are exactly the parents of those at
    ``d + 1``: coarser levels are derived from the occupied leaves by shifting cell coordinates,
    which costs time proportional to the occupied leaves, not to the points. Cube sizes that are
    not an octree depth are also answered (same anchor, computed from the points and cached), so a
    search configuration is not forced onto powers of two.
    """

    def __init__(self, points: FloatArray, leaf_size: float) -> None:
        self.points = as_points(points)
        self.leaf_size = _check_size(leaf_size, "leaf_size")
        lower, upper = _bounds(self.points)
        self.origin: FloatArray = np.floor(lower / self.leaf_size) * self.leaf_size
        # the cell of the farthest point is floor(span / leaf), so the root must hold one more leaf than that
        leaves_per_axis = math.floor(float((upper - self.origin).max()) / self.leaf_size) + 1
        self.depth = max(0, math.ceil(math.log2(leaves_per_axis)))
        if self.depth > BITS_PER_AXIS:
            raise ValueError(f"leaf_size {self.leaf_size} is too small for a cloud spanning {upper - lower}")
        self.root_size = self.leaf_size * (1 << self.depth)
        self._cache: dict[float, Occupancy] = {}
        cells = np.clip(cell_coordinates(self.points, self.origin, self.leaf_size), 0, (1 << self.depth) - 1)
        keys, counts = np.unique(pack_cells(cells), return_counts=True)
        self._leaf_cells = unpack_keys(keys)
        self._leaf_counts = counts.astype(np.int64)
        self._cache[self.leaf_size] = _occupancy_from_keys(self.leaf_size, self.origin, keys, self._leaf_counts)

    def cube_size(self, depth: int) -> float:
        """Side of the cubes at ``depth`` (0 = root cube, ``self.depth`` = leaves)."""
        if not 0 <= depth <= self.depth:
            raise ValueError(f"depth must be in 0..{self.depth}, got {depth}")
        return self.root_size / (1 << depth)

    def depth_of(self, cube_size: float) -> int | None:
        """The octree depth whose cubes have this size, or None if the size is not a depth."""
        ratio = cube_size / self.leaf_size
        shift = round(math.log2(ratio)) if ratio > 0 else -1
        if 0 <= shift <= self.depth and math.isclose(ratio, 1 << shift, rel_tol=1e-9):
            return self.depth - shift
        return None

    def occupancy(self, cube_size: float) -> Occupancy:
        cube_size = _check_size(cube_size, "cube_size")
        for size, occupancy in self._cache.items():
            if math.isclose(size, cube_size, rel_tol=1e-9):
                return occupancy
        depth = self.depth_of(cube_size)
        if depth is not None:
            shift = self.depth - depth
            keys, inverse = np.unique(pack_cells(self._leaf_cells >> shift), return_inverse=True)
            counts = np.bincount(inverse.reshape(-1), weights=self._leaf_counts, minlength=len(keys)).astype(np.int64)
        else:
            cells = cell_coordinates(self.points, self.origin, cube_size)
            keys, counts = np.unique(pack_cells(cells), return_counts=True)
            counts = counts.astype(np.int64)
        occupancy = _occupancy_from_keys(cube_size, self.origin, keys, counts)
        self._cache[cube_size] = occupancy
        return occupancy

    def occupancy_at_depth(self, depth: int) -> Occupancy:
        return self.occupancy(self.cube_size(depth))

    def occupied_cubes(self, cube_size: float) -> FloatArray:
        """Centres (M, 3) of the occupied cubes of this size, for drawing."""
        return self.occupancy(cube_size).centres
