"""The simulator's worlds: what stands where, and the route a platform takes through it.

* ``loop`` - the seed's world: a ground robot's ~100 m loop round one or two buildings over uneven
  ground among buildings, walls, parked cars, lamp posts and trees.
* ``indoor`` - one floor of a building: a hall with pillars, a corridor, rooms on both sides
  with doors (open leaves), tables and cabinets; the route walks into every room and back along
  the corridor, turning through doors within half a metre - the scale where a handheld scanner
  turns 30-45° between scans.
* ``outdoor`` - streets at car scale: a 3 x 2 grid of blocks with buildings, street trees, parked
  cars and lamp posts over gentle hills; a perimeter loop and a cut-through driven the other way.
* ``campus`` - the same at km scale: a 6 x 4 grid, a park, a small, a medium and a large loop
  (~2.9 km a lap), streets revisited in the opposite direction, and a two-level part: a ramp up
  to a parking deck's roof (4 m) driven round and down again, and later a pass under the deck at
  street level, so the same place is seen at two heights.

Every world is drawn from the session's seeded generator in a fixed order, so
:func:`slam6d.simulate.build_scene` with ``default_rng(seed)`` rebuilds it exactly. A builder takes a
resolved configuration (:func:`slam6d.simulate.resolved`: no field left at None).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import one_of
from slam6d.geometry import rot_z
from slam6d.routes import LoopPath, Route, Terrain, Tour, Waypoint
from slam6d.scene_mesh import MeshBuilder, Scene
from slam6d.simulation_config import SimulationConfig

Circle = tuple[float, float, float]  # x, y, radius of a footprint part


@dataclass(frozen=True)
class World:
    """A world's builder and the sensor and motion that suit it when the user names neither."""

    name: str
    description: str
    build: Callable[[SimulationConfig, np.random.Generator], Scene]
    sensor: str
    motion: str


# ---------------------------------------------------------------- placing objects


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
    route: Route,
    low: float | NDArray[np.float64],
    high: float | NDArray[np.float64],
    clearance: float,
    taken: list[Circle],
    size: NDArray[np.float64],
    yaw: float | None = None,
) -> tuple[NDArray[np.float64], float] | None:
    """Centre and yaw for a ``size`` footprint in the box [low, high]² clear of the route by
    ``clearance`` and of everything placed (``taken``, which it joins); None after 200 tries."""
    for _ in range(200):
        xy = rng.uniform(low, high, 2)
        angle = float(rng.uniform(0.0, np.pi)) if yaw is None else yaw
        circles = _footprint(xy, size, angle)
        centres = np.array([c[:2] for c in circles])
        radii = np.array([c[2] for c in circles])
        if (route.distance(centres) < radii + clearance).any():
            continue
        if taken:
            others = np.array(taken)
            gaps = np.hypot(others[:, None, 0] - centres[:, 0], others[:, None, 1] - centres[:, 1])
            if (gaps < others[:, None, 2] + radii + 0.5).any():
                continue
        taken.extend(circles)
        return xy, angle
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


def _tree(mesh: MeshBuilder, terrain: Terrain, xy: NDArray[np.float64], crown: float, rng: np.random.Generator) -> None:
    base = float(terrain.height(xy[0], xy[1]))
    trunk = rng.uniform(2.0, 3.5)
    mesh.cylinder(np.r_[xy, base - 0.3], rng.uniform(0.12, 0.3), trunk + 0.3 + crown * 0.5)
    mesh.blob(np.r_[xy, base + trunk + crown * 0.8], np.r_[crown, crown, crown * 1.2], rng)


def _car(mesh: MeshBuilder, terrain: Terrain, xy: NDArray[np.float64], yaw: float) -> None:
    base = float(terrain.height(xy[0], xy[1]))
    mesh.box(np.r_[xy, base + 0.45], np.r_[4.4, 1.8, 1.0], yaw)  # body
    mesh.box(np.r_[xy, base + 1.2], np.r_[2.4, 1.6, 0.6], yaw)  # cabin


