"""Synthetic Kurt3D-like outdoor sessions with exact ground truth and drifting odometry.

Real data never comes with a perfect reference, so the pipeline's accuracy (ATE/RPE) and the
workbench's default session come from here: a ground robot drives a closed loop around a block
over uneven ground among buildings, walls, parked cars, lamp posts and trees, stopping to take 3D
scans with a 2D laser scanner that is tilted (Kurt3D) or rotated (360°). The scene is one triangle
mesh cast against by open3d's Embree ray caster (deterministic, about 10 ms per 100k rays), so a
46 x 90k session takes seconds, dominated by writing text. Everything random is drawn from one
seeded generator in a fixed order: the same seed gives byte-identical files.

The robot's odometry integrates planar motion with a distance scale error, a heading drift that
grows with distance and with turning (skid steering), small noise, a random walk in height and
inclinometer noise on roll/pitch - what a ``.pose`` file of a real ground robot carries, and what
the pipeline starts from. Ground truth and odometry are also written as KITTI 3x4 files in the
same native uos frame and units (cm) as the ``.pose`` files, to compare directly with results.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path

import numpy as np
import open3d as o3d
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from slam6d.errors import Slam6dError
from slam6d.geometry import UOS, Matrix, make_pose, pose_from_xyzrpy, rot_z, xyzrpy_from_pose
from slam6d.io.poses import write_kitti_poses
from slam6d.io.uos import write_uos_scan

POINTS_PER_LINE = 181  # a SICK LMS 2xx: 181 readings per 180° sweep
PATTERNS = ("rotating", "tilting")

Progress = Callable[[int, int], None]


@dataclass
class SimulationConfig:
    """Everything that shapes a simulated session; lengths in metres, angles in degrees."""

    seed: int = 0
    scans: int = 20
    points_per_scan: int = 20_000  # laser shots per scan (181 per line); misses and too-near hits return nothing
    pattern: str = "rotating"  # "rotating": vertical fan turned 360° about z; "tilting": Kurt3D's 180° front fan
    elevation_min_deg: float = -40.0  # fan (rotating) or tilt (tilting) limits
    elevation_max_deg: float = 50.0
    loop_length: float = 32.0  # the loop is a rounded rectangle around a block
    loop_width: float = 20.0
    closing_gap: float = 0.6  # how far along the path the last scan stops short of the first
    sensor_height: float = 0.5
    min_range: float = 0.6  # the robot's own body
    max_range: float = 30.0
    range_noise: float = 0.01
    terrain_amplitude: float = 0.5  # of the smooth height field; slopes reach ~5-8°
    buildings: int = 7  # around the loop, besides the block inside it
    walls: int = 5
    cars: int = 4
    poles: int = 5
    trees: int = 22
    odometry_scale_error: float = 0.02  # relative error of every travelled distance
    odometry_yaw_drift_deg_per_m: float = 0.1
    odometry_turn_error: float = 0.04  # fraction of each turn misjudged (skid steering)
    odometry_translation_noise: float = 0.01  # std dev as a fraction of the step length
    odometry_yaw_noise_deg: float = 0.3
    odometry_height_noise: float = 0.02  # random walk per step
    odometry_tilt_noise_deg: float = 0.3  # inclinometer noise on roll and pitch, not accumulating
    decimals: int = 2  # of the centimetre coordinates written to the .3d files

    def validate(self) -> None:
        if self.scans < 2:
            raise ValueError(f"a session needs at least 2 scans, got {self.scans}")
        if self.points_per_scan < POINTS_PER_LINE:
            raise ValueError(f"points_per_scan must be at least one scan line ({POINTS_PER_LINE})")
        if self.pattern not in PATTERNS:
            raise ValueError(f"unknown scan pattern '{self.pattern}'; choose one of {', '.join(PATTERNS)}")
        if not self.elevation_min_deg < self.elevation_max_deg:
            raise ValueError("elevation_min_deg must be below elevation_max_deg")
        if not 0.0 < self.min_range < self.max_range:
            raise ValueError("need 0 < min_range < max_range")
        if min(self.loop_length, self.loop_width) < 8.0:
            raise ValueError("the loop must be at least 8 m in each direction")


@dataclass
class SimulatedSession:
    """What :func:`simulate_session` wrote; poses are canonical ``world_from_scan`` (metres)."""

    directory: Path
    scan_paths: list[Path]
    ground_truth: list[Matrix] = field(repr=False)
    odometry: list[Matrix] = field(repr=False)
    point_counts: list[int]
    ground_truth_file: Path
    odometry_file: Path
    parameters_file: Path


# ---------------------------------------------------------------- terrain


@dataclass
class Terrain:
    """A smooth height field: a sum of plane waves, so heights and normals are analytic."""

    wave_vectors: NDArray[np.float64]  # (K, 2) rad/m
    amplitudes: NDArray[np.float64]
    phases: NDArray[np.float64]

    @classmethod
    def random(cls, rng: np.random.Generator, amplitude: float) -> Terrain:
        count = 4
        wavelengths = rng.uniform(18.0, 45.0, count)
        directions = rng.uniform(0.0, np.pi, count)
        vectors = (2 * np.pi / wavelengths)[:, None] * np.c_[np.cos(directions), np.sin(directions)]
        amplitudes = amplitude * rng.uniform(0.4, 1.0, count) / np.sqrt(count)
        return cls(vectors, amplitudes, rng.uniform(0.0, 2 * np.pi, count))

    def height(self, x: NDArray[np.float64] | float, y: NDArray[np.float64] | float) -> NDArray[np.float64]:
        arg = np.multiply.outer(x, self.wave_vectors[:, 0]) + np.multiply.outer(y, self.wave_vectors[:, 1])
        return np.sin(arg + self.phases) @ self.amplitudes

    def normal(self, x: float, y: float) -> NDArray[np.float64]:
        arg = x * self.wave_vectors[:, 0] + y * self.wave_vectors[:, 1] + self.phases
        slope = (self.amplitudes * np.cos(arg)) @ self.wave_vectors  # (dh/dx, dh/dy)
        n = np.array([-slope[0], -slope[1], 1.0])
        return n / np.linalg.norm(n)


# ---------------------------------------------------------------- path


@dataclass
class LoopPath:
    """A rounded rectangle centred on the origin, driven counter-clockwise, with a gentle weave."""

    points: NDArray[np.float64]  # (M, 2) dense polyline, closed (last == first)
    arc: NDArray[np.float64]  # cumulative length at each polyline point
    _tree: cKDTree | None = field(default=None, repr=False)

    @classmethod
    def create(cls, length: float, width: float, rng: np.random.Generator) -> LoopPath:
        a, b = length / 2, width / 2
        r = 0.35 * min(a, b)
        # Corners and straights of the rounded rectangle, starting mid-way along the bottom side.
        segments = [
            np.c_[np.linspace(0.0, a - r, 200), np.full(200, -b)],
            _arc(a - r, -b + r, r, -np.pi / 2, 0.0),
            np.c_[np.full(200, a), np.linspace(-b + r, b - r, 200)],
            _arc(a - r, b - r, r, 0.0, np.pi / 2),
            np.c_[np.linspace(a - r, -a + r, 400), np.full(400, b)],
            _arc(-a + r, b - r, r, np.pi / 2, np.pi),
            np.c_[np.full(200, -a), np.linspace(b - r, -b + r, 200)],
            _arc(-a + r, -b + r, r, np.pi, 1.5 * np.pi),
            np.c_[np.linspace(-a + r, 0.0, 200), np.full(200, -b)],
        ]
        base = np.vstack(segments)
        base = base[np.r_[True, np.linalg.norm(np.diff(base, axis=0), axis=1) > 1e-9]]
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(base, axis=0), axis=1))]
        # Weave sideways by up to ~0.4 m with whole periods, so the path still closes on itself.
        tangent = np.gradient(base, arc, axis=0)
        normal = np.c_[-tangent[:, 1], tangent[:, 0]] / np.linalg.norm(tangent, axis=1)[:, None]
        cycles = int(rng.integers(2, 5))
        weave = rng.uniform(0.2, 0.4) * np.sin(2 * np.pi * cycles * arc / arc[-1]) * np.sin(np.pi * arc / arc[-1])
        points = base + weave[:, None] * normal
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
        return cls(points, arc)

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    def at(self, s: float) -> tuple[NDArray[np.float64], float]:
        """Position and heading (rad) at arc length ``s``."""
        here = self._interpolate(s)
        ahead = self._interpolate((s + 0.25) % self.length)  # the loop is closed: wrap round
        return here, float(np.arctan2(ahead[1] - here[1], ahead[0] - here[0]))

    def _interpolate(self, s: float) -> NDArray[np.float64]:
        return np.array([np.interp(s, self.arc, self.points[:, 0]), np.interp(s, self.arc, self.points[:, 1])])

    def distance(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance of each (N, 2) point to the path polyline (vertex-sampled, spacing < 0.2 m)."""
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree.query(np.atleast_2d(xy))[0]


