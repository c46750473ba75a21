"""Global relaxation: make every overlapping pair of scans agree at once, not just consecutive ones.

Two methods, both over the same neighbour graph (scans whose reduced clouds share more than
``min_pairs`` closest-point pairs within the ICP max distance, as in the seed):

* :func:`simultaneous_matching` - the seed's method. A queue starts at the first scan of the loop;
  each scan taken from it is re-matched by ICP against the union of its neighbours, and when it
  moves by more than a threshold its neighbours are queued again. The first scan stays fixed.
* :func:`lum_relaxation` - LUM-style: every neighbour pair is matched by ICP to a relative pose with
  an information matrix derived from its point pairs, and all poses are solved for at once by
  sparse least squares (:mod:`slam6d.posegraph`); a few rounds re-match the pairs from the new
  poses. This scales to large graphs because one sparse solve replaces many sweeps of the queue.

Residuals are reported before and after as the RMS closest-point distance over all neighbour
pairs (the quantity both methods reduce). A scan that does not overlap any other relaxed scan
makes the problem ill-posed; that raises :class:`RelaxationError` with the scans named. Scans left
out of the relaxation follow their predecessor rigidly, keeping the trajectory continuous.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import RegistrationError, Slam6dError
from slam6d.geometry import Matrix, invert, transform_points
from slam6d.icp import ICPConfig, ModelIndex, correspondences, icp
from slam6d.posegraph import (
    PoseEdge,
    PoseGraphResult,
    RelaxationError,
    check_connected,
    optimize_pose_graph,
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
    "lum",
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
    max_neighbours: int = 6  # strongest neighbours kept per scan for LUM edges
    edge_points: int = 4000  # data points per edge ICP (evenly thinned), keeps large graphs affordable
    tolerance: float = 0.0005  # metres: stop LUM rounds when no scan moves more


@dataclass
class NeighbourPair:
    i: int
    j: int
    pairs: int  # closest-point pairs within the ICP max distance (estimated from a thinned data cloud)


@dataclass
class RelaxationResult:
    poses: list[Matrix]
    residual_before: float  # RMS closest-point distance over neighbour pairs, metres
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

    def thinned(self, k: int, count: int) -> FloatArray:
        pts = self.points[k]
        if len(pts) <= count:
            return pts
        return pts[np.linspace(0, len(pts) - 1, count).round().astype(np.int64)]

    def extent(self, k: int) -> float:
        return float(np.percentile(np.linalg.norm(self.points[k], axis=1), 95))


class UnionIndex(ModelIndex):
    """Several scans placed in the world as one model (a metascan, or a scan's neighbours)."""

    def __init__(self, models: ScanModels, members: Sequence[int], poses: Sequence[Matrix]) -> None:
        self.members = list(members)
        super().__init__(
            np.concatenate([transform_points(poses[k], models.points[k]) for k in self.members]),
            normal_neighbours=models.config.normal_neighbours,
            normal_voxel_size=models.config.normal_voxel_size,
            backend=models.config.nn_backend,
            threads=models.config.threads,
        )


def neighbour_pairs(
    models: ScanModels,
    poses: Sequence[Matrix],
    min_pairs: int = 250,
    members: Iterable[int] | None = None,
    sample: int = 2000,
) -> list[NeighbourPair]:
    """Scan pairs with more than ``min_pairs`` closest-point pairs at the current poses.

    Only pairs whose scanned regions can touch (distance below the sum of their 95th-percentile
    ranges) are counted, on an evenly thinned copy of the data scan scaled back up; that turns an
    O(n²) sweep of full queries into a handful of cheap ones per scan.
    """
    chosen = sorted(set(range(len(models))) if members is None else set(members))
    extents = {k: models.extent(k) for k in chosen}
    found = []
    d = models.config.max_distance
    for a_pos, i in enumerate(chosen):
        for j in chosen[a_pos + 1 :]:
            if np.linalg.norm(poses[i][:3, 3] - poses[j][:3, 3]) > extents[i] + extents[j]:
                continue
            data = models.thinned(j, sample)
            scale = len(models.points[j]) / len(data)
            _, idx = models.index(i).nearest(transform_points(invert(poses[i]) @ poses[j], data), d)
            count = int(np.count_nonzero(idx >= 0) * scale)
            if count > min_pairs:
                found.append(NeighbourPair(i, j, count))
    return found


def pair_residual(
    models: ScanModels, poses: Sequence[Matrix], pairs: Sequence[NeighbourPair], sample: int = 2000
) -> float:
    """RMS closest-point distance over all neighbour pairs (pairs within the ICP max distance), metres."""
    total, count = 0.0, 0
    for pair in pairs:
        data = models.thinned(pair.j, sample)
        dist, idx = models.index(pair.i).nearest(
            transform_points(invert(poses[pair.i]) @ poses[pair.j], data), models.config.max_distance
        )
        ok = idx >= 0
        total += float(np.sum(dist[ok] ** 2))
        count += int(ok.sum())
    return float(np.sqrt(total / count)) if count else float("nan")


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
    before = [np.array(p) for p in poses]
    current = [np.array(p) for p in poses]
    chosen = sorted(set(range(len(models))) if members is None else set(members))
    fixed_set = {f for f in fixed if f in chosen} or {chosen[0]}
    pairs = neighbour_pairs(models, current, config.min_pairs, chosen)
    check_connected(len(models), [(p.i, p.j) for p in pairs], fixed_set | (set(range(len(models))) - set(chosen)))
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


def lum(
    poses: Sequence[Matrix],
    edges: Sequence[PoseEdge],
    fixed: Iterable[int] = (0,),
    max_iterations: int = 30,
    progress: Callable[[int, float], None] | None = None,
) -> PoseGraphResult:
    """Relax a pose graph given as relative-pose edges (see :func:`slam6d.posegraph.optimize_pose_graph`)."""
    return optimize_pose_graph(poses, edges, fixed=fixed, max_iterations=max_iterations, progress=progress)


def _strongest(pairs: Sequence[NeighbourPair], count: int, keep: int) -> list[NeighbourPair]:
    """Each scan's ``keep`` strongest neighbour pairs, plus every consecutive pair (the trajectory's spine)."""
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


def lum_relaxation(
    models: ScanModels,
    poses: Sequence[Matrix],
    fixed: Iterable[int] = (0,),
    config: RelaxationConfig = RelaxationConfig(),
    members: Iterable[int] | None = None,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
) -> RelaxationResult:
    """LUM: match all neighbour pairs, solve the pose graph, repeat from the new poses (module docstring)."""
    began = time.perf_counter()
    before = [np.array(p) for p in poses]
    current = [np.array(p) for p in poses]
    chosen = sorted(set(range(len(models))) if members is None else set(members))
    fixed_set = {f for f in fixed if f in chosen} or {chosen[0]}
    pairs = neighbour_pairs(models, current, config.min_pairs, chosen)
    graph_pairs = _strongest(pairs, len(models), config.max_neighbours)
    outside = set(range(len(models))) - set(chosen)
    check_connected(len(models), [(p.i, p.j) for p in graph_pairs], fixed_set | outside)
    residual_before = pair_residual(models, current, pairs)
    chi2_before: float | None = None
    chi2_after: float | None = None
    rounds = 0
    index_of = {k: n for n, k in enumerate(chosen)}
    for rounds in range(1, config.max_rounds + 1):
        edges = []
        for pair in graph_pairs:
            _check_cancel(cancel)
            try:
                edge = match_edge(models, current, pair, config)
            except RegistrationError as exc:
                raise RelaxationError(f"LUM: scans {pair.i} and {pair.j} no longer match: {exc}") from exc
            edges.append(PoseEdge(index_of[edge.i], index_of[edge.j], edge.measurement, edge.information))
        result = optimize_pose_graph(
            [current[k] for k in chosen], edges, fixed=[index_of[f] for f in fixed_set], max_iterations=20
        )
        if chi2_before is None:
            chi2_before = result.residual_before
        chi2_after = result.residual_after
        moved = []
        largest = 0.0
        for n, k in enumerate(chosen):
            sample = models.thinned(k, 200)
            shift = float(
                np.linalg.norm(
                    transform_points(result.poses[n], sample) - transform_points(current[k], sample), axis=1
                ).max()
            )
            largest = max(largest, shift)
            if shift > config.tolerance:
                moved.append(k)
            current[k] = result.poses[n]
        if progress is not None:
            progress(rounds, chi2_after, moved)
        if largest <= config.tolerance:
            break
    after = carry_forward(before, current, chosen)
    return RelaxationResult(
        poses=after,
        residual_before=residual_before,
        residual_after=pair_residual(models, after, pairs),
        iterations=rounds,
        method="lum",
        neighbours=graph_pairs,
        chi2_before=chi2_before,
        chi2_after=chi2_after,
        seconds=time.perf_counter() - began,
    )
