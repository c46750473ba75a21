"""Where a simulated platform can go: the ground it stands on and the closed route it follows.

A route is a dense closed polyline in the plane, driven in order; the platform's height and tilt
come from what it stands on at each point: the terrain (a smooth height field, so heights and
normals are analytic) or, on a :class:`Tour`, a structure such as a ramp or a parking deck's roof
whose heights the route carries itself. Both kinds of route answer :meth:`Route.stand`, so one
piece of code (:mod:`slam6d.motion`) places every platform in every world.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import pairwise

import numpy as np
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter1d
from scipy.spatial import cKDTree

SAMPLE_SPACING = 0.1  # metres between a tour's polyline vertices


@dataclass
class Terrain:
    """A smooth height field: a sum of plane waves, so heights and normals are analytic."""

    wave_vectors: NDArray[np.float64]  # (K, 2) rad/m
    amplitudes: NDArray[np.float64]
    phases: NDArray[np.float64]

    @classmethod
    def random(
        cls, rng: np.random.Generator, amplitude: float, wavelengths_m: tuple[float, float] = (18.0, 45.0)
    ) -> Terrain:
        count = 4
        wavelengths = rng.uniform(wavelengths_m[0], wavelengths_m[1], count)
        directions = rng.uniform(0.0, np.pi, count)
        vectors = (2 * np.pi / wavelengths)[:, None] * np.c_[np.cos(directions), np.sin(directions)]
        amplitudes = amplitude * rng.uniform(0.4, 1.0, count) / np.sqrt(count)
        return cls(vectors, amplitudes, rng.uniform(0.0, 2 * np.pi, count))

    @classmethod
    def flat(cls) -> Terrain:
        """Level ground at height 0: a building's floor."""
        return cls(np.zeros((1, 2)), np.zeros(1), np.zeros(1))

    def height(self, x: NDArray[np.float64] | float, y: NDArray[np.float64] | float) -> NDArray[np.float64]:
        arg = np.multiply.outer(x, self.wave_vectors[:, 0]) + np.multiply.outer(y, self.wave_vectors[:, 1])
        return np.sin(arg + self.phases) @ self.amplitudes

    def normal(self, x: float, y: float) -> NDArray[np.float64]:
        arg = x * self.wave_vectors[:, 0] + y * self.wave_vectors[:, 1] + self.phases
        slope = (self.amplitudes * np.cos(arg)) @ self.wave_vectors  # (dh/dx, dh/dy)
        n = np.array([-slope[0], -slope[1], 1.0])
        return n / np.linalg.norm(n)


@dataclass
class Route:
    """A closed polyline (last vertex == first), followed in the order of its vertices."""

    points: NDArray[np.float64]  # (M, 2) dense polyline, closed
    arc: NDArray[np.float64]  # cumulative length at each polyline point
    _tree: cKDTree | None = field(default=None, repr=False, kw_only=True)

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    def at(self, s: float) -> tuple[NDArray[np.float64], float]:
        """Position and heading (rad) at arc length ``s``."""
        here = self._interpolate(s)
        ahead = self._interpolate((s + 0.25) % self.length)  # the route is closed: wrap round
        return here, float(np.arctan2(ahead[1] - here[1], ahead[0] - here[0]))

    def _interpolate(self, s: float) -> NDArray[np.float64]:
        return np.array([np.interp(s, self.arc, self.points[:, 0]), np.interp(s, self.arc, self.points[:, 1])])

    def distance(self, xy: NDArray[np.float64]) -> NDArray[np.float64]:
        """Distance of each (N, 2) point to the route polyline (vertex-sampled, spacing < 0.2 m)."""
        if self._tree is None:
            self._tree = cKDTree(self.points)
        return self._tree.query(np.atleast_2d(xy))[0]

    def stand(self, s: float, terrain: Terrain) -> tuple[NDArray[np.float64], float, NDArray[np.float64]]:
        """Ground point under the platform, its heading (rad) and the ground's up vector at ``s``."""
        xy, heading = self.at(s)
        return np.r_[xy, terrain.height(xy[0], xy[1])], heading, terrain.normal(xy[0], xy[1])