def _pole(mesh: MeshBuilder, terrain: Terrain, xy: NDArray[np.float64]) -> None:
    mesh.cylinder(np.r_[xy, float(terrain.height(xy[0], xy[1])) - 0.3], 0.08, 4.5, sides=8)


# ---------------------------------------------------------------- loop: the seed's world


def loop_world(config: SimulationConfig, rng: np.random.Generator) -> Scene:
    """The seed's world; its draws from ``rng`` are unchanged, so old seeds give old sessions."""
    max_range = config.max_range  # resolved: the sensor's when the user named none
    assert max_range is not None
    terrain = Terrain.random(rng, config.terrain_amplitude)
    path = LoopPath.create(config.loop_length, config.loop_width, rng)
    mesh = MeshBuilder()
    half = max(config.loop_length, config.loop_width) / 2
    extent = half + max_range + 2.0
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
        if (placed := _place(rng, path, -ring, ring, 3.0, taken, size)) is not None:
            _building(mesh, terrain, placed[0], size, placed[1], rng.uniform(4.0, 12.0), rng)
            objects["buildings"] += 1
    for _ in range(config.walls):
        length, height = rng.uniform(4.0, 10.0), rng.uniform(1.2, 2.5)
        if (placed := _place(rng, path, -ring, ring, 2.0, taken, np.r_[length, 0.3])) is not None:
            xy, yaw = placed
            base = float(terrain.height(xy[0], xy[1]))
            mesh.box(np.r_[xy, base + height / 2 - 0.5], np.r_[length, 0.3, height + 1.0], yaw)
            objects["walls"] += 1
    for _ in range(config.cars):
        if (placed := _place(rng, path, -(half + 5.0), half + 5.0, 1.2, taken, np.r_[4.4, 1.8])) is not None:
            _car(mesh, terrain, *placed)
            objects["cars"] += 1
    for _ in range(config.poles):
        if (placed := _place(rng, path, -(half + 5.0), half + 5.0, 1.5, taken, np.r_[0.3, 0.3])) is not None:
            _pole(mesh, terrain, placed[0])
            objects["poles"] += 1
    for _ in range(config.trees):
        crown = rng.uniform(1.2, 2.6)
        if (placed := _place(rng, path, -(ring - 4.0), ring - 4.0, 1.0, taken, np.full(2, 1.4 * crown))) is not None:
            _tree(mesh, terrain, placed[0], crown, rng)
            objects["trees"] += 1
    vertices, triangles = mesh.build()
    return Scene(terrain, path, vertices, triangles, objects)


# ---------------------------------------------------------------- indoor: hall, corridor, rooms


WALL = 0.15  # thickness of interior walls, metres
DOOR_WIDTH, DOOR_HEIGHT = 1.0, 2.1


@dataclass(frozen=True)
class _Room:
    x0: float
    x1: float
    y0: float
    y1: float
    north: bool  # north of the corridor: its door is in its south wall
    door_x: float

    @property
    def door_wall_y(self) -> float:
        return self.y0 if self.north else self.y1

    def walk(self) -> list[Waypoint]:
        """In through the door, once round the room 1.2 m from its walls, out again."""
        inside = 1.2
        near_y = self.y0 + inside if self.north else self.y1 - inside
        far_y = self.y1 - inside if self.north else self.y0 + inside
        left, right = self.x0 + inside, self.x1 - inside
        return [(self.door_x, near_y, None), (right, near_y, None), (right, far_y, None), (left, far_y, None),
                (left, near_y, None), (self.door_x, near_y, None)]  # fmt: skip