def _arc(cx: float, cy: float, r: float, start: float, stop: float) -> NDArray[np.float64]:
    angles = np.linspace(start, stop, 120)
    return np.c_[cx + r * np.cos(angles), cy + r * np.sin(angles)]


# ---------------------------------------------------------------- scene meshes


class MeshBuilder:
    """Collects triangles of every scene object into one mesh for the ray caster."""

    def __init__(self) -> None:
        self._vertices: list[NDArray[np.float64]] = []
        self._triangles: list[NDArray[np.int64]] = []
        self._count = 0

    def add(self, vertices: NDArray[np.float64], triangles: NDArray[np.int64]) -> None:
        self._vertices.append(np.asarray(vertices, dtype=np.float64))
        self._triangles.append(np.asarray(triangles, dtype=np.int64) + self._count)
        self._count += len(vertices)

    def box(self, center: NDArray[np.float64], size: NDArray[np.float64], yaw: float = 0.0) -> None:
        corners = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)]) * size
        faces = np.array(
            [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
             [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
        )  # fmt: skip
        self.add(corners @ rot_z(yaw).T + center, faces)

    def cylinder(self, base: NDArray[np.float64], radius: float, height: float, sides: int = 14) -> None:
        angles = 2 * np.pi * np.arange(sides) / sides
        ring = np.c_[radius * np.cos(angles), radius * np.sin(angles)]
        vertices = np.vstack([np.c_[ring, np.zeros(sides)], np.c_[ring, np.full(sides, height)]]) + base
        i = np.arange(sides)
        j = (i + 1) % sides
        sides_tri = np.vstack([np.c_[i, j, j + sides], np.c_[i, j + sides, i + sides]])
        cap = np.c_[np.full(sides - 2, sides), np.arange(sides + 1, 2 * sides - 1), np.arange(sides + 2, 2 * sides)]
        self.add(vertices, np.vstack([sides_tri, cap]))

    def blob(self, center: NDArray[np.float64], radii: NDArray[np.float64], rng: np.random.Generator) -> None:
        """A lumpy ellipsoid, the crown of a tree."""
        sphere = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_loop(2)
        unit = np.asarray(sphere.vertices)
        unit = unit / np.linalg.norm(unit, axis=1)[:, None]
        lumps = 1.0 + 0.15 * rng.standard_normal(len(unit)).clip(-2, 2)
        self.add(unit * lumps[:, None] * radii + center, np.asarray(sphere.triangles))

    def height_field(self, terrain: Terrain, xs: NDArray[np.float64], ys: NDArray[np.float64]) -> None:
        gx, gy = np.meshgrid(xs, ys)
        vertices = np.c_[gx.ravel(), gy.ravel(), terrain.height(gx.ravel(), gy.ravel())]
        nx = len(xs)
        ii, jj = np.meshgrid(np.arange(nx - 1), np.arange(len(ys) - 1))
        a = (jj * nx + ii).ravel()
        self.add(vertices, np.vstack([np.c_[a, a + 1, a + nx + 1], np.c_[a, a + nx + 1, a + nx]]))

    def build(self) -> tuple[NDArray[np.float32], NDArray[np.uint32]]:
        return np.vstack(self._vertices).astype(np.float32), np.vstack(self._triangles).astype(np.uint32)


@dataclass
class Scene:
    """The world as one triangle mesh, plus what was placed (for the parameters file)."""

    terrain: Terrain
    path: LoopPath
    vertices: NDArray[np.float32] = field(repr=False)
    triangles: NDArray[np.uint32] = field(repr=False)
    objects: dict[str, int]
    _caster: o3d.t.geometry.RaycastingScene | None = field(default=None, repr=False)

    def cast(self, origin: NDArray[np.float64], directions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance to the first surface along each unit direction (inf for no hit)."""
        if self._caster is None:
            self._caster = o3d.t.geometry.RaycastingScene()
            self._caster.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))  # type: ignore[call-overload]
        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = directions
        return self._caster.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)  # type: ignore[call-overload]


Circle = tuple[float, float, float]  # x, y, radius of a footprint part


def _footprint(xy: NDArray[np.float64], size: NDArray[np.float64], yaw: float) -> list[Circle]:
    """Circles covering a rotated rectangle, so long buildings do not claim a huge disc around them."""
    long_axis = int(np.argmax(size))
    count = int(np.ceil(size[long_axis] / size[1 - long_axis]))
    step = size[long_axis] / count
    radius = float(np.hypot(step / 2, size[1 - long_axis] / 2))
    circles = []
    for k in range(count):
        local = np.zeros(2)
        local[long_axis] = (k - (count - 1) / 2) * step
        x, y = rot_z(yaw)[:2, :2] @ local + xy
        circles.append((float(x), float(y), radius))
    return circles


def _place(
    rng: np.random.Generator,
    path: LoopPath,
    bounds: float,
    clearance: float,
    taken: list[Circle],
    size: NDArray[np.float64],
) -> tuple[NDArray[np.float64], float] | None:
    """Centre and yaw for a ``size`` footprint clear of the path by ``clearance`` and of everything placed."""
    for _ in range(200):
        xy, yaw = rng.uniform(-bounds, bounds, 2), float(rng.uniform(0.0, np.pi))
        circles = _footprint(xy, size, yaw)
        centres = np.array([c[:2] for c in circles])
        radii = np.array([c[2] for c in circles])
        if (path.distance(centres) < radii + clearance).any():
            continue
        if any(np.hypot(x - cx, y - cy) < r + cr + 0.5 for x, y, r in taken for cx, cy, cr in circles):
            continue
        taken.extend(circles)
        return xy, yaw
    return None


def _building(mesh: MeshBuilder, terrain: Terrain, xy: NDArray[np.float64], size: NDArray[np.float64], yaw: float,
              height: float, rng: np.random.Generator) -> None:  # fmt: skip
    """A block with floor ledges and pilasters: structure along every wall so ICP cannot slide."""
    corners = (np.array([[-1, -1], [-1, 1], [1, -1], [1, 1]]) * size / 2) @ rot_z(yaw)[:2, :2].T + xy
    ground = float(terrain.height(corners[:, 0], corners[:, 1]).min()) - 0.5
    top = float(terrain.height(xy[0], xy[1])) + height
    mesh.box(np.r_[xy, (ground + top) / 2], np.r_[size, top - ground], yaw)
    for level in np.arange(ground + 3.5, top - 0.5, 3.0):  # a ledge per floor
        mesh.box(np.r_[xy, level], np.r_[size + 0.3, 0.2], yaw)
    rotation = rot_z(yaw)
    for axis in (0, 1):
        other = 1 - axis
        count = int(size[axis] // 3.5)
        for offset in (np.arange(count) - (count - 1) / 2) * 3.5:
            for side in (-1.0, 1.0):
                local = np.zeros(3)
                local[axis] = offset
                local[other] = side * (size[other] / 2 + 0.06)
                dims = np.full(3, 0.0)
                dims[axis], dims[other], dims[2] = 0.4, 0.12, top - ground
                mesh.box(np.r_[xy, 0.0] + rotation @ local + np.r_[0, 0, (ground + top) / 2], dims, yaw)
    if rng.random() < 0.5:  # an annex on one side
        side = rng.choice([-1.0, 1.0])
        annex = np.r_[size[0] * 0.4, size[1] * 0.5]
        offset = rotation[:2, :2] @ np.r_[0.0, side * (size[1] / 2 + annex[1] / 2 - 0.1)]
        annex_top = float(terrain.height(xy[0], xy[1])) + 2.8
        mesh.box(np.r_[xy + offset, (ground + annex_top) / 2], np.r_[annex, annex_top - ground], yaw)


def build_scene(config: SimulationConfig, rng: np.random.Generator) -> Scene:
    """The world of a session; drawn first from the seeded generator, so ``default_rng(seed)`` rebuilds it."""
    terrain = Terrain.random(rng, config.terrain_amplitude)
    path = LoopPath.create(config.loop_length, config.loop_width, rng)
    mesh = MeshBuilder()
    half = max(config.loop_length, config.loop_width) / 2
    extent = half + config.max_range + 2.0
    grid = np.arange(-extent, extent + 0.25, 0.5)
    mesh.height_field(terrain, grid, grid)
    taken: list[Circle] = []
    objects = {"buildings": 0, "walls": 0, "cars": 0, "poles": 0, "trees": 0}

    # The block inside the loop: one or two buildings, so the robot drives round them.
    inner = np.array([config.loop_length, config.loop_width]) - 2 * 4.0
    parts = [(np.zeros(2), inner * rng.uniform(0.55, 0.75))] if rng.random() < 0.5 else []
    if not parts:
        parts = [
            (np.r_[sign * inner[0] * 0.27, 0.0], inner * np.r_[0.4, 0.7] * rng.uniform(0.8, 1.0)) for sign in (-1, 1)
        ]
    for center, size in parts:
        _building(mesh, terrain, center, size, 0.0, rng.uniform(5.0, 10.0), rng)
        taken.extend(_footprint(center, size, 0.0))
        objects["buildings"] += 1

    ring = half + 16.0
    for _ in range(config.buildings):
        size = rng.uniform(5.0, 14.0, 2)
        if (placed := _place(rng, path, ring, 3.0, taken, size)) is not None:
            _building(mesh, terrain, placed[0], size, placed[1], rng.uniform(4.0, 12.0), rng)
            objects["buildings"] += 1
    for _ in range(config.walls):
        length, height = rng.uniform(4.0, 10.0), rng.uniform(1.2, 2.5)
        if (placed := _place(rng, path, ring, 2.0, taken, np.r_[length, 0.3])) is not None:
            xy, yaw = placed
            base = float(terrain.height(xy[0], xy[1]))
            mesh.box(np.r_[xy, base + height / 2 - 0.5], np.r_[length, 0.3, height + 1.0], yaw)
            objects["walls"] += 1
    for _ in range(config.cars):
        if (placed := _place(rng, path, half + 5.0, 1.2, taken, np.r_[4.4, 1.8])) is not None:
            xy, yaw = placed
            base = float(terrain.height(xy[0], xy[1]))
            mesh.box(np.r_[xy, base + 0.45], np.r_[4.4, 1.8, 1.0], yaw)  # body
            mesh.box(np.r_[xy, base + 1.2], np.r_[2.4, 1.6, 0.6], yaw)  # cabin
            objects["cars"] += 1
    for _ in range(config.poles):
        if (placed := _place(rng, path, half + 5.0, 1.5, taken, np.r_[0.3, 0.3])) is not None:
            xy = placed[0]
            mesh.cylinder(np.r_[xy, float(terrain.height(xy[0], xy[1])) - 0.3], 0.08, 4.5, sides=8)
            objects["poles"] += 1
    for _ in range(config.trees):
        crown = rng.uniform(1.2, 2.6)
        if (placed := _place(rng, path, ring - 4.0, 1.0, taken, np.full(2, 1.4 * crown))) is not None:
            xy = placed[0]
            base = float(terrain.height(xy[0], xy[1]))
            trunk = rng.uniform(2.0, 3.5)
            mesh.cylinder(np.r_[xy, base - 0.3], rng.uniform(0.12, 0.3), trunk + 0.3 + crown * 0.5)
            mesh.blob(np.r_[xy, base + trunk + crown * 0.8], np.r_[crown, crown, crown * 1.2], rng)
            objects["trees"] += 1
    vertices, triangles = mesh.build()
    return Scene(terrain, path, vertices, triangles, objects)


# ---------------------------------------------------------------- laser, poses, odometry


def scan_pattern(config: SimulationConfig) -> NDArray[np.float64]:
    """Unit ray directions in the scanner frame (x forward, y left, z up), in firing order."""
    lines = max(1, round(config.points_per_scan / POINTS_PER_LINE))
    low, high = np.radians(config.elevation_min_deg), np.radians(config.elevation_max_deg)
    if config.pattern == "rotating":
        # A vertical fan (181 readings from low to high elevation) turned about z through 360°.
        elevation = np.linspace(low, high, POINTS_PER_LINE)
        yaw = 2 * np.pi * np.arange(lines) / lines
        e, a = np.meshgrid(elevation, yaw)
        return np.c_[(np.cos(e) * np.cos(a)).ravel(), (np.cos(e) * np.sin(a)).ravel(), np.sin(e).ravel()]
    # Kurt3D: a horizontal 180° fan whose plane is pitched from low to high, one line per step.
    azimuth = np.radians(np.linspace(-90.0, 90.0, POINTS_PER_LINE))
    tilt = np.linspace(low, high, lines)
    a, t = np.meshgrid(azimuth, tilt)
    return np.c_[(np.cos(a) * np.cos(t)).ravel(), np.sin(a).ravel(), (np.cos(a) * np.sin(t)).ravel()]


def ground_truth_poses(config: SimulationConfig, scene: Scene) -> list[Matrix]:
    """Scanner poses standing on the terrain: up along the ground normal, forward along the path."""
    stops = np.linspace(0.0, scene.path.length - config.closing_gap, config.scans)
    poses = []
    for s in stops:
        xy, heading = scene.path.at(float(s))
        up = scene.terrain.normal(xy[0], xy[1])
        forward = np.array([np.cos(heading), np.sin(heading), 0.0])
        forward -= forward.dot(up) * up
        forward /= np.linalg.norm(forward)
        left = np.cross(up, forward)
        ground = np.r_[xy, scene.terrain.height(xy[0], xy[1])]
        poses.append(make_pose(np.c_[forward, left, up], ground + config.sensor_height * up))
    return poses


def drifting_odometry(config: SimulationConfig, truth: list[Matrix], rng: np.random.Generator) -> list[Matrix]:
    """Dead reckoning from the true motion: planar steps with scale and heading errors accumulate."""
    states = [xyzrpy_from_pose(p) for p in truth]
    x, y, z, _, _, yaw = states[0]
    odometry = [truth[0].copy()]
    tilt_noise = np.radians(config.odometry_tilt_noise_deg)
    for (px, py, pz, _, _, pyaw), (cx, cy, cz, roll, pitch, cyaw) in pairwise(states):
        step = rot_z(-pyaw)[:2, :2] @ np.array([cx - px, cy - py])
        distance = float(np.linalg.norm(step))
        turn = float(np.angle(np.exp(1j * (cyaw - pyaw))))
        measured = step * (1.0 + config.odometry_scale_error)
        measured += rng.normal(0.0, config.odometry_translation_noise * distance + 1e-12, 2)
        measured_turn = turn * (1.0 + config.odometry_turn_error) + np.radians(
            config.odometry_yaw_drift_deg_per_m * distance + rng.normal(0.0, config.odometry_yaw_noise_deg)
        )
        x, y = np.array([x, y]) + rot_z(yaw)[:2, :2] @ measured
        yaw += measured_turn
        z += (cz - pz) + rng.normal(0.0, config.odometry_height_noise)
        noisy_roll, noisy_pitch = roll + rng.normal(0.0, tilt_noise), pitch + rng.normal(0.0, tilt_noise)
        odometry.append(pose_from_xyzrpy(float(x), float(y), float(z), noisy_roll, noisy_pitch, float(yaw)))
    return odometry


def simulate_scan(
    config: SimulationConfig, scene: Scene, pose: Matrix, directions: NDArray[np.float64], rng: np.random.Generator
) -> NDArray[np.float64]:
    """Noisy returns of one scan in the scanner frame (canonical, metres), in firing order."""
    world_dirs = directions @ pose[:3, :3].T
    ranges = scene.cast(pose[:3, 3], world_dirs)
    ranges = ranges + rng.normal(0.0, config.range_noise, len(ranges))
    keep = np.isfinite(ranges) & (ranges >= config.min_range) & (ranges <= config.max_range)
    return directions[keep] * ranges[keep, None]


def simulate_session(
    out_dir: Path | str,
    config: SimulationConfig | None = None,
    progress: Progress | None = None,
    overwrite: bool = False,
) -> SimulatedSession:
    """Write a uos session (``scanNNN.3d`` + odometry ``.pose``) with ground truth beside it.

    Scans already in ``out_dir`` are refused unless ``overwrite``: left-over higher-numbered scans
    of an earlier, longer session would otherwise silently join the new one.
    """
    config = config or SimulationConfig()
    config.validate()
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise Slam6dError(f"{out}: exists and is not a directory")
    stale = sorted(out.glob("scan[0-9][0-9][0-9].*")) if out.is_dir() else []
    if stale and not overwrite:
        raise Slam6dError(
            f"{out}: already holds {len(stale)} scan file(s); choose an empty directory or overwrite them (--overwrite)"
        )
    for old in stale:
        old.unlink()
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(config.seed)
    scene = build_scene(config, rng)
    truth = ground_truth_poses(config, scene)
    odometry = drifting_odometry(config, truth, rng)
    directions = scan_pattern(config)
    paths, counts = [], []
    for index, (true_pose, odo_pose) in enumerate(zip(truth, odometry, strict=True)):
        points = simulate_scan(config, scene, true_pose, directions, rng)
        native = UOS.points_to_native(points)
        paths.append(write_uos_scan(out, index, native, UOS.pose_to_native(odo_pose), decimals=config.decimals))
        counts.append(len(points))
        if progress is not None:
            progress(index + 1, config.scans)
    gt_file, odo_file, params_file = out / "ground_truth_kitti.txt", out / "odometry_kitti.txt", out / "simulation.json"
    write_kitti_poses(gt_file, [UOS.pose_to_native(p) for p in truth])
    write_kitti_poses(odo_file, [UOS.pose_to_native(p) for p in odometry])
    parameters = {
        "generator": "slam6d simulate",
        "config": dataclasses.asdict(config),
        "format": "uos (cm, left-handed, y up); .pose files and odometry_kitti.txt hold odometry",
        "ground_truth": gt_file.name,
        "odometry": odo_file.name,
        "path_length_m": round(scene.path.length, 3),
        "scene_objects": scene.objects,
        "scene_triangles": len(scene.triangles),
        "points_per_scan": counts,
    }
    params_file.write_text(json.dumps(parameters, indent=1) + "\n")
    return SimulatedSession(out, paths, truth, odometry, counts, gt_file, odo_file, params_file)
