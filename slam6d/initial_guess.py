"""Initial guesses for pairwise registration: odometry extrapolation and the octree search.

ICP only converges from a start inside its basin (roughly: most closest-point pairs must be true
partners). Kurt3D gets that start in two ways, both here:

* :func:`extrapolate_odometry` — apply the odometry increment since the previous scan on top of
  that scan's registered pose, so the correction ICP found last time is not lost.
* :func:`octree_guess` — when odometry is poor (a large jump, a slipping robot, unknown start), a
  discrete search over 6-tuples ``(dx, dy, dz, droll, dpitch, dyaw)`` around the current guess,
  coarse to fine over cube sizes, maximising the number of data cubes that land in occupied model
  cubes.

Search design (why it stays cheap):

* Every level searches the full 6-D grid jointly rather than yaw and translation apart from roll
  and pitch: a 5° tilt moves points 15 m away by 1.3 m, more than a coarse cube, so scores taken
  with the tilt wrong would mislead the yaw/translation search. The joint grid stays affordable
  because of the next point.
* Translation steps equal the cube size, so shifting a rotated point by ``(a, b, c)`` steps shifts
  its cube by exactly ``(a, b, c)``: for each rotation the data points are transformed and
  discretised once, and the translations are the cells of a small box around it: the occupied model
  cubes in that box (read as a few 64-bit tile masks) each credit the translation that reaches
  them (:meth:`Occupancy.count_hits`). The rotation grid is small (the angle step is the angle that
  moves a far point by one cube), so a level costs ``rotations x points`` box reads, a few
  milliseconds in a serial numba kernel.
* Data points are reduced to one real point per data cube of the level (and evenly thinned to
  ``max_points``), so the score counts cubes, not points, and dense near-range returns do not
  dominate it.
* Angle steps halve with the cube sizes (the coarsest level's step is ``max_angle_step``). A step
  from the far points alone (``cube / lever`` with a 30 m lever on a street) gave the coarsest level
  ~4,000 rotations, 20 times the grid on an indoor hall: the 24-51 s per scan without odometry
  that users saw on car scans. Far points misplaced by a coarse rotation step merely add the same
  noise to every candidate; the finer levels, with finer steps, use them.
* Rotations turn about the scanner (the data frame's origin) when it stands inside its scan, else
  about the data's centroid (:func:`search_pivot`): a start is off because the vehicle's heading
  is, and turning about a centroid metres away couples each rotation with a translation that can
  leave the true pose outside the translation range.
* Points on the dominant near-level planes (ground, floor, ceiling; :func:`level_surfaces`) are not
  scored. A multi-beam lidar samples them in concentric rings about itself, which overlap best
  when the two scanners stand at the same place whatever the heading: on simulated VLP-16 street
  pairs, scoring them put the winners about a metre off (at the co-located pose) and ICP from
  there recovered 1 of 6 hard starts; without them 6 of 6, winners 9-13 cm off
  (``benchmarks/robustness.py --octree-rings``).
* Finer levels search a few of their own steps around the previous winner (±2 in translation, ±1
  in angle by default; with halving cubes ±1 step of the level above): a coarse winner is only
  known to within its own step, and translation errors also absorb the coupling of a residual
  rotation about the pivot. This keeps the fine levels at 3,375 candidates each, against tens of
  thousands at the coarsest level.
* Ties (common on plateaus at coarse levels) go to the candidate with the smallest offset in step
  units, so a correct start is never moved without evidence.

The trace keeps every candidate of every level: as a grid (six axes of offsets plus a score per grid
point), which holds tens of thousands of candidates in a few hundred kilobytes of JSON, yet reads as
a sequence of :class:`Candidate`.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from typing import overload

import numpy as np
from numpy.typing import NDArray

from slam6d.geometry import invert, pose_from_xyzrpy, rot_x, rot_y, rot_z, transform_points
from slam6d.octree import Octree, as_points, reduce_points

FloatArray = NDArray[np.float64]

Progress = Callable[[int, int], None]


def extrapolate_odometry(
    prev_odometry: FloatArray, prev_registered: FloatArray, current_odometry: FloatArray
) -> FloatArray:
    """Pose guess for a new scan: previous registered pose · (previous odometry⁻¹ · current odometry).

    The bracket is the motion the odometry measured between the two scans, expressed in the previous
    scan's frame; applying it to the registered (corrected) previous pose carries that correction
    forward instead of restarting from the drifting odometry. All three are 4x4 world_from_scan poses,
    so it holds for full 6-DoF motion, not only the planar (x, z, θy) odometry of a ground robot.
    """
    return np.asarray(prev_registered, dtype=np.float64) @ invert(prev_odometry) @ np.asarray(current_odometry)


# ---------------------------------------------------------------- configuration


@dataclass(frozen=True)
class OctreeSearchConfig:
    """Levels and bounds of the octree search. Lengths in metres, angles in radians.

    Defaults suit scans spanning ``reference_extent`` (indoor/outdoor robot scans, tens of metres):
    cube sizes 1.6 -> 0.1 m are consecutive octree depths, and the coarsest level covers ±2.4 m in
    x/y, ±0.8 m in z, ±48° yaw and ±6° roll/pitch, enough for starts off by 2 m and 45° yaw with ±5°
    tilt about the scanner. ``translation_range``/``yaw_range``/``tilt_range`` bound the
    coarsest level only (rounded up to whole steps); finer levels search
    ``refine_translation_steps``/``refine_rotation_steps`` of their own steps each way. Angle steps
    are ``cube_size / lever`` where the lever is the ``lever_percentile`` distance of the data from
    the pivot, capped at ``cube_sizes[0] / max_angle_step`` (so the steps halve with the cubes).
    ``max_points`` bounds the reduced data points scored per level. ``skip_level_surfaces`` leaves
    the points within ``surface_tolerance`` of a near-level plane holding at least
    ``surface_share`` of the scan out of the score (see :func:`level_surfaces`).
    """

    cube_sizes: tuple[float, ...] = (1.6, 0.8, 0.4, 0.2, 0.1)
    translation_range: tuple[float, float, float] = (2.4, 2.4, 0.8)
    yaw_range: float = math.radians(48.0)
    tilt_range: float = math.radians(6.0)
    refine_translation_steps: int = 2
    refine_rotation_steps: int = 1
    max_angle_step: float = math.radians(6.0)
    lever_percentile: float = 75.0
    max_points: int = 3000
    reference_extent: float = 25.0
    skip_level_surfaces: bool = True
    surface_tolerance: float = 0.15
    surface_share: float = 0.1

    def __post_init__(self) -> None:
        sizes = self.cube_sizes
        if not sizes or any(not (s > 0 and math.isfinite(s)) for s in sizes):
            raise ValueError(f"cube_sizes must be positive numbers, got {sizes}")
        if any(b > a for a, b in itertools.pairwise(sizes)):
            raise ValueError(f"cube_sizes must go from coarse to fine, got {sizes}")
        if len(self.translation_range) != 3 or any(r < 0 for r in self.translation_range):
            raise ValueError(f"translation_range must be three non-negative lengths, got {self.translation_range}")
        if self.yaw_range < 0 or self.tilt_range < 0:
            raise ValueError("yaw_range and tilt_range must not be negative")
        if self.refine_translation_steps < 0 or self.refine_rotation_steps < 0:
            raise ValueError("refine_translation_steps and refine_rotation_steps must be >= 0")
        if not self.max_angle_step > 0:
            raise ValueError(f"max_angle_step must be positive, got {self.max_angle_step}")
        if not 0 < self.lever_percentile <= 100:
            raise ValueError(f"lever_percentile must be in (0, 100], got {self.lever_percentile}")
        if self.max_points < 10:
            raise ValueError(f"max_points must be at least 10, got {self.max_points}")
        if not self.reference_extent > 0:
            raise ValueError(f"reference_extent must be positive, got {self.reference_extent}")
        if not (self.surface_tolerance > 0 and 0 < self.surface_share < 1):
            raise ValueError(
                f"surface_tolerance must be positive and surface_share in (0, 1), got {self.surface_tolerance}, "
                f"{self.surface_share}"
            )

    def for_extent(self, extent: float) -> OctreeSearchConfig:
        """The same search scaled to a cloud of size ``extent`` (lengths scale, angles do not).

        An object scan (the Stanford bunny is ~15 cm) would fall in a single 0.8 m cube; scaling
        keeps the number of cubes across the object, and the reach of the search relative to the
        object, as they are for a ``reference_extent`` scene.
        """
        if not (extent > 0 and math.isfinite(extent)):
            raise ValueError(f"extent must be a positive length, got {extent}")
        scale = extent / self.reference_extent
        return replace(
            self,
            cube_sizes=tuple(s * scale for s in self.cube_sizes),
            translation_range=(
                self.translation_range[0] * scale,
                self.translation_range[1] * scale,
                self.translation_range[2] * scale,
            ),
            reference_extent=extent,
            surface_tolerance=self.surface_tolerance * scale,
        )


def cloud_extent(points: FloatArray, percentile: float = 90.0) -> float:
    """Robust size of a cloud: twice the ``percentile`` distance from its median point (stray far returns
    of a laser scan would make a bounding box meaningless)."""
    points = as_points(points)
    if len(points) > 20_000:
        points = points[:: len(points) // 20_000]
    centre = np.median(points, axis=0)
    return 2.0 * float(np.percentile(np.linalg.norm(points - centre, axis=1), percentile))


def config_for(model_points: FloatArray, config: OctreeSearchConfig | None = None) -> OctreeSearchConfig:
    """``config`` (default settings if None), scaled to the model's size when the model is small.

    "Small" is less than a quarter of ``reference_extent``: then the default metre-scale cubes would
    cover the whole cloud with a handful of cubes and the score could not tell poses apart.
    """
    config = config or OctreeSearchConfig()
    extent = cloud_extent(model_points)
    if extent < config.reference_extent / 4.0:
        return config.for_extent(extent)
    return config


# ---------------------------------------------------------------- trace


@dataclass
class Candidate:
    """One evaluated 6-tuple: offsets (dx, dy, dz, droll, dpitch, dyaw) about the level's pivot, the
    data->model transform they give, and the number of data cubes that landed in occupied model cubes."""

    offsets: tuple[float, float, float, float, float, float]
    transform: FloatArray
    score: int


def offset_transform(start: FloatArray, pivot: FloatArray, offsets: Sequence[float]) -> FloatArray:
    """``start`` followed by a rotation (roll, pitch, yaw about x, y, z; Rz·Ry·Rx) about ``pivot`` and a shift.

    p' = R (p - c) + c + d for p = start(data point): the data turn in place about their centroid
    as placed by ``start``, then move by d, all in model-frame axes.
    """
    dx, dy, dz, roll, pitch, yaw = (float(v) for v in offsets)
    c = np.asarray(pivot, dtype=np.float64)
    delta = pose_from_xyzrpy(0.0, 0.0, 0.0, roll, pitch, yaw)
    delta[:3, 3] = c + np.array([dx, dy, dz]) - delta[:3, :3] @ c
    return delta @ np.asarray(start, dtype=np.float64)


@dataclass
class CandidateGrid(Sequence[Candidate]):
    """Every candidate of a level, stored as a grid: ``scores[i, j, k, l, m, n]`` is the score of the
    offsets ``(axes[0][i], axes[1][j], axes[2][k], axes[3][l], axes[4][m], axes[5][n])`` applied to
    ``start`` about ``pivot``. Indexing and iterating yield :class:`Candidate` (flat C order)."""

    start: FloatArray
    pivot: FloatArray
    axes: tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]
    scores: NDArray[np.int32]

    def __len__(self) -> int:
        return int(self.scores.size)

    @overload
    def __getitem__(self, index: int) -> Candidate: ...
    @overload
    def __getitem__(self, index: slice) -> list[Candidate]: ...
    def __getitem__(self, index: int | slice) -> Candidate | list[Candidate]:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        if not -len(self) <= index < len(self):
            raise IndexError(f"candidate {index} out of range ({len(self)} candidates)")
        cell = np.unravel_index(index % len(self), self.scores.shape)
        offsets = tuple(float(axis[i]) for axis, i in zip(self.axes, cell, strict=True))
        return Candidate(offsets, offset_transform(self.start, self.pivot, offsets), int(self.scores[cell]))  # type: ignore[arg-type]

    def __iter__(self) -> Iterator[Candidate]:
        for index in range(len(self)):
            yield self[index]

    def offsets(self) -> FloatArray:
        """(K, 6) offsets of all candidates, in the same flat order as :meth:`score_list`."""
        grids = np.meshgrid(*self.axes, indexing="ij")
        return np.stack([g.reshape(-1) for g in grids], axis=1)

    def score_list(self) -> NDArray[np.int32]:
        return self.scores.reshape(-1)

    def best(self, count: int) -> list[Candidate]:
        """The ``count`` highest-scoring candidates, best first."""
        flat = self.score_list()
        order = np.argsort(-flat, kind="stable")[:count]
        return [self[int(i)] for i in order]


@dataclass
class SearchLevel:
    """One level of the coarse-to-fine search: its cube size, every candidate with its score, the winner.

    ``steps`` are the grid spacings (dx, dy, dz, droll, dpitch, dyaw); ``data_points`` the reduced data
    points scored (the best possible score); ``model_cubes`` the occupied model cubes.
    """

    cube_size: float
    candidates: CandidateGrid
    winner: Candidate
    steps: tuple[float, float, float, float, float, float]
    data_points: int
    model_cubes: int
    seconds: float


@dataclass
class GuessResult:
    """Outcome of :func:`octree_guess`: the data->model transform, its score at the finest level, the trace."""

    transform: FloatArray
    score: int
    levels: list[SearchLevel]
    initial: FloatArray
    config: OctreeSearchConfig
    seconds: float = field(default=0.0)


# ---------------------------------------------------------------- search


def _axis(half_range: float, step: float) -> tuple[FloatArray, float]:
    """Symmetric grid ``-n*step .. n*step`` with n = ceil(half_range / step) (0 if the range is 0)."""
    n = math.ceil(half_range / step - 1e-9) if half_range > 0 else 0
    return np.arange(-n, n + 1, dtype=np.float64) * step, step


def _angle_axis(half_range: float, wanted_step: float) -> tuple[FloatArray, float]:
    """Symmetric angle grid reaching exactly ±half_range with a step no larger than ``wanted_step``."""
    if half_range <= 0:
        return np.zeros(1), wanted_step
    n = math.ceil(half_range / wanted_step - 1e-9)
    step = half_range / n
    return np.arange(-n, n + 1, dtype=np.float64) * step, step


def _thin(indices: NDArray[np.int64], max_points: int) -> NDArray[np.int64]:
    """Evenly spaced subset (deterministic); reduced indices follow scan order, so this spreads spatially."""
    if len(indices) <= max_points:
        return indices
    return indices[np.linspace(0, len(indices) - 1, max_points).round().astype(np.int64)]


def level_surfaces(
    points: FloatArray, tolerance: float, min_share: float, max_tilt: float = math.radians(30.0), planes: int = 2
) -> NDArray[np.bool_]:
    """Which points lie on the dominant near-level planes of a scan (ground, floor, ceiling).

    A multi-beam lidar samples a level surface in concentric rings about itself, so the rings of two
    scans overlap best when the scanners stand at the same place and overlap equally under any yaw
    about the sensor: scored by cube overlap, those points pull the search towards co-located
    scanners and leave the heading undetermined, and on a street scan they are most of the points.
    Up to ``planes`` planes within ``max_tilt`` of the scan's own x-y plane, each holding at least
    ``min_share`` of the points, are found by RANSAC on a sample (deterministic seed); points within
    ``tolerance`` of one are flagged.
    """
    points = as_points(points)
    sample = points[reduce_points(points, max(4.0 * tolerance, 1e-9))]
    rng = np.random.default_rng(0)
    flagged = np.zeros(len(points), dtype=bool)
    remaining = np.ones(len(sample), dtype=bool)
    for _ in range(planes):
        candidates = sample[remaining]
        if len(candidates) < 3:
            break
        picks = candidates[rng.integers(0, len(candidates), (256, 3))]
        normals = np.cross(picks[:, 1] - picks[:, 0], picks[:, 2] - picks[:, 0])
        lengths = np.linalg.norm(normals, axis=1)
        usable = lengths > 1e-12
        normals[usable] /= lengths[usable, None]
        usable &= np.abs(normals[:, 2]) >= math.cos(max_tilt)
        if not usable.any():
            break
        normals, offsets = normals[usable], -np.einsum("ij,ij->i", normals[usable], picks[usable, 0])
        support = (np.abs(candidates @ normals.T + offsets) <= tolerance).sum(axis=0)
        best = int(np.argmax(support))
        if support[best] < min_share * len(sample):
            break
        normal, offset = normals[best], offsets[best]
        on_plane = np.abs(sample @ normal + offset) <= tolerance
        remaining &= ~on_plane
        flagged |= np.abs(points @ normal + offset) <= tolerance
    return flagged


def search_pivot(data_points: FloatArray) -> FloatArray:
    """The point (data frame) the search turns the data about: the scanner when it stands inside its
    scan, else the data's centroid.

    A start is off because the vehicle's heading or position is: a rotation about the vehicle, i.e.
    the scanner. Turning about a centroid metres away instead couples every rotation step with a
    translation of (distance x angle), which on a one-sided street scan leaves the true pose outside
    the translation range. An object scanned from outside (the origin far from its points) keeps
    the centroid, where rotation and translation stay nearly independent.
    """
    lower, upper = data_points.min(axis=0), data_points.max(axis=0)
    if np.all(lower <= 0.0) and np.all(upper >= 0.0):
        return np.zeros(3)
    return np.asarray(data_points.mean(axis=0), dtype=np.float64)


def _search_level(
    tree: Octree,
    data_points: FloatArray,
    start: FloatArray,
    cube_size: float,
    previous: SearchLevel | None,
    config: OctreeSearchConfig,
    pivot_in_data: FloatArray,
) -> SearchLevel:
    began = time.perf_counter()
    occupancy = tree.occupancy(cube_size)
    chosen = _thin(reduce_points(data_points, cube_size), config.max_points)
    placed = transform_points(start, data_points[chosen])
    pivot = transform_points(start, pivot_in_data[None, :])[0]
    # Angle steps halve with the cubes (the lever is capped at what makes the coarsest level's step
    # max_angle_step), so each level's few steps cover the uncertainty of the level above; a lever
    # from far points alone would give a coarse level thousands of rotations and ~20 s of search.
    lever = float(np.percentile(np.linalg.norm(placed - pivot, axis=1), config.lever_percentile))
    lever = max(min(lever, config.cube_sizes[0] / config.max_angle_step), cube_size)
    angle_step = min(cube_size / lever, config.max_angle_step)

    if previous is None:
        trans_ranges = config.translation_range
        roll_range = pitch_range = config.tilt_range
        yaw_range = config.yaw_range
    else:
        # a few of this level's own steps each way (an axis the coarsest level did not search stays fixed)
        own = (cube_size, cube_size, cube_size, angle_step, angle_step, angle_step)
        counts = (config.refine_translation_steps,) * 3 + (config.refine_rotation_steps,) * 3
        ranges = [
            count * step if len(axis) > 1 else 0.0
            for axis, step, count in zip(previous.candidates.axes, own, counts, strict=True)
        ]
        trans_ranges = (ranges[0], ranges[1], ranges[2])
        roll_range, pitch_range, yaw_range = ranges[3:]
    axes_t = [_axis(r, cube_size) for r in trans_ranges]
    roll_axis, roll_step = _angle_axis(roll_range, angle_step)
    pitch_axis, pitch_step = _angle_axis(pitch_range, angle_step)
    yaw_axis, yaw_step = _angle_axis(yaw_range, angle_step)

    # rotations in (roll, pitch, yaw) C order; shifts in (x, y, z) C order
    rr, pp, yy = np.meshgrid(roll_axis, pitch_axis, yaw_axis, indexing="ij")
    rotations = np.stack(
        [rot_z(y) @ rot_y(p) @ rot_x(r) for r, p, y in zip(rr.ravel(), pp.ravel(), yy.ravel(), strict=True)]
    )
    steps_int = [np.rint(axis / cube_size).astype(np.int64) for axis, _ in axes_t]
    sx, sy, sz = np.meshgrid(*steps_int, indexing="ij")
    shifts = np.stack([sx.ravel(), sy.ravel(), sz.ravel()], axis=1)
    raw = occupancy.count_hits(placed, rotations, pivot, shifts)
    shape_t = tuple(len(a) for a, _ in axes_t)
    shape_r = (len(roll_axis), len(pitch_axis), len(yaw_axis))
    # raw is (rotation, shift); the trace grid is (x, y, z, roll, pitch, yaw)
    scores = raw.reshape(shape_r + shape_t).transpose(3, 4, 5, 0, 1, 2).copy()
    axes = (axes_t[0][0], axes_t[1][0], axes_t[2][0], roll_axis, pitch_axis, yaw_axis)
    steps = (cube_size, cube_size, cube_size, roll_step, pitch_step, yaw_step)
    grid = CandidateGrid(start=np.array(start, dtype=np.float64), pivot=pivot, axes=axes, scores=scores)
    winner = grid[_winner_index(grid, steps)]
    return SearchLevel(
        cube_size=float(cube_size),
        candidates=grid,
        winner=winner,
        steps=steps,
        data_points=len(chosen),
        model_cubes=len(occupancy),
        seconds=time.perf_counter() - began,
    )


def _winner_index(grid: CandidateGrid, steps: Sequence[float]) -> int:
    """Highest score; among equals the smallest offset in step units (no move without evidence)."""
    flat = grid.score_list()
    top = np.flatnonzero(flat == flat.max())
    if len(top) == 1:
        return int(top[0])
    cells = np.unravel_index(top, grid.scores.shape)
    cost = np.zeros(len(top))
    for axis, index, step in zip(grid.axes, cells, steps, strict=True):
        cost += (axis[index] / step) ** 2
    return int(top[np.argmin(cost)])


def octree_guess(
    model_points: FloatArray | Octree,
    data_points: FloatArray,
    initial: FloatArray = np.eye(4),
    config: OctreeSearchConfig | None = None,
    progress: Progress | None = None,
) -> GuessResult:
    """Search a data->model transform near ``initial`` that puts the most data cubes into model cubes.

    ``model_points`` (model frame) may be a prebuilt :class:`Octree` (built once per scan and shared
    with the viewer); ``data_points`` are in the data frame. ``config=None`` uses the default
    settings, scaled to the cloud's size when the cloud is small (see :func:`config_for`); an explicit
    config is used as given. ``progress(done, total)`` is called after each level.
    """
    began = time.perf_counter()
    model = model_points.points if isinstance(model_points, Octree) else as_points(model_points, "model points")
    data_points = as_points(data_points, "data points")
    initial = np.asarray(initial, dtype=np.float64)
    if initial.shape != (4, 4) or not np.all(np.isfinite(initial)):
        raise ValueError(f"initial must be a finite 4x4 transform, got shape {initial.shape}")
    if config is None:
        config = config_for(model)
    tree = model_points if isinstance(model_points, Octree) else Octree(model, leaf_size=config.cube_sizes[-1])

    pivot = search_pivot(data_points)
    scored = data_points
    if config.skip_level_surfaces:
        on_surface = level_surfaces(data_points, config.surface_tolerance, config.surface_share)
        if (~on_surface).sum() >= 10 * len(config.cube_sizes):  # keep everything if little else is left
            scored = data_points[~on_surface]
    levels: list[SearchLevel] = []
    current = initial
    for number, cube_size in enumerate(config.cube_sizes):
        level = _search_level(tree, scored, current, cube_size, levels[-1] if levels else None, config, pivot)
        levels.append(level)
        current = level.winner.transform
        if progress is not None:
            progress(number + 1, len(config.cube_sizes))
    return GuessResult(
        transform=current,
        score=levels[-1].winner.score,
        levels=levels,
        initial=initial,
        config=config,
        seconds=time.perf_counter() - began,
    )