def _wall_with_doors(mesh: MeshBuilder, axis: int, at: float, start: float, stop: float, height: float,
                     doors: list[tuple[float, float, float]]) -> None:  # fmt: skip
    """A wall along x (``axis`` 0, at y = ``at``) or y (axis 1), from ``start`` to ``stop``, with
    openings ``(centre, width, height)`` and a lintel above each."""
    edges = sorted((c - w / 2, c + w / 2, h) for c, w, h in doors)
    pieces: list[tuple[float, float, float, float]] = []  # along-wall from, to, z from, z to
    cursor = start
    for lo, hi, door_height in edges:
        pieces.append((cursor, lo, 0.0, height))
        pieces.append((lo, hi, door_height, height))
        cursor = hi
    pieces.append((cursor, stop, 0.0, height))
    for a, b, z0, z1 in pieces:
        if b - a < 1e-6 or z1 - z0 < 1e-6:
            continue
        centre_along, size_along = (a + b) / 2, b - a
        centre = np.r_[centre_along, at] if axis == 0 else np.r_[at, centre_along]
        size = np.r_[size_along, WALL] if axis == 0 else np.r_[WALL, size_along]
        mesh.box(np.r_[centre, (z0 + z1) / 2], np.r_[size, z1 - z0])


def indoor_world(config: SimulationConfig, rng: np.random.Generator) -> Scene:
    """A hall (16 x 14 m, 6 m high, four pillars), a 30 m corridor 2.5 m wide, five rooms of
    6 x 5 m on each side (3 m high) with a door each; the walk visits five rooms, returns along
    the corridor and circles the hall."""
    terrain = Terrain.flat()
    hall_x, hall_y, hall_height = 16.0, 14.0, 6.0
    corridor_y0, corridor_y1, storey = 5.75, 8.25, 3.0
    mid_y = (corridor_y0 + corridor_y1) / 2
    end_x = hall_x + 30.0
    columns = np.arange(hall_x, end_x, 6.0)
    rooms = [
        _Room(float(x0), float(x0) + 6.0, y0, y1, north, float(x0) + rng.uniform(1.3, 4.7))
        for x0 in columns
        for north, y0, y1 in ((True, corridor_y1, corridor_y1 + 5.0), (False, corridor_y0 - 5.0, corridor_y0))
    ]
    visited = [rooms[2 * c + c % 2] for c in range(len(columns))]  # north and south rooms by turns
    waypoints: list[Waypoint] = [(hall_x + 2.5, mid_y, None)]
    for room in visited:
        waypoints += [(room.door_x, mid_y, None), *room.walk(), (room.door_x, mid_y, None)]
    waypoints += [(end_x - 1.5, mid_y, None), (hall_x - 4.0, mid_y, None)]  # back along the corridor
    waypoints += [(hall_x - 4.0, 3.0, None), (3.0, 3.0, None), (3.0, hall_y - 3.0, None),
                  (hall_x - 4.0, hall_y - 3.0, None), (hall_x - 4.0, mid_y, None)]  # fmt: skip
    route = Tour.through(waypoints, terrain, corner_radius=0.35)

    mesh = MeshBuilder()
    south, north = corridor_y0 - 5.0, corridor_y1 + 5.0
    mesh.box(np.r_[end_x / 2, hall_y / 2, -0.1], np.r_[end_x + 2.0, hall_y + 2.0, 0.2])  # floor
    mesh.box(np.r_[hall_x / 2, hall_y / 2, hall_height + 0.1], np.r_[hall_x, hall_y, 0.2])  # hall ceiling
    mesh.box(np.r_[(hall_x + end_x) / 2, (south + north) / 2, storey + 0.1], np.r_[end_x - hall_x, north - south, 0.2])
    # The hall's walls; its east wall opens onto the corridor.
    _wall_with_doors(mesh, 0, 0.0, 0.0, hall_x, hall_height, [])
    _wall_with_doors(mesh, 0, hall_y, 0.0, hall_x, hall_height, [])
    _wall_with_doors(mesh, 1, 0.0, 0.0, hall_y, hall_height, [])
    _wall_with_doors(mesh, 1, hall_x, 0.0, hall_y, hall_height, [(mid_y, corridor_y1 - corridor_y0, 2.6)])
    for pillar in ((5.5, 5.0), (10.5, 5.0), (5.5, 9.0), (10.5, 9.0)):
        mesh.box(np.r_[pillar, hall_height / 2], np.r_[0.6, 0.6, hall_height])
    # Corridor walls with the rooms' doors, the rooms' outer and partition walls, the corridor's end.
    for wall_y, is_north in ((corridor_y0, False), (corridor_y1, True)):
        doors = [(r.door_x, DOOR_WIDTH, DOOR_HEIGHT) for r in rooms if r.north == is_north]
        _wall_with_doors(mesh, 0, wall_y, hall_x, end_x, storey, doors)
    _wall_with_doors(mesh, 0, south, hall_x, end_x, storey, [])
    _wall_with_doors(mesh, 0, north, hall_x, end_x, storey, [])
    for x in np.arange(hall_x + 6.0, end_x, 6.0):
        _wall_with_doors(mesh, 1, float(x), south, corridor_y0, storey, [])
        _wall_with_doors(mesh, 1, float(x), corridor_y1, north, storey, [])
    _wall_with_doors(mesh, 1, end_x, south, north, storey, [])
    objects = {"rooms": len(rooms), "doors": len(rooms), "pillars": 4, "furniture": 0}
    for room in rooms:
        # The door's leaf stands open into the room, hinged at the door's west edge.
        into = 1.0 if room.north else -1.0
        leaf = np.r_[room.door_x - DOOR_WIDTH / 2, room.door_wall_y + into * 0.5, 1.0]
        mesh.box(leaf, np.r_[0.04, 0.9, 2.0])
        taken: list[Circle] = []
        low, high = np.r_[room.x0 + 0.6, room.y0 + 0.6], np.r_[room.x1 - 0.6, room.y1 - 0.6]
        for size, height in ((np.r_[1.4, 0.7], 0.75), (np.r_[1.0, 0.5], 1.9), (np.r_[0.8, 0.8], 1.1)):
            if (placed := _place(rng, route, low, high, 0.6, taken, size)) is not None:
                xy, yaw = placed
                mesh.box(np.r_[xy, height / 2], np.r_[size, height], yaw)
                objects["furniture"] += 1
    vertices, triangles = mesh.build()
    return Scene(terrain, route, vertices, triangles, objects)


