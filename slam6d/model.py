"""The model side of a registration: points with their search structures and normals, built once.

A model is searched by every ICP iteration, every loop check and every relaxation round that pairs
with it, so its kd-tree, plane sample and normals are kept in a :class:`ModelIndex` and reused; the
metascan (the union of recent registered scans) is either one model over the joined points
(:func:`fused_model`, what sparse multi-beam scans need: the scans' rings interleave) or a
:class:`StackedModel` searching each member's own index in place.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Sequence

import numpy as np
from numpy.typing import NDArray

from slam6d import nn
from slam6d.errors import RegistrationError
from slam6d.geometry import invert, transform_points
from slam6d.normals import cell_normals, estimate_normals
from slam6d.octree import reduce_points

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

NORMAL_NEIGHBOURS = 12  # k of the k-NN normals
NORMAL_VOXEL_SIZE = 0.05  # metres: the plane sample's voxel (0 = the raw points)


# How far (m) both scanners must stand off a pair's plane, on opposite sides, for the pair to be left
# out as the wall's other face (ModelIndex.plane_pairs). A plane through or next to a scanner (the
# floor under a robot's scanner, a ring's false level plane at the scanner's height, a wall seen at
# grazing incidence) has no side the scanner is clearly on: with no margin the Kurt3D hall of the
# robustness matrix ended 5.13 cm off (4.07 before the test), with 0.05 or 0.25 m 4.64 cm.
FACE_SIDE_MARGIN = 0.05


def on_the_seen_side(
    views: FloatArray, scanners: FloatArray, partners: FloatArray, normals: FloatArray
) -> NDArray[np.bool_]:
    """Per pair: whether the data scanner (``scanners``, one row or one per pair) does not stand
    clearly on the other side of the partner's plane than the model's scanner that saw it
    (``views``), i.e. whether the pair may be kept (see :meth:`ModelIndex.plane_pairs`)."""
    seen = np.einsum("ij,ij->i", views - partners, normals)
    standing = np.einsum("ij,ij->i", scanners - partners, normals)
    margin = FACE_SIDE_MARGIN
    return ~(((seen > margin) & (standing < -margin)) | ((seen < -margin) & (standing > margin)))


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
    takes the normals from the cubes of that size instead, or of up to eight times that size where
    the smaller cube holds no plane (:func:`cell_normals` over all the model's points: a multi-beam
    lidar's rings are farther apart than one cube), so the sample only decides which points are
    paired. ``viewpoint``: where the scanner that took the points stood, in their frame (the origin
    of a scan's own frame), which lets the cube normals leave out the false level planes its rings
    make at its own height (:func:`cell_normals`); None where it is unknown or the points come from
    several scanners; ``viewpoints`` (one per point) says it for each point instead, e.g. a
    :func:`fused_model` of several scans. Known viewpoints let :meth:`plane_pairs` refuse a pair
    whose model plane the model's scanner saw from the other side than the data scanner stands
    on (see there).

    Everything is built on first use and cached: point-to-point never pays for normals, and normals
    are estimated only for sample points that actually get paired. One index may serve registrations
    running in several threads: filling the caches is locked.
    """

    def __init__(
        self,
        points: FloatArray,
        normal_neighbours: int = NORMAL_NEIGHBOURS,
        normal_voxel_size: float = NORMAL_VOXEL_SIZE,
        backend: str = nn.DEFAULT_BACKEND,
        threads: int = 2,
        normal_cell: float = 0.0,
        index: nn.NeighbourIndex | None = None,
        viewpoint: FloatArray | None = None,
        viewpoints: FloatArray | None = None,
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
        self.viewpoint = None if viewpoint is None else np.asarray(viewpoint, dtype=np.float64).reshape(3)
        if viewpoints is not None and np.shape(viewpoints) != points.shape:
            raise ValueError(
                f"viewpoints must be one per model point, shape {points.shape}, got {np.shape(viewpoints)}"
            )
        self.viewpoints = None if viewpoints is None else np.asarray(viewpoints, dtype=np.float64)
        self._lock = threading.RLock()
        if index is not None and len(index) != len(points):
            raise ValueError(f"the shared neighbour index has {len(index)} points, the model {len(points)}")
        self._index: nn.NeighbourIndex | None = index
        self._plane_indices: IndexArray | None = None
        self._plane_index: nn.NeighbourIndex | None = None
        self._normals = np.zeros((0, 3))
        self._normal_state = np.zeros(0, dtype=np.int8)  # per sample point: 0 unknown, 1 usable, 2 unusable
        self._smallest_cube_share: float | None = None

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
                level = np.zeros(len(self.points), dtype=np.int8)
                normals, usable = cell_normals(self.points, self.normal_cell, level_out=level, viewpoint=self.viewpoint)
                self._normals = normals[indices]
                self._normal_state = usable[indices].astype(np.int8)
                self._smallest_cube_share = float(np.mean(level[indices] == 1)) if len(indices) else 0.0
            self._plane_indices = indices
            self._plane_index = (
                self.index
                if len(indices) == len(self.points)
                else nn.build_index(self.points[indices], self.backend, self.threads)
            )

    @property
    def smallest_cube_share(self) -> float | None:
        """Share of the plane sample whose normal a ``normal_cell`` cube gives (not a larger cube, not
        k-NN); None without per-cube normals. Near 0 where the scan's lines lie farther apart than a
        cube: a multi-beam lidar outdoors (simulated VLP-16 streets and campus: 0.00-0.11), where
        :func:`fused_model` is needed; a quarter to a half on dense or close-range scans (BALM's
        hall 0.28, a VLP-16 indoors 0.27-0.50, the seed's SICK loop 0.55)."""
        self._ensure_plane_sample()
        return self._smallest_cube_share

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

    def sample_viewpoints(self, sample: IndexArray) -> FloatArray | None:
        """Where the scanner stood that took each given plane-sample point (model frame), or None
        where the model does not know."""
        if self.viewpoints is not None:
            return self.viewpoints[self.plane_indices[np.asarray(sample, dtype=np.int64)]]
        if self.viewpoint is not None:
            return np.broadcast_to(self.viewpoint, (len(sample), 3))
        return None

    def plane_pairs(
        self, points: FloatArray, max_distance: float, scanner: FloatArray | None = None
    ) -> tuple[IndexArray, FloatArray, FloatArray, FloatArray]:
        """Point-to-plane pairs of ``points`` (model frame) with the plane sample within ``max_distance``:
        (indices into ``points``, paired sample points, their distances, the sample's normals there).

        Points whose partner has no usable normal (a line, too few neighbours) are left out: what
        ICP, loop verification and the workbench's edge residuals all pair with.

        ``scanner`` (where the data points' scanner stands, model frame; or one row per point where
        they come from several scans) also leaves out pairs whose
        model plane the model's scanner saw from one side and the data scanner stands on the other
        (where the model knows its viewpoints, :meth:`sample_viewpoints`): a thin wall's two faces
        are two surfaces a slab's thickness apart, and within ``max_distance`` a point on one pairs
        with the other. The case measured: the simulated campus's parking-deck parapet (0.2 m),
        seen from the ramp on one side and from the roof on the other, held each step where the car
        tops or leaves the ramp 6-17 cm short of the truth, even started from the truth
        (docs/scale.md, "The ramp's crest: a parapet's two faces").
        """
        dist, idx = self.plane_index.nearest(points, max_distance)
        found = np.flatnonzero(idx >= 0)
        normals, usable = self.plane_normals_for(idx[found])
        found, normals = found[usable], normals[usable]
        partners = self.sample_points(idx[found])
        views = None if scanner is None else self.sample_viewpoints(idx[found])
        if views is not None and scanner is not None:
            scanners = np.asarray(scanner, dtype=np.float64)
            scanners = scanners[found] if scanners.ndim == 2 else scanners.reshape(1, 3)
            same_side = on_the_seen_side(views, scanners, partners, normals)
            found, partners, normals = found[same_side], partners[same_side], normals[same_side]
        return found, partners, dist[found], normals

    def plane_residuals(self, points: FloatArray, max_distance: float) -> FloatArray:
        """Signed point-to-plane distances of the :meth:`plane_pairs` of ``points``: how far the
        points that pair lie off the model's surface, whatever the scans' point spacing."""
        found, partners, _, normals = self.plane_pairs(points, max_distance)
        return np.einsum("ij,ij->i", points[found] - partners, normals)


def fused_model(
    clouds: Sequence[FloatArray],
    poses: Sequence[FloatArray],
    normal_neighbours: int = NORMAL_NEIGHBOURS,
    normal_voxel_size: float = NORMAL_VOXEL_SIZE,
    backend: str = nn.DEFAULT_BACKEND,
    threads: int = 2,
    normal_cell: float = 0.0,
    voxel_size: float = 0.0,
) -> ModelIndex:
    """One model of several registered scans (``poses``: world from each scan): their points joined in
    the last scan's frame, with the plane sample, cube normals and k-NN fallback over the union (the
    options as for :class:`ModelIndex`), reduced to one real point per ``voxel_size`` voxel where the
    scans overlap (0: every point).

    Why (multi-beam lidar): one scan's rings are metres apart on the ground and tens of centimetres
    on walls, and most of a car's pairs lie on crowns, poles and corners, where a normal fitted to
    one or two rings is the rings' own plane, not the surface's. A data point pairs with the nearest
    sample point, on a ring up to the max distance away, and that offset taken along a wrong normal
    is a residual at the true pose whose sign follows the rings: it tilted every campus step by
    ~0.25° (docs/scale.md, "Roll and pitch on the campus"). Scans taken a few metres back put their
    rings between the last scan's, so over the union the pairs are closer and the planes span
    interleaved rings. Unlike a :class:`StackedModel`, whose members keep their own normals, the
    union is indexed anew, which the cube normals (one pass over the points) make cheap.
    """
    if not clouds or len(clouds) != len(poses):
        raise ValueError("a fused model needs one pose per scan and at least one scan")
    last_from_world = invert(np.asarray(poses[-1], dtype=np.float64))
    points = np.concatenate(
        [
            transform_points(last_from_world @ np.asarray(p, dtype=np.float64), c)
            for c, p in zip(clouds, poses, strict=True)
        ]
    )
    viewpoints = np.concatenate(
        [
            np.broadcast_to((last_from_world @ np.asarray(p, dtype=np.float64))[:3, 3], (len(c), 3))
            for c, p in zip(clouds, poses, strict=True)
        ]
    )  # each point's scanner, so that pairs keep to the face it saw (ModelIndex.plane_pairs)
    if voxel_size > 0:  # a dense scanner's scans cover the same surfaces: keep the scans' own density
        kept = reduce_points(points, voxel_size)
        points, viewpoints = points[kept], viewpoints[kept]
    return ModelIndex(
        points, normal_neighbours, normal_voxel_size, backend, threads, normal_cell, viewpoints=viewpoints
    )


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

    def sample_viewpoints(self, sample: IndexArray) -> FloatArray | None:
        """The members' viewpoints placed by their poses; None unless every member knows its own."""
        sample = np.asarray(sample, dtype=np.int64)
        out = np.empty((len(sample), 3))
        for k, chosen, local in self._sample.split(sample):
            views = self.members[k].sample_viewpoints(local)
            if views is None:
                return None
            out[chosen] = transform_points(self._poses[k], np.asarray(views))
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