@dataclass
class LoopPath(Route):
    """A rounded rectangle centred on the origin, driven counter-clockwise, with a gentle weave."""

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


def _arc(cx: float, cy: float, r: float, start: float, stop: float) -> NDArray[np.float64]:
    angles = np.linspace(start, stop, 120)
    return np.c_[cx + r * np.cos(angles), cy + r * np.sin(angles)]


Waypoint = tuple[float, float, float | None]  # x, y and the height of a structure there (None: on the terrain)


@dataclass
class Tour(Route):
    """A closed route through waypoints with rounded corners, partly on structures (ramps, decks).

    Between two waypoints on the terrain the platform follows the terrain; where either end
    carries a height the segment is a structure whose surface rises linearly between the ends (a
    terrain end starts at the terrain's height there): a ramp, or with equal heights a flat deck.
    """

    heights: NDArray[np.float64]  # (M,) surface height on structures (NaN on the terrain)
    ups: NDArray[np.float64]  # (M, 3) the structure's up vector (NaN on the terrain)

    @classmethod
    def through(
        cls,
        waypoints: Sequence[Waypoint],
        terrain: Terrain,
        corner_radius: float,
        keep_right: float = 0.0,
    ) -> Tour:
        """The closed tour through ``waypoints`` (back to the first), corners rounded over about
        ``corner_radius`` metres, shifted ``keep_right`` metres to the right of the travel direction
        (so a street driven both ways has two lanes)."""
        if len(waypoints) < 3:
            raise ValueError("a tour needs at least 3 waypoints")
        ends = [*waypoints, waypoints[0]]
        xy_parts, heights_parts = [], []
        for (xa, ya, za), (xb, yb, zb) in pairwise(ends):
            count = max(1, int(np.ceil(np.hypot(xb - xa, yb - ya) / SAMPLE_SPACING)))
            t = np.arange(count) / count
            xy_parts.append(np.c_[xa + t * (xb - xa), ya + t * (yb - ya)])
            if za is None and zb is None:
                heights_parts.append(np.full(count, np.nan))
            else:
                low = za if za is not None else float(terrain.height(xa, ya))
                high = zb if zb is not None else float(terrain.height(xb, yb))
                heights_parts.append(low + t * (high - low))
        raw = np.vstack(xy_parts)
        heights = np.concatenate(heights_parts)
        sigma = corner_radius / SAMPLE_SPACING
        smooth = np.c_[
            gaussian_filter1d(raw[:, 0], sigma, mode="wrap"), gaussian_filter1d(raw[:, 1], sigma, mode="wrap")
        ]
        tangent = np.roll(smooth, -1, axis=0) - np.roll(smooth, 1, axis=0)
        tangent /= np.linalg.norm(tangent, axis=1)[:, None]
        right = np.c_[tangent[:, 1], -tangent[:, 0]]
        points = smooth + keep_right * right
        points, heights = np.vstack([points, points[:1]]), np.r_[heights, heights[:1]]
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))]
        # A structure's up vector: perpendicular to the route's slope and to the horizontal left.
        surface = np.where(np.isnan(heights), terrain.height(points[:, 0], points[:, 1]), heights)
        forward = np.c_[np.gradient(points, arc, axis=0), np.gradient(surface, arc)]
        left = np.c_[-forward[:, 1], forward[:, 0], np.zeros(len(forward))]
        ups = np.cross(forward, left)
        ups /= np.linalg.norm(ups, axis=1)[:, None]
        return cls(points, arc, heights, ups)

    def stand(self, s: float, terrain: Terrain) -> tuple[NDArray[np.float64], float, NDArray[np.float64]]:
        s = s % self.length
        k = int(np.clip(np.searchsorted(self.arc, s), 1, len(self.arc) - 1))
        if np.isnan(self.heights[k - 1]) or np.isnan(self.heights[k]):
            return super().stand(s, terrain)
        xy, heading = self.at(s)
        return np.r_[xy, np.interp(s, self.arc[k - 1 : k + 1], self.heights[k - 1 : k + 1])], heading, self.ups[k]

    def on_structure(self) -> NDArray[np.bool_]:
        """Which polyline vertices lie on a structure rather than the terrain."""
        return ~np.isnan(self.heights)