# ---------------------------------------------------------------- city blocks: outdoor and campus


@dataclass(frozen=True)
class CityLayout:
    """A grid of blocks between streets, and the tour driven through them."""

    blocks: tuple[int, int]  # along x, along y
    pitch: float  # metres between street centrelines
    street_half_width: float  # from a street's centreline to the blocks' edge
    terrain_amplitude: float
    terrain_wavelengths: tuple[float, float]
    loops: tuple[tuple[tuple[float, float], ...], ...]  # each a closed loop of intersections (grid units)
    park: tuple[int, int]  # the block that is a park
    deck: tuple[int, int] | None = None  # the block holding the parking deck, if any
    deck_height: float = 4.0  # of its roof above the ground


OUTDOOR = CityLayout(
    blocks=(3, 2), pitch=60.0, street_half_width=7.0, terrain_amplitude=1.5, terrain_wavelengths=(60.0, 160.0),
    loops=(((0, 0), (3, 0), (3, 2), (0, 2)),  # the perimeter, counter-clockwise
           ((0, 0), (1, 0), (1, 2), (3, 2), (3, 1), (0, 1))),  # two of its streets the other way
    park=(1, 1),
)  # fmt: skip
CAMPUS = CityLayout(
    blocks=(6, 4), pitch=80.0, street_half_width=8.0, terrain_amplitude=0.6, terrain_wavelengths=(200.0, 500.0),
    loops=(((0, 0), (1, 0), (1, 1), (0, 1)),  # small, counter-clockwise, up onto the deck first
           ((0, 0), (3, 0), (3, 2), (1, 2), (1, 0.6625), (0, 0.6625)),  # medium: a street of the first the other way, under the deck
           ((0, 0), (6, 0), (6, 4), (0, 4))),  # large, counter-clockwise
    # Every loop leaves the origin eastwards and comes back southwards: no U-turns between them.
    park=(4, 2),
    deck=(0, 0),
)  # fmt: skip
KEEP_RIGHT = 2.5  # metres from a street's centreline to the driving lane


