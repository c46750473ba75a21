"""Global relaxation: make every overlapping pair of scans agree at once, not just consecutive ones.

Two methods, both over the same neighbour graph (scans whose reduced clouds share more than
``min_pairs`` closest-point pairs within the ICP max distance, as in the seed):

* :func:`simultaneous_matching` - the seed's method. A queue starts at the first scan of the loop;
  each scan taken from it is re-matched by ICP against the union of its neighbours, and when it
  moves by more than a threshold its neighbours are queued again. The first scan stays fixed.
* :func:`lum_relaxation` - LUM-style: like 3DTK's LUM, each round takes the closest-point pairs of
  every neighbour pair at the current poses and solves one linear system for all poses at once
  (here with point-to-plane residuals, Cauchy-weighted with a scale that halves from the ICP max
  distance each round, and a sparse solve); the next round re-pairs from the new poses. No pair is
  re-matched by ICP, so a round costs one closest-point query per data point of each edge; a
  round samples ``pair_points`` data points per overlapping pair on average (so the budget grows
  with the graph, not with a fixed total), shared among all pairs (the long-range ones that make a
  map globally consistent included) in proportion to their overlap. Each scan's
  plane-sample tree (built once) is queried once per round by the points of all its neighbours
  at once (against the registration's model when one was handed over,
  :meth:`ScanModels.share_plane_model`), the normal blocks of all pairs of a scan are summed in one
  compiled pass, and the joint system goes to :class:`slam6d.block_system.BlockSystem`. Rounds stop
  once a round at the final robust scale moves no scan by more than ``settle_fraction`` of that
  scale, or changes the Cauchy-weighted cost by less than ``chi2_tolerance`` (re-pairing keeps
  scans jittering below a millimetre, so the movement alone may never fall under ``tolerance``).

Residuals are reported before and after as the RMS point-to-plane distance of sampled data points
paired within the ICP max distance with their neighbour scan (the quantity both methods reduce).
Not the closest-point distance: between sparse scans that reads the point spacing (~11 cm on the
simulated loop whether or not the loop is relaxed). Simultaneous matching samples every neighbour
pair evenly (:func:`pair_residual`); LUM takes them from its rounds' own queries (see
:func:`lum_relaxation`), so reporting costs it no extra pass. A scan that does not overlap any other relaxed scan
makes the problem ill-posed; that raises :class:`RelaxationError` with the scans named. Scans left
out of the relaxation follow their predecessor rigidly, keeping the trajectory continuous.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace

import numba
import numpy as np
from numpy.typing import NDArray

from slam6d import nn
from slam6d.block_system import BlockSystem
from slam6d.errors import RegistrationError, RelaxationError, Slam6dError
from slam6d.geometry import Matrix, invert, make_pose, so3_exp, transform_points
from slam6d.icp import ICPConfig, correspondences, icp
from slam6d.model import ModelIndex
from slam6d.posegraph import (
    PoseEdge,
    check_connected,
    point_pair_information,
)

FloatArray = NDArray[np.float64]
Progress = Callable[[int, float, list[int]], None]  # (iteration, residual, scans moved)

__all__ = [
    "Cancelled",
    "NeighbourPair",
    "RelaxationConfig",
    "RelaxationError",
    "RelaxationResult",
    "ScanModels",
    "carry_forward",
    "lum_relaxation",
    "neighbour_pairs",
    "pair_residual",
    "simultaneous_matching",
]


class Cancelled(Slam6dError):  # noqa: N818 - reads as "the run was cancelled"
    """The caller asked to stop (the workbench's cancel button)."""


@dataclass(frozen=True)
class RelaxationConfig:
    min_pairs: int = 250  # the seed's neighbour criterion
    move_threshold: float = 0.005  # metres: re-queue neighbours when a scan moves more (simultaneous matching)
    max_rounds: int = 10  # queue pops per scan (simultaneous) / re-matching rounds (LUM)
    lum_icp_iterations: int = 8
    max_neighbours: int = 0  # strongest neighbours kept per scan for LUM edges; 0 = every neighbour pair
    edge_points: int = 4000  # data points per edge (evenly thinned), at most
    min_edge_points: int = 50  # and at least
    overlap_exponent: float = 1.0  # a pair's weight in LUM grows with its overlap to this power
    pair_points: int = 250  # data points per LUM round and graph pair on average, shared in proportion to overlap
    round_points: int = 0  # a cap on the data points per LUM round (0 = none)
    first_scale: float = 0.25  # Cauchy scale of the first LUM round, relative to the ICP max distance
    tolerance: float = 0.0005  # metres: stop LUM rounds when no scan moves more
    settle_fraction: float = 0.2  # or when, at the final robust scale, none moves more than this fraction of it
    chi2_tolerance: float = 0.005  # or when a round at the final robust scale changes the robust cost less (fraction)
    damping: float = 1e-3  # Levenberg damping of the joint LUM step, relative to the diagonal
    robust_scale: float = 0.05  # metres: final Cauchy scale of the LUM point-to-plane residuals (0 = least squares)


@dataclass
class NeighbourPair:
    i: int
    j: int
    pairs: int  # closest-point pairs within the ICP max distance (estimated from a thinned data cloud)


@dataclass
class RelaxationResult:
    poses: list[Matrix]
    residual_before: float  # RMS point-to-plane distance over neighbour pairs, metres
    residual_after: float
    iterations: int
    method: str
    neighbours: list[NeighbourPair] = field(default_factory=list)
    chi2_before: float | None = None  # pose-graph error (LUM only)
    chi2_after: float | None = None
    seconds: float = 0.0


class ScanModels:
    """Each scan's reduced points and kd-tree in its own frame, built once and shared by all stages."""

    def __init__(self, points: Sequence[FloatArray], config: ICPConfig, indices: Sequence[ModelIndex] | None = None):
        self.points = [np.ascontiguousarray(p, dtype=np.float64) for p in points]
        self.config = config
        self._indices: list[ModelIndex | None] = list(indices) if indices is not None else [None] * len(points)
        self._thinned: dict[tuple[int, int], FloatArray] = {}
        self._plane_models: dict[int, ModelIndex] = {}
        self._extents: dict[int, float] = {}

    def __len__(self) -> int:
        return len(self.points)

    def index(self, k: int) -> ModelIndex:
        model = self._indices[k]
        if model is None:
            model = ModelIndex(
                self.points[k],
                normal_neighbours=self.config.normal_neighbours,
                normal_voxel_size=self.config.normal_voxel_size,
                backend=self.config.nn_backend,
                threads=self.config.threads,
            )
            self._indices[k] = model
        return model

    def plane_model(self, k: int) -> ModelIndex:
        """Scan k as LUM rounds pair against it: the model handed over by :meth:`share_plane_model`
        when there is one, else :meth:`index` (normals by k-NN, estimated where pairs need them)."""
        model = self._plane_models.get(k)
        return model if model is not None else self.index(k)

    def share_plane_model(self, k: int, model: ModelIndex) -> None:
        """Let LUM rounds pair against ``model``: scan k's points in its own frame, e.g. the
        registration's model with its plane sample and normals built already.

        On the simulated loop, rounds against the registration models (a sample of one point per
        0.2 m cube, normals per 0.4 m cube) cost half the CPU of rounds against the full reduced scan
        with k-NN normals (~0.5 instead of ~0.9-1.0 s), for an ATE of 0.21 instead of 0.20 cm;
        on BALM hall ~3.8 instead of ~6.2 s CPU for an RPE of 0.55 instead of 0.54 cm.
        """
        if model.points is not self.points[k] and not np.array_equal(model.points, self.points[k]):
            raise ValueError(f"the plane model of scan {k} holds other points than the scan")
        self._plane_models[k] = model

    def thinned(self, k: int, count: int) -> FloatArray:
        """``count`` points spread evenly over the scan (all of them when it has fewer), cached."""
        pts = self.points[k]
        if len(pts) <= count:
            return pts
        key = (k, count)
        if key not in self._thinned:
            self._thinned[key] = pts[np.linspace(0, len(pts) - 1, count).round().astype(np.int64)]
        return self._thinned[key]

    def extent(self, k: int) -> float:
        if k not in self._extents:
            self._extents[k] = float(np.percentile(np.linalg.norm(self.points[k], axis=1), 95))
        return self._extents[k]


class UnionIndex(ModelIndex):
    """Several scans placed in the world as one model (a metascan, or a scan's neighbours).

    Built from the members' own plane samples and normals (estimated once per scan, in its own
    frame, and only rotated here): a union is rebuilt for every scan registered against it, and
    re-estimating normals over the union each time cost several times more than the matching.
    Normals from one scan's points are also not blurred by a misalignment between the members.
    """

    def __init__(self, models: ScanModels, members: Sequence[int], poses: Sequence[Matrix]) -> None:
        self.members = list(members)
        parts = [models.index(k) for k in self.members]
        super().__init__(
            np.concatenate([transform_points(poses[k], models.points[k]) for k in self.members]),
            normal_neighbours=models.config.normal_neighbours,
            normal_voxel_size=models.config.normal_voxel_size,
            backend=models.config.nn_backend,
            threads=models.config.threads,
        )
        offsets = np.cumsum([0] + [len(models.points[k]) for k in self.members])
        samples, normals, usable = [], [], []
        for k, part in zip(self.members, parts, strict=True):
            points, part_normals, part_usable = part.plane_normals()
            samples.append(transform_points(poses[k], points))
            normals.append(part_normals @ np.asarray(poses[k])[:3, :3].T)
            usable.append(part_usable)
        self._sample_indices = np.concatenate([o + p.plane_indices for o, p in zip(offsets, parts, strict=False)])
        self._sample_normals = np.concatenate(normals)
        self._sample_usable = np.concatenate(usable)
        self._sample_index = nn.build_index(np.concatenate(samples), self.backend, self.threads)

    @property
    def plane_indices(self) -> NDArray[np.int64]:
        return self._sample_indices

    @property
    def plane_index(self) -> nn.NeighbourIndex:
        return self._sample_index

    def plane_normals_for(self, sample: NDArray[np.int64]) -> tuple[FloatArray, NDArray[np.bool_]]:
        sample = np.asarray(sample, dtype=np.int64)
        return self._sample_normals[sample], self._sample_usable[sample]

    def plane_normals(self) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        return self._sample_index.points, self._sample_normals, self._sample_usable


def _placed_in(
    models: ScanModels, poses: Sequence[Matrix], i: int, others: Sequence[int], count: int | Sequence[int]
) -> tuple[FloatArray, FloatArray, NDArray[np.int64], FloatArray]:
    """Thinned points of each scan in ``others`` placed in scan i's frame, stacked for one query.

    Returns the placed points, the same points in their own frames, the position in ``others``
    each point came from, and the relative poses inv(X_i) X_j. Querying scan i's tree once with
    all of them replaces one query (and its Python overhead) per pair.
    """
    points, source = _gathered(models, others, [count] * len(others) if isinstance(count, int) else count)
    relative = _relative(poses, i, others)
    return _place(points, source, relative), points, source, relative


def _gathered(models: ScanModels, others: Sequence[int], counts: Sequence[int]) -> tuple[FloatArray, NDArray[np.int64]]:
    """The thinned points of each scan in ``others`` (in its own frame) stacked, and the position in
    ``others`` each came from."""
    own = [models.thinned(j, c) for j, c in zip(others, counts, strict=True)]
    return np.concatenate(own), np.repeat(np.arange(len(others)), [len(d) for d in own])


def _relative(poses: Sequence[Matrix], i: int, others: Sequence[int] | NDArray[np.int64]) -> FloatArray:
    """inv(X_i) X_j for every j in ``others``, stacked."""
    return np.matmul(invert(poses[i]), np.stack([poses[j] for j in others]))


@numba.njit(cache=True, nogil=True)
def _place(points, source, relative):  # type: ignore[no-untyped-def]
    """Each point moved by the relative pose of the pair it belongs to (one pass, no (n, 3, 3) gather)."""
    out = np.empty_like(points)
    for n in range(points.shape[0]):
        r = relative[source[n]]
        x, y, z = points[n, 0], points[n, 1], points[n, 2]
        for a in range(3):
            out[n, a] = r[a, 0] * x + r[a, 1] * y + r[a, 2] * z + r[a, 3]
    return out


@numba.njit(cache=True, nogil=True)
def _pair_blocks(q, p, found, partners, normals, relative, source, pairs, robust_scale):  # type: ignore[no-untyped-def]
    """Per pair: J^T W J (12x12, order i then j), J^T W r, the sums of r² and of w r², and the point count.

    Point ``found[t]`` (placed ``q``, own frame ``p``) is paired with the model point ``partners[t]``
    whose normal is ``normals[t]``. Accumulated point by point: the (n, 12) Jacobian and the
    per-pair products built with numpy cost more than the closest-point query of the round.
    """
    blocks = np.zeros((pairs, 12, 12))
    gradients = np.zeros((pairs, 12))
    sums = np.zeros((pairs, 3))  # r², w r², count
    jac = np.empty(12)
    for t in range(found.shape[0]):
        n = found[t]
        s = source[n]
        nx, ny, nz = normals[t, 0], normals[t, 1], normals[t, 2]
        qx, qy, qz = q[n, 0], q[n, 1], q[n, 2]
        px, py, pz = p[n, 0], p[n, 1], p[n, 2]
        r = (qx - partners[t, 0]) * nx + (qy - partners[t, 1]) * ny + (qz - partners[t, 2]) * nz
        rel = relative[s]
        # R_ij^T n
        ax = rel[0, 0] * nx + rel[1, 0] * ny + rel[2, 0] * nz
        ay = rel[0, 1] * nx + rel[1, 1] * ny + rel[2, 1] * nz
        az = rel[0, 2] * nx + rel[1, 2] * ny + rel[2, 2] * nz
        jac[0], jac[1], jac[2] = -nx, -ny, -nz
        jac[3] = -(qy * nz - qz * ny)
        jac[4] = -(qz * nx - qx * nz)
        jac[5] = -(qx * ny - qy * nx)
        jac[6], jac[7], jac[8] = ax, ay, az
        jac[9] = py * az - pz * ay
        jac[10] = pz * ax - px * az
        jac[11] = px * ay - py * ax
        w = 1.0
        if robust_scale > 0.0:
            u = r / robust_scale
            w = 1.0 / (1.0 + u * u)
        block = blocks[s]
        for a in range(12):
            wa = w * jac[a]
            gradients[s, a] += wa * r
            for b in range(a, 12):
                block[a, b] += wa * jac[b]
        sums[s, 0] += r * r
        sums[s, 1] += w * r * r
        sums[s, 2] += 1.0
    for s in range(pairs):
        for a in range(12):
            for b in range(a):
                blocks[s, a, b] = blocks[s, b, a]
    return blocks, gradients, sums


def _by_model(pairs: Sequence[NeighbourPair]) -> dict[int, list[int]]:
    grouped: dict[int, list[int]] = {}
    for pair in pairs:
        grouped.setdefault(pair.i, []).append(pair.j)
    return grouped


def neighbour_pairs(
    models: ScanModels,
    poses: Sequence[Matrix],
    min_pairs: int = 250,
    members: Iterable[int] | None = None,
    sample: int = 200,
) -> list[NeighbourPair]:
    """Scan pairs with more than ``min_pairs`` closest-point pairs at the current poses.

    Only pairs whose scanned regions can touch (distance below the sum of their 95th-percentile
    ranges) are counted, on an evenly thinned copy of the data scan scaled back up; that turns an
    O(n²) sweep of full queries into one cheap query per scan. A quarter of ``sample`` is tried
    first: a pair where a third of it finds partners is far above any useful ``min_pairs`` and
    keeps that estimate; only the others are counted on the full ``sample``.
    """
    chosen = sorted(set(range(len(models))) if members is None else set(members))
    extents = np.array([models.extent(k) for k in chosen])
    centres = np.array([poses[k][:3, 3] for k in chosen])
    found = []
    first = max(1, sample // 4)
    for a_pos, i in enumerate(chosen):
        gaps = np.linalg.norm(centres[a_pos + 1 :] - centres[a_pos], axis=1)
        reach = extents[a_pos] + extents[a_pos + 1 :]
        near = [chosen[a_pos + 1 + n] for n in np.flatnonzero(gaps <= reach)]
        if not near:
            continue
        hits, sizes = _hits(models, poses, i, near, first)
        sure = hits * 3 >= sizes
        unsure = [j for j, s in zip(near, sure, strict=True) if not s]
        if unsure:
            hits[~sure], sizes[~sure] = _hits(models, poses, i, unsure, sample)
        for j, hit, size in zip(near, hits, sizes, strict=True):
            count = int(hit * len(models.points[j]) / size)
            if count > min_pairs:
                found.append(NeighbourPair(i, j, count))
    return found


def _hits(
    models: ScanModels, poses: Sequence[Matrix], i: int, others: Sequence[int], sample: int
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Per scan of ``others``: how many of its ``sample`` thinned points have a partner in scan i, of how many."""
    placed, _, source, _ = _placed_in(models, poses, i, others, sample)
    _, idx = models.index(i).nearest(placed, models.config.max_distance)
    return np.bincount(source[idx >= 0], minlength=len(others)), np.bincount(source, minlength=len(others))


def pair_residual(
    models: ScanModels, poses: Sequence[Matrix], pairs: Sequence[NeighbourPair], sample: int = 150
) -> float:
    """RMS point-to-plane distance over all neighbour pairs (pairs within the ICP max distance), metres."""
    residuals = [
        _plane_residuals(models, i, _placed_in(models, poses, i, others, sample)[0])
        for i, others in _by_model(pairs).items()
    ]
    return _rms(residuals)


def _plane_residuals(models: ScanModels, i: int, placed: FloatArray) -> FloatArray:
    """Point-to-plane residuals of ``placed`` (scan i's frame) against scan i's plane model."""
    return models.plane_model(i).plane_residuals(placed, models.config.max_distance)


def _rms(residuals: Sequence[FloatArray]) -> float:
    count = sum(len(r) for r in residuals)
    return float(np.sqrt(sum(float(r @ r) for r in residuals) / count)) if count else float("nan")


def _adjacency(pairs: Sequence[NeighbourPair], count: int) -> list[list[int]]:
    adjacent: list[list[int]] = [[] for _ in range(count)]
    for pair in pairs:
        adjacent[pair.i].append(pair.j)
        adjacent[pair.j].append(pair.i)
    return adjacent


def carry_forward(before: Sequence[Matrix], after: Sequence[Matrix], relaxed: Iterable[int]) -> list[Matrix]:
    """Scans outside ``relaxed`` follow the correction of the closest relaxed scan before them.

    Without this, relaxing a loop in the middle of a trajectory would tear it where the loop ends.
    """
    relaxed_set = set(relaxed)
    out = [np.array(p) for p in after]
    correction = np.eye(4)
    for k in range(len(before)):
        if k in relaxed_set:
            correction = out[k] @ invert(before[k])
        else:
            out[k] = correction @ before[k]
    return out


def _check_cancel(cancel: Callable[[], bool] | None) -> None:
    if cancel is not None and cancel():
        raise Cancelled("relaxation cancelled")


def _set_up(
    models: ScanModels,
    poses: Sequence[Matrix],
    fixed: Iterable[int],
    members: Iterable[int] | None,
    config: RelaxationConfig,
) -> tuple[list[Matrix], list[Matrix], list[int], set[int], list[NeighbourPair]]:
    """What both relaxations start from: poses before and working copies, the scans taking part,
    the fixed ones among them (the first member when none is), and the overlapping pairs."""
    before = [np.array(p) for p in poses]
    current = [np.array(p) for p in poses]
    chosen = sorted(set(range(len(models))) if members is None else set(members))
    fixed_set = {f for f in fixed if f in chosen} or {chosen[0]}
    return before, current, chosen, fixed_set, neighbour_pairs(models, current, config.min_pairs, chosen)


def _check_graph(models: ScanModels, pairs: Sequence[NeighbourPair], fixed: set[int], chosen: list[int]) -> None:
    """Refuse a graph in which some member is not tied to a fixed scan (scans left out count as fixed)."""
    outside = set(range(len(models))) - set(chosen)
    check_connected(len(models), [(p.i, p.j) for p in pairs], fixed | outside)


def simultaneous_matching(
    models: ScanModels,
    poses: Sequence[Matrix],
    fixed: Iterable[int] = (0,),
    config: RelaxationConfig = RelaxationConfig(),
    members: Iterable[int] | None = None,
    start: int | None = None,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
) -> RelaxationResult:
    """The seed's simultaneous matching over the scans ``members`` (default all), see the module docstring."""
    began = time.perf_counter()
    before, current, chosen, fixed_set, pairs = _set_up(models, poses, fixed, members, config)
    _check_graph(models, pairs, fixed_set, chosen)
    adjacent = _adjacency(pairs, len(models))
    residual_before = pair_residual(models, current, pairs)
    first = start if start is not None else min(chosen)
    order = [k for k in chosen if k >= first] + [k for k in chosen if k < first]
    queue = deque(k for k in order if k not in fixed_set)
    queued = set(queue)
    pops = 0
    limit = config.max_rounds * len(chosen)
    while queue and pops < limit:
        _check_cancel(cancel)
        k = queue.popleft()
        queued.discard(k)
        pops += 1
        if not adjacent[k]:
            continue
        union = UnionIndex(models, adjacent[k], current)
        try:
            result = icp(union, models.points[k], current[k], models.config)
        except RegistrationError as exc:
            raise RelaxationError(f"simultaneous matching: scan {k} no longer matches its neighbours: {exc}") from exc
        sample = models.thinned(k, 500)
        moved = float(
            np.linalg.norm(
                transform_points(result.transform, sample) - transform_points(current[k], sample), axis=1
            ).max()
        )
        current[k] = result.transform
        requeued = []
        if moved > config.move_threshold:
            for n in adjacent[k]:
                if n not in fixed_set and n not in queued:
                    queue.append(n)
                    queued.add(n)
                    requeued.append(n)
        if progress is not None:
            progress(pops, result.rms, [k])
    after = carry_forward(before, current, chosen)
    return RelaxationResult(
        poses=after,
        residual_before=residual_before,
        residual_after=pair_residual(models, after, pairs),
        iterations=pops,
        method="simultaneous",
        neighbours=pairs,
        seconds=time.perf_counter() - began,
    )


def _strongest(pairs: Sequence[NeighbourPair], count: int, keep: int) -> list[NeighbourPair]:
    """Each scan's ``keep`` strongest neighbour pairs, plus every consecutive pair (the trajectory's spine).

    ``keep`` <= 0 keeps every pair: the long-range pairs are what makes a map globally consistent.
    """
    if keep <= 0:
        return sorted(pairs, key=lambda p: (p.i, p.j))
    by_scan: list[list[NeighbourPair]] = [[] for _ in range(count)]
    for pair in pairs:
        by_scan[pair.i].append(pair)
        by_scan[pair.j].append(pair)
    chosen: dict[tuple[int, int], NeighbourPair] = {}
    for lst in by_scan:
        for pair in sorted(lst, key=lambda p: -p.pairs)[:keep]:
            chosen[(pair.i, pair.j)] = pair
        # the strongest pairs are nearly always the scan's temporal neighbours; the pairs that make a
        # map globally consistent are the long-range ones, so keep the best of those too
        far = [p for p in lst if abs(p.j - p.i) > keep]
        for pair in sorted(far, key=lambda p: -p.pairs)[: max(1, keep // 2)]:
            chosen[(pair.i, pair.j)] = pair
    for pair in pairs:
        if pair.j == pair.i + 1:
            chosen[(pair.i, pair.j)] = pair
    return sorted(chosen.values(), key=lambda p: (p.i, p.j))


def match_edge(models: ScanModels, poses: Sequence[Matrix], pair: NeighbourPair, config: RelaxationConfig) -> PoseEdge:
    """ICP of scan j against scan i (own frames) from the current poses, with LUM's information matrix."""
    cfg = replace(models.config, max_iterations=config.lum_icp_iterations)
    data = models.thinned(pair.j, config.edge_points)
    model = models.index(pair.i)
    start = invert(poses[pair.i]) @ poses[pair.j]
    result = icp(model, data, start, cfg)
    data_idx, model_idx = correspondences(model, data, result.transform, cfg.max_distance, limit=-1)
    placed = transform_points(result.transform, data[data_idx])
    sigma2 = float(np.mean(np.sum((placed - model.points[model_idx]) ** 2, axis=1))) if len(data_idx) else 1.0
    # floor sigma at a millimetre: a perfect synthetic match must not get infinite weight
    info = point_pair_information(placed, result.transform, max(sigma2, 1e-6))
    return PoseEdge(pair.i, pair.j, result.transform, info)


@dataclass
class _ScanBatch:
    """Scan i's share of every LUM round: the data points of all its graph neighbours, fixed for the run.

    The budget does not change between rounds, so the thinned points are gathered once; a round
    only moves them by the current relative poses.
    """

    i: int
    others: NDArray[np.int64]  # the neighbours j of the pairs (i, j)
    points: FloatArray  # their thinned points, each in its own scan's frame, stacked
    source: NDArray[np.int64]  # position in ``others`` each point came from
    weights: FloatArray  # per pair, the weight of each of its point pairs


def _batches(
    models: ScanModels, graph_pairs: Sequence[NeighbourPair], budget: dict[tuple[int, int], tuple[int, float]]
) -> list[_ScanBatch]:
    batches = []
    for i, others in _by_model(graph_pairs).items():
        points, source = _gathered(models, others, [budget[(i, j)][0] for j in others])
        weights = np.array([budget[(i, j)][1] for j in others])
        batches.append(_ScanBatch(i, np.array(others, dtype=np.int64), points, source, weights))
    return batches


@dataclass
class _ScanSystem:
    """Normal-equation blocks of scan i's pairs from one round's query (see :func:`_scan_system`)."""

    blocks: FloatArray  # (pairs, 12, 12) J^T W J, order i then j
    gradients: FloatArray  # (pairs, 12) J^T W r
    sums: FloatArray  # (pairs, 3): sum of r², of w r², point count


def _scan_system(models: ScanModels, current: Sequence[Matrix], batch: _ScanBatch, robust_scale: float) -> _ScanSystem:
    """Normal-equation blocks of every pair (i, j) of ``batch`` from one query of scan i's plane sample.

    Data points ``p`` of scan j are placed in scan i's frame by inv(X_i) X_j and paired with the
    closest point ``m`` (normal ``n``) of scan i's plane sample. With both poses perturbed on the
    right, X <- X Exp([ρ, φ]), the residual r = n·(q - m), q = inv(X_i) X_j p, moves by
    J_i = [-n, -(q × n)] and J_j = [R_ij^T n, p × R_ij^T n].
    With ``robust_scale`` c > 0 each pair is weighted by Cauchy's w = 1 / (1 + (r/c)²)
    (iteratively reweighted least squares): pairs of different surfaces that happen to lie within
    the max distance then barely pull. The sums of r² are the residual report's, which so needs no
    query of its own.
    """
    model = models.plane_model(batch.i)
    relative = _relative(current, batch.i, batch.others)
    q = _place(batch.points, batch.source, relative)
    found, partners, _, normals = model.plane_pairs(q, models.config.max_distance)
    blocks, gradients, sums = _pair_blocks(
        q, batch.points, found, partners, normals, relative, batch.source, len(batch.others), float(robust_scale)
    )
    return _ScanSystem(blocks, gradients, sums)


def _edge_budget(
    models: ScanModels, graph_pairs: Sequence[NeighbourPair], config: RelaxationConfig
) -> dict[tuple[int, int], tuple[int, float]]:
    """Data points sampled per pair and the weight each of its point pairs gets.

    Points go to the pairs in proportion to their overlap (the overlapping fraction of the data
    scan): the strongly overlapping, mostly consecutive pairs carry the local accuracy and need the
    samples. The weight is set apart from the sampling so that a pair's total pull grows with
    overlap**``overlap_exponent``. With 1 (the default) every point pair weighs the same. On BALM
    hall 0.5 and 0 (every pair pulling equally) moved the self-consistency check by less than
    0.1 cm and raised the RPE (0.57, 0.59 vs 0.56 cm); at full resolution the far-apart pairs do
    not agree with each other either, so favouring them does not make them agree.
    """
    share = {(p.i, p.j): p.pairs / len(models.points[p.j]) for p in graph_pairs}
    total = config.pair_points * len(graph_pairs)
    if config.round_points > 0:
        total = min(total, config.round_points)
    unit = total / max(sum(share.values()), 1e-9)
    budget = {}
    for key, s in share.items():
        count = int(np.clip(unit * s, config.min_edge_points, config.edge_points))
        budget[key] = (count, s**config.overlap_exponent / count)
    mean = np.mean([c * w for c, w in budget.values()]) / np.mean([c for c, _ in budget.values()])
    return {key: (c, w / mean) for key, (c, w) in budget.items()}


@dataclass
class _Round:
    moved: dict[int, Matrix]  # new poses of the free scans
    chi2: float  # sum of budget-weighted squared point-to-plane residuals before the step
    cost: float  # the same, Cauchy-weighted
    residual: float  # RMS point-to-plane distance of the round's pairs (before the step), metres


def _joint_step(
    models: ScanModels,
    current: list[Matrix],
    batches: Sequence[_ScanBatch],
    fixed: set[int],
    config: RelaxationConfig,
    robust_scale: float,
) -> _Round:
    """One Gauss-Newton step of all scans at once over the current closest-point pairs (LUM's round).

    Each scan is queried once, by the thinned points of all its graph neighbours at once; the
    joint system is solved by :class:`slam6d.block_system.BlockSystem`. Each pair's residuals count
    with its budget weight. A little Levenberg damping keeps directions no pair constrains (a scan
    seeing one flat wall) from running away.
    """
    count = len(current)
    systems = [_scan_system(models, current, batch, robust_scale) for batch in batches]
    ei = np.concatenate([np.full(len(b.others), b.i) for b in batches])
    ej = np.concatenate([b.others for b in batches])
    weight = np.concatenate([b.weights for b in batches])
    blocks = np.concatenate([s.blocks for s in systems])
    gradients = np.concatenate([s.gradients for s in systems])
    sums = np.concatenate([s.sums for s in systems])
    paired = sums[:, 2] > 0
    if not paired.any():
        raise RelaxationError("LUM: no neighbour pair has point pairs with usable normals at the current poses")
    ei, ej, weight = ei[paired], ej[paired], weight[paired]
    blocks = blocks[paired] * weight[:, None, None]
    gradients = gradients[paired] * weight[:, None]
    sums = sums[paired]
    diag = np.zeros((count, 6, 6))
    rhs = np.zeros((count, 6))
    np.add.at(diag, ei, blocks[:, :6, :6])
    np.add.at(diag, ej, blocks[:, 6:, 6:])
    np.add.at(rhs, ei, -gradients[:, :6])
    np.add.at(rhs, ej, -gradients[:, 6:])
    unused = [k for k in range(count) if k not in fixed and not diag[k].any()]
    system = BlockSystem(count, fixed | set(unused), ei, ej)
    scale = np.einsum("nii->ni", diag)
    damped = diag + (config.damping * scale + 1e-9 * max(float(scale.max()), 1.0))[:, :, None] * np.eye(6)
    step = system.solve(damped, np.ascontiguousarray(blocks[:, :6, 6:]), rhs)
    moved = {}
    for k in range(count):
        if k not in fixed and k not in unused:
            moved[k] = current[k] @ make_pose(so3_exp(step[k, 3:]), step[k, :3])
    return _Round(moved, float(weight @ sums[:, 0]), float(weight @ sums[:, 1]), _plane_rms(sums))


def _plane_rms(sums: FloatArray) -> float:
    """RMS point-to-plane residual of every point pair, unweighted: comparable between rounds
    whatever their robust scale."""
    count = float(sums[:, 2].sum())
    return float(np.sqrt(sums[:, 0].sum() / count)) if count else float("nan")


def _round_residual(models: ScanModels, current: Sequence[Matrix], batches: Sequence[_ScanBatch]) -> float:
    """The rounds' residual at ``current`` without a step: the query of one more round."""
    return _rms(
        [_plane_residuals(models, b.i, _place(b.points, b.source, _relative(current, b.i, b.others))) for b in batches]
    )


def lum_relaxation(
    models: ScanModels,
    poses: Sequence[Matrix],
    fixed: Iterable[int] = (0,),
    config: RelaxationConfig = RelaxationConfig(),
    members: Iterable[int] | None = None,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
) -> RelaxationResult:
    """LUM: all scans solved at once from the closest-point pairs of all neighbour pairs (module docstring).

    The residuals reported come from the rounds' own queries (RMS point-to-plane distance of the
    sampled data points paired within the ICP max distance): before is the first
    round's, at the starting poses; after is the last round's, at the poses it started from when
    that round ended the relaxation by settling (at the final robust scale its step moved no scan
    by more than ``settle_fraction`` of that scale, or changed the robust cost by less than
    ``chi2_tolerance``), otherwise one more query at the final poses.
    """
    began = time.perf_counter()
    before, current, chosen, fixed_set, pairs = _set_up(models, poses, fixed, members, config)
    graph_pairs = _strongest(pairs, len(models), config.max_neighbours)
    _check_graph(models, graph_pairs, fixed_set, chosen)
    batches = _batches(models, graph_pairs, _edge_budget(models, graph_pairs, config))
    held = fixed_set | (set(range(len(models))) - set(chosen))
    first: _Round | None = None
    last: _Round | None = None
    rounds = 0
    settled = False
    previous: float | None = None  # robust cost of the last round at the final robust scale
    for rounds in range(1, config.max_rounds + 1):
        _check_cancel(cancel)
        # graduated robustness: a tight kernel from the start would ignore exactly the centimetre
        # misalignments the relaxation is meant to remove, so the scale halves from the max distance
        scale = config.robust_scale
        if scale > 0:
            scale = max(scale, config.first_scale * 0.5 ** (rounds - 1) * models.config.max_distance)
        last = _joint_step(models, current, batches, held, config, scale)
        first = first or last
        moved = []
        largest = 0.0
        for k, pose in last.moved.items():
            sample = models.thinned(k, 200)
            shift = float(
                np.linalg.norm(transform_points(pose, sample) - transform_points(current[k], sample), axis=1).max()
            )
            largest = max(largest, shift)
            if shift > config.tolerance:
                moved.append(k)
            current[k] = pose
        if progress is not None:
            progress(rounds, last.residual, moved)
        # re-pairing keeps every scan jittering by a fraction of a millimetre, so a round that no
        # longer lowers the robust cost (at the final scale: comparable between rounds) ends it too
        settled = previous is not None and abs(previous - last.cost) <= config.chi2_tolerance * previous
        previous = last.cost if scale <= config.robust_scale else None
        small = largest <= max(config.tolerance, config.settle_fraction * config.robust_scale)
        settled = (small or settled) and scale <= config.robust_scale
        if settled:
            break
    assert first is not None and last is not None
    after = carry_forward(before, current, chosen)
    return RelaxationResult(
        poses=after,
        residual_before=first.residual,
        residual_after=last.residual if settled else _round_residual(models, current, batches),
        iterations=rounds,
        method="lum",
        neighbours=graph_pairs,
        chi2_before=first.chi2,
        chi2_after=last.chi2,
        seconds=time.perf_counter() - began,
    )
