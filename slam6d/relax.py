"""Global relaxation: make every overlapping pair of scans agree at once, not just consecutive ones.

Two methods, both over the same neighbour graph (scans whose reduced clouds share more than
``min_pairs`` closest-point pairs within the ICP max distance, as in the seed):

* :func:`slam6d.simultaneous.simultaneous_matching` - the seed's method: a queue of scans, each
  re-matched by ICP against the union of its neighbours, its neighbours queued again when it moves.
* :func:`slam6d.lum.lum_relaxation` - LUM-style: each round pairs every neighbour pair at the
  current poses and solves one linear system for all poses at once.

This module holds what both share: their settings and result, each scan's model built once
(:class:`ScanModels`), the neighbour graph (:func:`neighbour_graph`), the residual both report, and
:func:`carry_forward`. Residuals are reported before and after as the RMS point-to-plane distance
of sampled data points paired within the ICP max distance with their neighbour scan (the quantity
both methods reduce). Not the closest-point distance: between sparse scans that reads the point
spacing (~11 cm on the simulated loop whether or not the loop is relaxed). A scan that does not
overlap any other relaxed scan makes the problem ill-posed; that raises :class:`RelaxationError`
with the scans named. Scans left out of the relaxation follow their predecessor rigidly, keeping
the trajectory continuous.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from itertools import islice

import numba
import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Cancelled, RelaxationError
from slam6d.geometry import Matrix, invert, path_lengths
from slam6d.icp import ICPConfig
from slam6d.model import ModelIndex
from slam6d.nn import RadiusIndex
from slam6d.posegraph import check_connected

FloatArray = NDArray[np.float64]
Progress = Callable[[int, float, list[int]], None]  # (iteration, residual, scans moved)

__all__ = [
    "Cancelled",
    "NeighbourGraph",
    "NeighbourPair",
    "RelaxationConfig",
    "RelaxationError",
    "RelaxationResult",
    "ScanModels",
    "carry_forward",
    "neighbour_graph",
    "pair_residual",
]


@dataclass(frozen=True)
class RelaxationConfig:
    min_pairs: int = 250  # the seed's neighbour criterion
    move_threshold: float = 0.005  # metres: re-queue neighbours when a scan moves more (simultaneous matching)
    max_rounds: int = 10  # queue pops per scan (simultaneous) / re-matching rounds (LUM)
    lum_icp_iterations: int = 8
    max_neighbours: int = 0  # strongest neighbours kept per scan for LUM edges; 0 = every neighbour pair
    neighbours_per_scan: int = 48  # the neighbour graph's bound: pairs per scan (0 = every overlapping pair)
    edge_points: int = 4000  # data points per edge (evenly thinned), at most
    min_edge_points: int = 50  # and at least
    overlap_exponent: float = 1.0  # a pair's weight in LUM grows with its overlap to this power
    pair_points: int = 250  # data points per LUM round and graph pair on average, shared in proportion to overlap
    round_points: int = 0  # a cap on the data points per LUM round (0 = none)
    min_round_points: int = 300_000  # and a floor: few scans' pairs leave the sample's noise in the poses
    first_scale: float = 0.2  # first LUM round's Cauchy scale / the ICP max distance (x 0.25 m: the final scale)
    tolerance: float = 0.0005  # metres: stop LUM rounds when no scan moves more
    settle_fraction: float = 0.2  # or when none moves more than this fraction of the final robust scale (lum._settled)
    chi2_tolerance: float = 0.005  # or when a round at the final robust scale changes the robust cost less (fraction)
    damping: float = 1e-3  # LUM: a scan's directions weaker than this x its strongest are held (lum._damped)
    robust_scale: float = 0.05  # metres: final Cauchy scale of the LUM point-to-plane residuals (0 = least squares)
    coarse_fraction: float = 0.25  # LUM's first rounds sample this share of pair_points (1 = all rounds at full)
    coarse_chi2_tolerance: float = 0.05  # until a round changes their robust cost less: then the full sample
    settle_on: str = "cost"  # what ends LUM's rounds: "cost" or "movement" (the scans', lum._settled)
    steady_tolerance: float = 0.005  # metres: full rounds go on while carrying the scans one way more (lum._settled)
    acceleration_depth: int = 1  # LUM: Anderson mixing of this many past rounds (0 = plain rounds; lum._Accelerator)

    def __post_init__(self) -> None:
        # a share above 1 would silently mean "every round on the full sample"; say so instead
        if not 0 < self.coarse_fraction <= 1:
            raise ValueError(
                f"coarse_fraction must be in (0, 1] (1 = every round on the full sample), got {self.coarse_fraction}"
            )
        if self.settle_on not in ("cost", "movement"):
            raise ValueError(f"settle_on must be 'cost' or 'movement', got {self.settle_on!r}")
        if not (self.coarse_chi2_tolerance >= 0 and math.isfinite(self.coarse_chi2_tolerance)):
            raise ValueError(f"coarse_chi2_tolerance must be a fraction >= 0, got {self.coarse_chi2_tolerance}")
        if self.acceleration_depth < 0:
            raise ValueError(f"acceleration_depth must be >= 0 (0 = plain rounds), got {self.acceleration_depth}")
        if self.min_round_points < 0:
            raise ValueError(f"min_round_points must be >= 0 (0 = no floor), got {self.min_round_points}")
        if not self.steady_tolerance >= 0:  # inf: the cost's test alone; NaN would never settle
            raise ValueError(f"steady_tolerance must be metres >= 0, got {self.steady_tolerance}")


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
            self._thinned[key] = pts[spread_evenly(np.array([len(pts)]), np.array([count]))[0]]
        return self._thinned[key]

    def extent(self, k: int) -> float:
        if k not in self._extents:
            self._extents[k] = float(np.percentile(np.linalg.norm(self.points[k], axis=1), 95))
        return self._extents[k]


def placed_in(
    models: ScanModels, poses: Sequence[Matrix], i: int, others: Sequence[int], count: int | Sequence[int]
) -> tuple[FloatArray, FloatArray, NDArray[np.int64], FloatArray]:
    """Thinned points of each scan in ``others`` placed in scan i's frame, stacked for one query.

    Returns the placed points, the same points in their own frames, the position in ``others``
    each point came from, and the relative poses inv(X_i) X_j. Querying scan i's tree once with
    all of them replaces one query (and its Python overhead) per pair.
    """
    points, source = gathered(models, others, count)
    relative = relative_poses(poses, i, others)
    return place(points, source, relative), points, source, relative


def spread_evenly(lengths: NDArray[np.int64], counts: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """For scans of ``lengths`` points, ``counts`` indices each spread evenly from the first point
    to the last (all of them where a scan has no more than that), stacked; and which scan each
    index is of. The indices are ``np.linspace(0, length - 1, count).round()``'s, bit for bit,
    computed for every scan at once: a LUM relaxation samples a budget of its own for every pair,
    and one linspace per pair (16,000 pairs at 400 scans, two samples) cost 0.6 s under cProfile."""
    lengths = np.asarray(lengths, dtype=np.int64)
    counts = np.minimum(np.asarray(counts, dtype=np.int64), lengths)
    source = np.repeat(np.arange(len(counts)), counts)
    starts = np.cumsum(counts) - counts
    position = (np.arange(len(source)) - starts[source]).astype(np.float64)
    step = (lengths - 1).astype(np.float64) / np.maximum(counts - 1, 1)  # linspace's delta / (num - 1)
    spread = position * step[source]
    ends = counts > 1  # linspace sets the last value to the end exactly (a single one stays at 0)
    spread[(starts + counts - 1)[ends]] = (lengths - 1)[ends]
    return spread.round().astype(np.int64), source


def gathered(
    models: ScanModels, others: Sequence[int], counts: int | Sequence[int]
) -> tuple[FloatArray, NDArray[np.int64]]:
    """The thinned points of each scan in ``others`` (in its own frame) stacked, and the position in
    ``others`` each came from: the points :meth:`ScanModels.thinned` gives. One ``count`` for all
    takes the cached copies (the neighbour graph samples every scan the same way for many
    others); a count per scan (a LUM budget's, nearly every pair's its own) spreads them without
    caching a copy per count."""
    if isinstance(counts, int | np.integer):
        own = [models.thinned(j, counts) for j in others]
        return np.concatenate(own), np.repeat(np.arange(len(others)), [len(d) for d in own])
    index, source = spread_evenly(np.array([len(models.points[j]) for j in others]), np.asarray(counts))
    bounds = np.searchsorted(source, np.arange(len(others) + 1))
    own = [models.points[j][index[a:b]] for j, a, b in zip(others, bounds[:-1], bounds[1:], strict=True)]
    return np.concatenate(own), source


def relative_poses(
    poses: Sequence[Matrix] | FloatArray, i: int, others: Sequence[int] | NDArray[np.int64]
) -> FloatArray:
    """inv(X_i) X_j for every j in ``others``, stacked. ``poses`` as one (n, 4, 4) array (what a
    round that places every scan's neighbours passes) saves stacking them anew for every scan."""
    if isinstance(poses, np.ndarray):
        return np.matmul(invert(poses[i]), poses[np.asarray(others, dtype=np.int64)])
    return np.matmul(invert(poses[i]), np.stack([poses[j] for j in others]))


@numba.njit(cache=True, nogil=True)
def place(points, source, relative):  # type: ignore[no-untyped-def]
    """Each point moved by the relative pose of the pair it belongs to (one pass, no (n, 3, 3) gather)."""
    out = np.empty_like(points)
    for n in range(points.shape[0]):
        r = relative[source[n]]
        x, y, z = points[n, 0], points[n, 1], points[n, 2]
        for a in range(3):
            out[n, a] = r[a, 0] * x + r[a, 1] * y + r[a, 2] * z + r[a, 3]
    return out


def by_model(pairs: Sequence[NeighbourPair]) -> dict[int, list[int]]:
    grouped: dict[int, list[int]] = {}
    for pair in pairs:
        grouped.setdefault(pair.i, []).append(pair.j)
    return grouped


@dataclass(frozen=True)
class NeighbourGraph:
    """The overlapping scan pairs found, and how many pairs had their overlap counted to find them
    (the graph's cost: each count is one query of a thinned scan against another's tree)."""

    pairs: list[NeighbourPair]
    counted: int


def neighbour_graph(
    models: ScanModels,
    poses: Sequence[Matrix],
    min_pairs: int = 250,
    members: Iterable[int] | None = None,
    sample: int = 200,
    links: Iterable[tuple[int, int]] = (),
    per_scan: int = 0,
) -> NeighbourGraph:
    """Scan pairs with more than ``min_pairs`` closest-point pairs at the current poses.

    A pair in ``links`` (scans registered one onto the other, e.g. consecutive scans of sequential
    matching) is kept with any closest-point pairs at all: the registration related the two scans,
    so a sparse scan whose overlap falls under ``min_pairs`` must not cut the graph there.

    Only pairs whose scanned regions can touch (distance below the sum of their 95th-percentile
    ranges) are counted, found through a radius index over the scan positions, on an evenly thinned
    copy of the data scan scaled back up (:class:`_Overlaps`); that turns an O(n²) sweep of full
    queries into one cheap query per scan.

    ``per_scan`` > 0 bounds the graph to ``per_scan`` x scans pairs however densely the scans lie.
    Each scan has its overlap counted with ``2 x per_scan`` candidates spread along the path
    (:func:`_spread_candidates`), the pairs counted already from the other side included: a scan
    only adds candidates until it has that many, so the pairs counted stay near ``per_scan`` per
    scan whatever the density (without the pairs counted from the other side in its tally, every
    scan of a 400-scan loop counted 96 candidates of its own, most not mutual: 78 pairs per scan
    against 49 at 100 scans, where almost every pair lies within the bound). When the overlapping
    pairs found exceed the bound, each scan keeps ``per_scan`` of the ``2 x per_scan`` counted pairs
    it ranks first (:func:`_bounded_choice`), otherwise all of them are kept (BALM hall's 89 scans
    all overlap: 3,916 pairs, and every one dropped there cost accuracy, measured with 48 or 64 per
    scan: far-apart self-consistency 1.90-1.94 instead of 1.88 cm). With 0 every overlapping pair
    is kept, and their number grows with the square of the density (a 98 m loop: 3,413 pairs at 100
    scans, 52,776 at 400).
    """
    chosen = sorted(set(range(len(models))) if members is None else set(members))
    linked = {(min(i, j), max(i, j)) for i, j in links}
    if len(chosen) < 2:
        return NeighbourGraph([], 0)
    ids = np.array(chosen, dtype=np.int64)
    extents = np.array([models.extent(k) for k in chosen])
    centres = np.array([poses[k][:3, 3] for k in chosen])
    nearby = RadiusIndex(centres)
    widest = float(extents.max())

    def near(a_pos: int) -> NDArray[np.int64]:
        """The scans whose reach overlaps scan ``chosen[a_pos]``'s, ascending."""
        ball = nearby.within(centres[a_pos], extents[a_pos] + widest)
        ball = ball[ball != a_pos]
        gaps = np.linalg.norm(centres[ball] - centres[a_pos], axis=1)
        return ids[np.sort(ball[gaps <= extents[a_pos] + extents[ball]])]

    overlaps = _Overlaps(models, poses, sample)
    keep: set[tuple[int, int]] = set()
    if per_scan <= 0:
        for a_pos, i in enumerate(chosen):
            later = [int(j) for j in near(a_pos) if j > i]
            overlaps.count(i, later)
            keep.update((i, j) for j in later)
    else:
        travelled = path_lengths(poses)
        positions = np.array([p[:3, 3] for p in poses])
        on_path = [_ScanOnPath(i, positions, travelled, extents[a_pos], per_scan) for a_pos, i in enumerate(chosen)]
        candidates = []
        for a_pos, i in enumerate(chosen):
            counted = overlaps.of(i)
            order = _spread_candidates(on_path[a_pos], near(a_pos))  # the sequential neighbours first
            sequential = sum(1 for j in order[:2] if abs(j - i) == 1 and j not in counted)
            room = max(2 * per_scan - len(counted), sequential)
            overlaps.count(i, list(islice((j for j in order if j not in counted), room)))
            # what scan i chooses from: the 2 x per_scan of its counted pairs it ranks first
            ranked = np.array(order, dtype=np.int64)
            candidates.append(ranked[np.isin(ranked, list(counted))][: max(2 * per_scan, sequential)].tolist())
        keep = {key for key, found in overlaps.found.items() if found > min_pairs}
        if len(keep) > per_scan * len(chosen):  # within the bound the whole graph is kept: nothing to choose
            keep = set()
            for scan, pool in zip(on_path, candidates, strict=True):
                counted = overlaps.of(scan.i)
                overlapping = [j for j in pool if counted[j] > min_pairs]
                for j in _bounded_choice(scan, overlapping, {j: counted[j] for j in overlapping}):
                    keep.add((min(scan.i, j), max(scan.i, j)))
    members_set = set(chosen)
    for i, j in linked:  # a registration related the two scans: kept with any pairs at all
        if i in members_set and j in members_set:
            overlaps.count(i, [j])
            keep.add((i, j))
    found = overlaps.found
    pairs = [
        NeighbourPair(i, j, found[(i, j)])
        for i, j in sorted(keep)
        if found[(i, j)] > min_pairs or (found[(i, j)] > 0 and (i, j) in linked)
    ]
    return NeighbourGraph(pairs, len(found))


class _Overlaps:
    """Closest-point pairs of scan pairs, each pair counted once (from whichever scan asks first).

    A pair's count is an estimate: ``sample`` evenly thinned points of scan j placed in scan i's
    frame and found in its tree within the ICP max distance, scaled up to j's size. A quarter of
    ``sample`` is tried first: a pair where a third of it finds partners is far above any useful
    ``min_pairs`` and keeps that estimate; only the others are counted on the full ``sample``.
    """

    def __init__(self, models: ScanModels, poses: Sequence[Matrix], sample: int) -> None:
        self.models = models
        self.poses = poses
        self.sample = sample
        self.found: dict[tuple[int, int], int] = {}
        self._partners: dict[int, dict[int, int]] = {}

    def of(self, i: int) -> dict[int, int]:
        """Scan i's counted pairs so far: partner -> closest-point pairs (a live view)."""
        return self._partners.setdefault(i, {})

    def count(self, i: int, others: Sequence[int]) -> None:
        """Count the pairs (i, j) for every j in ``others`` not counted yet: one query of scan i's tree."""
        counted = self.of(i)
        todo = [j for j in others if j not in counted]
        if not todo:
            return
        hits, sizes = self._hits(i, todo, max(1, self.sample // 4))
        unsure = hits * 3 < sizes
        if unsure.any():
            hits[unsure], sizes[unsure] = self._hits(
                i, [j for j, u in zip(todo, unsure, strict=True) if u], self.sample
            )
        for j, hit, size in zip(todo, hits.tolist(), sizes.tolist(), strict=True):
            found = int(hit * len(self.models.points[j]) / size)
            self.found[(i, j) if i < j else (j, i)] = found
            counted[j] = found
            self.of(j)[i] = found

    def _hits(self, i: int, others: Sequence[int], sample: int) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        """Per scan of ``others``: how many of its ``sample`` thinned points have a partner in scan i, of how many."""
        placed, _, source, _ = placed_in(self.models, self.poses, i, others, sample)
        _, idx = self.models.index(i).nearest(placed, self.models.config.max_distance)
        return np.bincount(source[idx >= 0], minlength=len(others)), np.bincount(source, minlength=len(others))


SECTORS = 8  # bearings a scan's neighbours are spread over
STRETCH = 0.25  # a path stretch (the unit neighbours are spread along) as a fraction of the scan's reach


@dataclass(frozen=True)
class _ScanOnPath:
    """Scan ``i`` where it lies - every scan's position, how far along the path each lies, how far
    scan i reaches - and its bound of neighbours: what choosing the scans it is paired with needs."""

    i: int
    positions: FloatArray
    travelled: FloatArray
    reach: float
    per_scan: int

    def stretches(self, others: NDArray[np.int64] | Sequence[int]) -> FloatArray:
        """Which stretch of the path each of ``others`` lies on, counted from scan i (signed: before or after it)."""
        return np.floor((self.travelled[np.asarray(others)] - self.travelled[self.i]) / max(STRETCH * self.reach, 1e-9))

    def sectors(self, others: NDArray[np.int64] | Sequence[int]) -> NDArray[np.int64]:
        """The bearing sector around scan i that each of ``others`` lies in."""
        d = self.positions[np.asarray(others, dtype=np.int64)] - self.positions[self.i]
        return np.floor((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * SECTORS).astype(np.int64) % SECTORS

    def gaps(self, others: NDArray[np.int64]) -> FloatArray:
        """How far each of ``others`` lies from scan i (metres): the order within a path stretch."""
        return np.linalg.norm(self.positions[others] - self.positions[self.i], axis=1)


def _spread_candidates(scan: _ScanOnPath, near: NDArray[np.int64]) -> list[int]:
    """The scans worth counting overlap with for scan i, best first: its sequential neighbours,
    then the closest scan of each path stretch (a quarter of its reach) in reach, then the second
    closest of each, and so on, nearer ones first within each round.

    The stretches make the order independent of how densely the path is scanned: a revisit from
    the other direction, much farther along the path, is a stretch of its own and gets its
    candidates before a tenth scan of the stretch scan i lies on.
    """
    sequential = [j for j in (scan.i - 1, scan.i + 1) if j in set(near.tolist())]
    if len(near) == 0:
        return sequential
    gaps = scan.gaps(near)
    stretches = scan.stretches(near)
    order = np.lexsort((gaps, stretches))  # by stretch, the closest first within each
    sorted_stretches = stretches[order]
    starts = np.flatnonzero(np.r_[True, sorted_stretches[1:] != sorted_stretches[:-1]])
    rank = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    spread = near[order[np.lexsort((gaps[order], rank))]]
    return sequential + spread[~np.isin(spread, sequential)].tolist()


def _bounded_choice(scan: _ScanOnPath, overlapping: Sequence[int], strength: dict[int, int]) -> list[int]:
    """At most ``per_scan`` neighbours of scan i, chosen by overlap but spread in direction and along the path.

    The sequential neighbours first (the trajectory's spine keeps every scan connected), then the
    best-overlapping scan of each bearing sector around scan i, then round by round over the path's
    stretches (the best of each, then the second best of each, ...). Overlap alone would spend the whole bound on the
    scans just before and after (the same stretch of path, seen the same way); the pairs that make
    a map globally consistent are the ones seen from elsewhere.
    """
    candidates = np.asarray(overlapping, dtype=np.int64)
    strengths = np.array([strength[j] for j in overlapping], dtype=np.int64)
    ranked = candidates[np.argsort(-strengths, kind="stable")]
    picked = [j for j in (scan.i - 1, scan.i + 1) if j in strength]
    others = ranked[~np.isin(ranked, picked)]
    _, first_of_sector = np.unique(scan.sectors(others), return_index=True)  # the best of each sector
    picked += others[np.sort(first_of_sector)].tolist()
    picked = picked[: max(scan.per_scan, 2)]
    # then round by round over the path's stretches: the best of each stretch not represented yet,
    # then the second best of each, ... (a scan's own stretch holds the most, and the most alike)
    rest = ranked[~np.isin(ranked, picked)]
    if len(rest) == 0 or len(picked) >= scan.per_scan:
        return picked
    stretches = scan.stretches(rest)
    taken, taken_counts = np.unique(scan.stretches(picked), return_counts=True) if picked else (np.zeros(0), [])
    already = dict(zip(taken.tolist(), np.asarray(taken_counts).tolist(), strict=True))
    order = np.argsort(stretches, kind="stable")  # within a stretch: ranked (best first) order kept
    sorted_stretches = stretches[order]
    starts = np.flatnonzero(np.r_[True, sorted_stretches[1:] != sorted_stretches[:-1]])
    within = np.arange(len(order)) - np.repeat(starts, np.diff(np.r_[starts, len(order)]))
    rounds = np.empty(len(rest), dtype=np.int64)
    rounds[order] = within + 1 + np.array([already.get(s, 0) for s in sorted_stretches.tolist()], dtype=np.int64)
    rest_strength = np.array([strength[j] for j in rest.tolist()], dtype=np.int64)
    by_round = np.lexsort((rest, -rest_strength, rounds))
    return picked + rest[by_round[: scan.per_scan - len(picked)]].tolist()


def measured_result(
    models: ScanModels,
    pairs: list[NeighbourPair],
    poses: list[Matrix],
    residual_before: float,
    iterations: int,
    method: str,
    began: float,
    chi2: Sequence[float] = (),
) -> RelaxationResult:
    """A relaxation's result, its residual measured afresh over its neighbour pairs at the poses it
    reached (the methods that do not already know it from their last round); ``began``: its
    ``time.perf_counter()`` at the start; ``chi2``: the pose-graph error per round, if it has one."""
    return RelaxationResult(
        poses=poses,
        residual_before=residual_before,
        residual_after=pair_residual(models, poses, pairs),
        iterations=iterations,
        method=method,
        neighbours=pairs,
        chi2_before=chi2[0] if chi2 else None,
        chi2_after=chi2[-1] if chi2 else None,
        seconds=time.perf_counter() - began,
    )


def pair_residual(
    models: ScanModels, poses: Sequence[Matrix], pairs: Sequence[NeighbourPair], sample: int = 150
) -> float:
    """RMS point-to-plane distance over all neighbour pairs (pairs within the ICP max distance), metres."""
    residuals = [
        plane_residuals(models, i, placed_in(models, poses, i, others, sample)[0])
        for i, others in by_model(pairs).items()
    ]
    return rms(residuals)


def plane_residuals(models: ScanModels, i: int, placed: FloatArray) -> FloatArray:
    """Point-to-plane residuals of ``placed`` (scan i's frame) against scan i's plane model."""
    return models.plane_model(i).plane_residuals(placed, models.config.max_distance)


def rms(residuals: Sequence[FloatArray]) -> float:
    count = sum(len(r) for r in residuals)
    return float(np.sqrt(sum(float(r @ r) for r in residuals) / count)) if count else float("nan")


def adjacency(pairs: Sequence[NeighbourPair], count: int) -> list[list[int]]:
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


def check_cancel(cancel: Callable[[], bool] | None) -> None:
    if cancel is not None and cancel():
        raise Cancelled("relaxation cancelled")


def set_up(
    models: ScanModels,
    poses: Sequence[Matrix],
    fixed: Iterable[int],
    members: Iterable[int] | None,
    config: RelaxationConfig,
    links: Iterable[tuple[int, int]] = (),
) -> tuple[list[Matrix], list[Matrix], list[int], set[int], list[NeighbourPair]]:
    """What both relaxations start from: poses before and working copies, the scans taking part,
    the fixed ones among them (the first member when none is), and the overlapping pairs (``links``:
    see :func:`neighbour_graph`)."""
    before = [np.array(p) for p in poses]
    current = [np.array(p) for p in poses]
    chosen = sorted(set(range(len(models))) if members is None else set(members))
    fixed_set = {f for f in fixed if f in chosen} or {chosen[0]}
    graph = neighbour_graph(
        models, current, config.min_pairs, chosen, links=links, per_scan=config.neighbours_per_scan
    ).pairs
    return before, current, chosen, fixed_set, graph


def check_graph(models: ScanModels, pairs: Sequence[NeighbourPair], fixed: set[int], chosen: list[int]) -> None:
    """Refuse a graph in which some member is not tied to a fixed scan (scans left out count as fixed)."""
    outside = set(range(len(models))) - set(chosen)
    check_connected(len(models), [(p.i, p.j) for p in pairs], fixed | outside)