@dataclass(frozen=True)
class _Deck:
    """A parking deck: a roof slab on columns, reached by a ramp from the street south of it."""

    x0: float
    x1: float
    y0: float
    y1: float
    roof: float  # absolute height of the roof's surface
    ramp_x: float
    ramp_foot_y: float  # where the ramp leaves the street, on the terrain

    def drive(self) -> list[Waypoint]:
        """Up the ramp, once round the roof, down again."""
        up = [(self.ramp_x, self.ramp_foot_y, None), (self.ramp_x, self.y0, self.roof)]
        lo_y, hi_y = self.y0 + 8.0, self.y1 - 8.0
        left, right = self.x0 + 8.0, self.x1 - 8.0
        roof = [(self.ramp_x, lo_y, self.roof), (right, lo_y, self.roof), (right, hi_y, self.roof),
                (left, hi_y, self.roof), (left, lo_y, self.roof), (self.ramp_x, lo_y, self.roof)]  # fmt: skip
        return up + roof + up[::-1]

    def build(self, mesh: MeshBuilder, terrain: Terrain) -> None:
        """The roof slab with its parapet, the columns, and the ramp with its side walls."""
        thickness = 0.4
        centre = np.r_[(self.x0 + self.x1) / 2, (self.y0 + self.y1) / 2]
        mesh.box(np.r_[centre, self.roof - thickness / 2], np.r_[self.x1 - self.x0, self.y1 - self.y0, thickness])
        half_ramp = 4.0
        for x0, x1, y0, y1 in ((self.x0, self.x1, self.y1, self.y1), (self.x0, self.x0, self.y0, self.y1),
                               (self.x1, self.x1, self.y0, self.y1), (self.x0, self.ramp_x - half_ramp, self.y0, self.y0),
                               (self.ramp_x + half_ramp, self.x1, self.y0, self.y0)):  # fmt: skip
            # A parapet round the roof, open where the ramp arrives.
            size = np.r_[max(x1 - x0, 0.2), max(y1 - y0, 0.2), 1.1]
            mesh.box(np.r_[(x0 + x1) / 2, (y0 + y1) / 2, self.roof + 0.55], size)
        # Columns on an 8 m grid, leaving a lane at mid-depth free for the pass under the deck.
        mid = (self.y0 + self.y1) / 2
        for x in np.arange(self.x0 + 2.0, self.x1 - 1.0, 8.0):
            for y in (self.y0 + 2.0, mid - 7.0, mid + 7.0, self.y1 - 2.0):
                base = float(terrain.height(x, y)) - 0.3
                top = self.roof - thickness
                mesh.box(np.r_[x, y, (base + top) / 2], np.r_[0.5, 0.5, top - base])
        foot = float(terrain.height(self.ramp_x, self.ramp_foot_y))
        ramp = np.array([[self.ramp_x - half_ramp, self.ramp_foot_y, foot], [self.ramp_x + half_ramp, self.ramp_foot_y, foot],
                         [self.ramp_x + half_ramp, self.y0, self.roof], [self.ramp_x - half_ramp, self.y0, self.roof]])  # fmt: skip
        mesh.slab(ramp, 0.3)
        for side in (-1.0, 1.0):  # its side walls, a metre above its deck
            x = self.ramp_x + side * (half_ramp + 0.1)
            wall = np.array([[x - 0.1, self.ramp_foot_y, foot + 1.0], [x + 0.1, self.ramp_foot_y, foot + 1.0],
                             [x + 0.1, self.y0, self.roof + 1.0], [x - 0.1, self.y0, self.roof + 1.0]])  # fmt: skip
            mesh.slab(wall, 1.5)


