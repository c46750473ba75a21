"""A simulated world as one triangle mesh, and the ray caster that scans it.

Every object of a world (terrain, buildings, walls, trees, a parking deck) is appended to one
mesh, so open3d's Embree caster answers a whole scan in one call: about 10 ms per 100k rays,
whatever the world's size, which is what makes thousands of scans of a campus affordable. The
mesh is built once per session; scans only cast against it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cache

import numpy as np
from numpy.typing import NDArray

from slam6d.geometry import rot_z
from slam6d.open3d_viewer import defer_plotly_viewer
from slam6d.routes import Route, Terrain

defer_plotly_viewer()  # the ray caster draws nothing: open3d without dash, half its import
import open3d as o3d  # noqa: E402

_BOX_FACES = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
     [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]]
)  # fmt: skip


@cache
def _unit_sphere() -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """A twice-subdivided icosahedron on the unit sphere (162 vertices), made once: a campus has hundreds of trees."""
    sphere = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_loop(2)
    unit = np.asarray(sphere.vertices)
    unit = unit / np.linalg.norm(unit, axis=1)[:, None]
    unit.flags.writeable = False
    triangles = np.asarray(sphere.triangles).astype(np.int64)
    triangles.flags.writeable = False
    return unit, triangles


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
        self.add(corners @ rot_z(yaw).T + center, _BOX_FACES)

    def slab(self, top: NDArray[np.float64], thickness: float) -> None:
        """A plate under the quadrilateral ``top`` (4 corners in order round it): a ramp's deck."""
        top = np.asarray(top, dtype=np.float64)
        bottom = top - np.r_[0.0, 0.0, thickness]
        # Corners in the box's (i, j, k) order: i, j pick the quad corner, k bottom/top.
        order = [0, 3, 1, 2]  # quad corners at (i, j) = (0,0), (0,1), (1,0), (1,1)
        vertices = np.array([(bottom, top)[k][order[2 * i + j]] for i in (0, 1) for j in (0, 1) for k in (0, 1)])
        self.add(vertices, _BOX_FACES)

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
        unit, triangles = _unit_sphere()
        lumps = 1.0 + 0.15 * rng.standard_normal(len(unit)).clip(-2, 2)
        self.add(unit * lumps[:, None] * radii + center, triangles)

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
    """The world as one triangle mesh, the route through it, and what was placed (for the parameters file)."""

    terrain: Terrain
    route: Route
    vertices: NDArray[np.float32] = field(repr=False)
    triangles: NDArray[np.uint32] = field(repr=False)
    objects: dict[str, int]
    _caster: o3d.t.geometry.RaycastingScene | None = field(default=None, repr=False)

    def cast(self, origin: NDArray[np.float64], directions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance to the first surface along each unit direction (inf for no hit)."""
        return self._cast_rays(origin, directions)["t_hit"].numpy().astype(np.float64)

    def surface_normals(self, origin: NDArray[np.float64], directions: NDArray[np.float64]) -> NDArray[np.float64]:
        """Unit normal of the first surface along each unit direction (0 for no hit): the exact
        normals an estimate from the scan's points can be judged against."""
        return self._cast_rays(origin, directions)["primitive_normals"].numpy().astype(np.float64)

    def _cast_rays(self, origin: NDArray[np.float64], directions: NDArray[np.float64]) -> dict[str, o3d.core.Tensor]:
        if self._caster is None:
            self._caster = o3d.t.geometry.RaycastingScene()
            self._caster.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))  # type: ignore[call-overload]
        rays = np.empty((len(directions), 6), dtype=np.float32)
        rays[:, :3] = origin
        rays[:, 3:] = directions
        return self._caster.cast_rays(o3d.core.Tensor(rays))  # type: ignore[call-overload]