def city_world(layout: CityLayout, config: SimulationConfig, rng: np.random.Generator) -> Scene:
    """Blocks of buildings (a park among them) along streets with trees, parked cars and lamp
    posts, over gentle terrain; the tour drives the layout's loops one after the other."""
    terrain = Terrain.random(rng, layout.terrain_amplitude, layout.terrain_wavelengths)
    pitch, half_street = layout.pitch, layout.street_half_width
    deck = None
    if layout.deck is not None:
        bx0, by0 = layout.deck[0] * pitch + half_street, layout.deck[1] * pitch + half_street
        bx1, by1 = bx0 + pitch - 2 * half_street, by0 + pitch - 2 * half_street
        x0, x1, y0, y1 = bx0 + 8.0, bx1 - 8.0, by0 + 28.0, by1 - 2.0
        roof = float(terrain.height((x0 + x1) / 2, (y0 + y1) / 2)) + layout.deck_height
        deck = _Deck(x0, x1, y0, y1, roof, (bx0 + bx1) / 2, by0)
    waypoints: list[Waypoint] = []
    for number, loop in enumerate(layout.loops):
        if deck is not None and number == 0:  # the first loop leaves its first street for the deck
            street_y = loop[0][1] * pitch
            waypoints += [(loop[0][0] * pitch, street_y, None), (deck.ramp_x, street_y, None), *deck.drive(),
                          (deck.ramp_x, street_y, None)]  # fmt: skip
            loop = loop[1:]
        waypoints += [(i * pitch, j * pitch, None) for i, j in loop]
    # Loops meet where one ends and the next begins: no zero-length legs.
    waypoints = [w for k, w in enumerate(waypoints) if k == 0 or w != waypoints[k - 1]]
    route = Tour.through(waypoints, terrain, corner_radius=5.0, keep_right=KEEP_RIGHT)

    mesh = MeshBuilder()
    nx, ny = layout.blocks
    margin = 60.0  # of terrain beyond the outer streets
    xs = np.arange(-margin, nx * pitch + margin + 1.0, 2.0)
    ys = np.arange(-margin, ny * pitch + margin + 1.0, 2.0)
    mesh.height_field(terrain, xs, ys)
    objects = {"buildings": 0, "trees": 0, "cars": 0, "poles": 0, "hedges": 0, "decks": 0}
    if deck is not None:
        deck.build(mesh, terrain)
        objects["decks"] = 1
    for bi in range(nx):
        for bj in range(ny):
            if (bi, bj) == layout.deck:
                continue
            low = np.r_[bi * pitch + half_street + 3.0, bj * pitch + half_street + 3.0]
            high = low + pitch - 2 * half_street - 6.0
            taken: list[Circle] = []
            if (bi, bj) == layout.park:
                for _ in range(int(rng.integers(20, 31))):
                    crown = rng.uniform(1.5, 3.5)
                    if (placed := _place(rng, route, low, high, 2.0, taken, np.full(2, 1.4 * crown))) is not None:
                        _tree(mesh, terrain, placed[0], crown, rng)
                        objects["trees"] += 1
                for _ in range(6):
                    length = rng.uniform(5.0, 15.0)
                    if (placed := _place(rng, route, low, high, 2.0, taken, np.r_[length, 0.8])) is not None:
                        xy, yaw = placed
                        mesh.box(np.r_[xy, float(terrain.height(xy[0], xy[1])) + 0.3], np.r_[length, 0.8, 1.6], yaw)
                        objects["hedges"] += 1
                continue
            for _ in range(int(rng.integers(2, 5))):
                size = np.r_[rng.uniform(12.0, 0.45 * pitch), rng.uniform(10.0, 0.35 * pitch)]
                yaw = float(rng.choice([0.0, np.pi / 2])) + rng.normal(0.0, 0.05)
                if (placed := _place(rng, route, low, high, 4.0, taken, size, yaw)) is not None:
                    _building(mesh, terrain, placed[0], size, yaw, rng.uniform(6.0, 24.0), rng)
                    objects["buildings"] += 1
            for _ in range(int(rng.integers(0, 5))):  # a courtyard's trees
                crown = rng.uniform(1.5, 3.0)
                if (placed := _place(rng, route, low, high, 2.0, taken, np.full(2, 1.4 * crown))) is not None:
                    _tree(mesh, terrain, placed[0], crown, rng)
                    objects["trees"] += 1
    _line_streets(mesh, terrain, route, layout, rng, objects)
    vertices, triangles = mesh.build()
    return Scene(terrain, route, vertices, triangles, objects)


def _line_streets(mesh: MeshBuilder, terrain: Terrain, route: Route, layout: CityLayout, rng: np.random.Generator,
                  objects: dict[str, int]) -> None:  # fmt: skip
    """Along both sides of every street, every 6 m: a tree on the pavement (30 %), a car parked at
    the kerb (25 %), a lamp post (7 %) or nothing; intersections and the route's lanes kept clear."""
    nx, ny = layout.blocks
    pitch = layout.pitch
    centres, outwards, horizontals = [], [], []
    for horizontal in (True, False):
        lines, blocks = (ny + 1, nx) if horizontal else (nx + 1, ny)
        along = np.arange(10.0, blocks * pitch - 9.0, 6.0)
        along = along[(along % pitch >= 12.0) & (along % pitch <= pitch - 12.0)]  # not in an intersection
        for line in range(lines):
            for side in (-1.0, 1.0):
                across = np.full(len(along), line * pitch)
                centres.append(np.c_[along, across] if horizontal else np.c_[across, along])
                outwards.append(np.tile([0.0, side] if horizontal else [side, 0.0], (len(along), 1)))
                horizontals.append(np.full(len(along), horizontal))
    centre, outward, horizontal_street = np.vstack(centres), np.vstack(outwards), np.concatenate(horizontals)
    kind = rng.random(len(centre))
    offset = np.where(kind < 0.3, 6.5, np.where(kind < 0.55, 5.0, 7.2))  # pavement, kerb, lamp line
    spots = centre + offset[:, None] * outward
    clearance = route.distance(spots)
    for k in np.nonzero((kind < 0.55) | (kind > 0.93))[0]:
        if kind[k] < 0.3:
            crown = rng.uniform(1.2, 2.4)
            if clearance[k] > crown + 0.8:
                _tree(mesh, terrain, spots[k], crown, rng)
                objects["trees"] += 1
        elif kind[k] < 0.55 and clearance[k] > 2.3:
            _car(mesh, terrain, spots[k], 0.0 if horizontal_street[k] else np.pi / 2)
            objects["cars"] += 1
        elif kind[k] > 0.93 and clearance[k] > 1.0:
            _pole(mesh, terrain, spots[k])
            objects["poles"] += 1


WORLDS: dict[str, World] = {
    world.name: world
    for world in (
        World("loop", "a ground robot's ~100 m loop round a block over uneven ground (the seed's world)", loop_world,
              "rotating-sick", "robot"),
        World("indoor", "a hall, a corridor and ten rooms with doors: 30-45° turns within half a metre",
              indoor_world, "vlp16", "handheld"),
        World("outdoor", "streets at car scale: 3 x 2 blocks, two loops (~0.96 km)",
              lambda config, rng: city_world(OUTDOOR, config, rng), "hdl32", "car"),
        World("campus", "6 x 4 blocks at km scale: three loops (~2.9 km), a parking deck with a ramp",
              lambda config, rng: city_world(CAMPUS, config, rng), "vlp16", "car"),
    )
}  # fmt: skip
WORLD_NAMES = tuple(WORLDS)


def get_world(name: str) -> World:
    return one_of(WORLDS, name, "world")
