"""LUM-style global relaxation: all scans solved at once from the closest-point pairs of all neighbours.

Like 3DTK's LUM, each round takes the closest-point pairs of every neighbour pair (see
:mod:`slam6d.relax`) at the current poses and solves one linear system for all poses at once
(here with point-to-plane residuals, Cauchy-weighted with a scale that halves from the ICP max
distance each round, and a sparse solve); the next round re-pairs from the new poses. No pair is
re-matched by ICP, so a round costs one closest-point query per data point of each edge; a round
samples ``pair_points`` data points per overlapping pair on average (so the budget grows with the
graph, not with a fixed total), shared among all pairs (the long-range ones that make a map
globally consistent included) in proportion to their overlap. Each scan's plane-sample tree
(built once) is queried once per round by the points of all its neighbours at once (against the
registration's model when one was handed over, :meth:`slam6d.relax.ScanModels.share_plane_model`),
the normal blocks of all pairs of a scan are summed in one compiled pass, and the joint system
goes to :class:`slam6d.block_system.BlockSystem`. Rounds stop (by default, ``settle_on="cost"``;
the other rule below) once a round at the final robust scale moves no scan by more than
``settle_fraction`` of that scale, or changes the Cauchy-weighted cost by less than
``chi2_tolerance`` (re-pairing keeps scans jittering below a millimetre, so the movement alone may
never fall under ``tolerance``). The residuals reported come from the rounds' own queries, so
reporting costs no extra pass.

Each round goes only part of the way (on the dense simulated loop the ATE roughly halves per
round, whatever the robust scale: the closest-point pairs are drawn at the current poses), so the
rounds needed grow with how far off the relaxation starts: 5 rounds at 100 scans (3.3 cm after
loop closing), 8 at 400 (25.4 cm), each round's work following the pairs. Because that
contraction is steady, each round's result is mixed with the round's before by Anderson's
method (``acceleration_depth``, :class:`_Accelerator`, :mod:`slam6d.acceleration`): at 400 scans
the second round then ends at 2.3 cm instead of 8.0 cm, and LUM ends in 6 rounds at 0.15 cm
instead of 8 at 0.19 cm (docs/scale.md, "Mixing the rounds"). A round samples at least
``min_round_points``: on a few scans the per-pair sample is so small that its own optimum lies
centimetres off the scans'. The first
rounds also run on a thin sample (``coarse_fraction`` of ``pair_points``, the same pairs)
until a round changes its robust cost by less than ``coarse_chi2_tolerance``; the full sample then
refines in two or three rounds whatever the start (docs/scale.md, "The rounds' sample"). The
chi2 and robust cost of a thin round are scaled by the full sample's points over its own, so the
chi2 reported before (the first round's) is an estimate of the full sample's, within a few per cent. On the
400 scans this took 15.8 instead of 21.9 s of CPU to an ATE of 0.20 instead of 0.25 cm.

The thin rounds change where the rounds stop, not where they converge. The settle tests fire while
rounds still move the scans by millimetres (the robust cost is mostly the scanner's noise: on the
400 scans it changed by 0.26 % in the round that took the ATE from 0.42 to 0.26 cm), so each
relaxation ends part of the way along its own path: from the start with every round on the full
sample, from the thin sample's own optimum after thin rounds (a few millimetres off the full
sample's; on BALM hall its consecutive RPE is 0.74 cm). Hence BALM's RPE was 0.55 cm with the
thin rounds and 0.53 cm without: run without settling, both reach the same poses (0.03 mm apart on
average), RPE 0.535 cm / 0.042°, where the mixed rounds now end too (0.535 cm). The full rounds do
not settle on the cost while they still carry the scans one way (``steady_tolerance``,
:func:`_settled`). ``settle_on="movement"`` ends the rounds on the scans' movement
instead (:func:`_settled`): the two then end 0.23 mm apart on BALM, but it costs the 400 scans 50 %
more CPU, and on a VLP-16 campus, whose rounds keep moving scans by centimetres, it let relaxing a
run's poses again drift off the map, so the cost stays the default (docs/scale.md, "The rounds'
sample": where the rounds stop).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numba
import numpy as np
from numpy.typing import NDArray

from slam6d.acceleration import AndersonMixer, PoseChart
from slam6d.attitude import TiltPrior, measured_ups, tilt_information
from slam6d.block_system import BlockSystem
from slam6d.errors import RelaxationError
from slam6d.geometry import Matrix, invert, make_pose, so3_exp, transform_points
from slam6d.icp import correspondences, icp
from slam6d.model import on_the_seen_side
from slam6d.nn import build_index
from slam6d.posegraph import PoseEdge, point_pair_information
from slam6d.relax import (
    FloatArray,
    NeighbourPair,
    Progress,
    RelaxationConfig,
    RelaxationResult,
    ScanModels,
    by_model,
    carry_forward,
    check_cancel,
    check_graph,
    gathered,
    place,
    plane_residuals,
    relative_poses,
    rms,
    set_up,
)

if TYPE_CHECKING:
    from slam6d.scheduler import Scheduler

__all__ = ["lum_relaxation", "match_edge", "pair_information"]


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
    return PoseEdge(pair.i, pair.j, result.transform, pair_information(models, pair, result.transform, config))


def pair_information(models: ScanModels, pair: NeighbourPair, relative: Matrix, config: RelaxationConfig) -> Matrix:
    """LUM's information matrix of scan j placed at ``relative`` in scan i's frame, from their closest-point pairs.

    What a relaxation weighs an edge by, and what a g2o export writes for it. Without pairs (the scans
    do not overlap at that pose) the information is zero: the edge says nothing.
    """
    data = models.thinned(pair.j, config.edge_points)
    model = models.index(pair.i)
    data_idx, model_idx = correspondences(model, data, relative, models.config.max_distance, limit=-1)
    placed = transform_points(relative, data[data_idx])
    sigma2 = float(np.mean(np.sum((placed - model.points[model_idx]) ** 2, axis=1))) if len(data_idx) else 1.0
    # floor sigma at a millimetre: a perfect synthetic match must not get infinite weight
    return point_pair_information(placed, relative, max(sigma2, 1e-6))


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
    for i, others in by_model(graph_pairs).items():
        points, source = gathered(models, others, [budget[(i, j)][0] for j in others])
        weights = np.array([budget[(i, j)][1] for j in others])
        batches.append(_ScanBatch(i, np.array(others, dtype=np.int64), points, source, weights))
    return batches


@dataclass
class _SharedBatch:
    """What a worker needs of one scan's share of the rounds, sent once per relaxation
    (:meth:`slam6d.scheduler.Scheduler.share`): scan i's plane sample with every normal estimated,
    and its batch's points. Rounds then send only the relative poses."""

    sample: FloatArray  # scan i's plane sample, own frame
    normals: FloatArray
    usable: NDArray[np.bool_]
    points: FloatArray
    source: NDArray[np.int64]
    pairs: int
    backend: str
    views: FloatArray | None = None  # where scan i's scanner saw each sample point from, if known


def _shared_batch(models: ScanModels, batch: _ScanBatch) -> _SharedBatch:
    model = models.plane_model(batch.i)
    sample, normals, usable = model.plane_normals()
    views = model.sample_viewpoints(np.arange(len(sample)))
    views = None if views is None else np.ascontiguousarray(views)
    return _SharedBatch(sample, normals, usable, batch.points, batch.source, len(batch.others), model.backend, views)


def _remote_scan_system(
    shared: _SharedBatch, relative: FloatArray, robust_scale: float, max_distance: float
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`_scan_system` on a worker: the same query and blocks from plain arrays (a one-thread
    kd-tree built here; every normal was estimated before sending, so none is estimated here)."""
    q = place(shared.points, shared.source, relative)
    _, idx = build_index(shared.sample, shared.backend, threads=1).nearest(q, max_distance)
    found = np.flatnonzero(idx >= 0)
    found = found[shared.usable[idx[found]]]
    if shared.views is not None:  # as ModelIndex.plane_pairs: keep to the faces scan i saw
        scanners = relative[:, :3, 3][shared.source[found]]
        partner = idx[found]
        found = found[
            on_the_seen_side(shared.views[partner], scanners, shared.sample[partner], shared.normals[partner])
        ]
    partner = idx[found]
    return _pair_blocks(
        q,
        shared.points,
        found,
        shared.sample[partner],
        shared.normals[partner],
        relative,
        shared.source,
        shared.pairs,
        float(robust_scale),
    )


class _Level:
    """The rounds' point sample at one budget: each scan's batch, and what the workers hold of it."""

    def __init__(
        self,
        models: ScanModels,
        graph_pairs: Sequence[NeighbourPair],
        config: RelaxationConfig,
        scheduler: Scheduler | None,
    ) -> None:
        self.batches = _batches(models, graph_pairs, _edge_budget(models, graph_pairs, config))
        self.shared = scheduler.share([_shared_batch(models, b) for b in self.batches]) if scheduler is not None else []
        self.points = sum(len(b.points) for b in self.batches)  # a round's budget-weighted sums grow with it


@dataclass
class _ScanSystem:
    """Normal-equation blocks of scan i's pairs from one round's query (see :func:`_scan_system`)."""

    blocks: FloatArray  # (pairs, 12, 12) J^T W J, order i then j
    gradients: FloatArray  # (pairs, 12) J^T W r
    sums: FloatArray  # (pairs, 3): sum of r², of w r², point count


def _scan_system(models: ScanModels, current: FloatArray, batch: _ScanBatch, robust_scale: float) -> _ScanSystem:
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
    relative = relative_poses(current, batch.i, batch.others)
    q = place(batch.points, batch.source, relative)
    # each point's scanner in scan i's frame: pairs keep to the faces scan i saw from the same side
    scanners = relative[:, :3, 3][batch.source]
    found, partners, _, normals = model.plane_pairs(q, models.config.max_distance, scanners)
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
    share = np.array([p.pairs / len(models.points[p.j]) for p in graph_pairs])
    total = max(config.pair_points * len(graph_pairs), config.min_round_points)
    if config.round_points > 0:
        total = min(total, config.round_points)
    unit = total / max(float(share.sum()), 1e-9)
    # every pair at once: one np.clip per pair (16,000 pairs at 400 scans, two samples) cost 0.7 s under cProfile
    counts = np.clip(unit * share, config.min_edge_points, config.edge_points).astype(np.int64)
    weights = share**config.overlap_exponent / counts
    weights = weights / (np.mean(counts * weights) / np.mean(counts))
    return {(p.i, p.j): (int(c), float(w)) for p, c, w in zip(graph_pairs, counts, weights, strict=True)}


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
    scheduler: Scheduler | None = None,
    shared: Sequence[Any] = (),
    tilt: TiltPrior | None = None,
    patterns: dict[frozenset[int], BlockSystem] | None = None,
) -> _Round:
    """One Gauss-Newton step of all scans at once over the current closest-point pairs (LUM's round).

    Each scan is queried once, by the thinned points of all its graph neighbours at once; the
    joint system is solved by :class:`slam6d.block_system.BlockSystem`. Each pair's residuals count
    with its budget weight. Damping of only the directions a scan's pairs leave (nearly)
    unconstrained keeps them (a scan seeing one flat wall) from running away (:func:`_damped`).
    ``patterns`` keeps the block systems of earlier rounds by their held scans (the edges are the
    batches' own, fixed for the relaxation): working a pattern out (its ordering and symbolic
    factor) cost more than the factorisations themselves (2.7 of 4.3 s of linear algebra over 6
    rounds on 250 campus scans). ``tilt``: the measured up of each scan as a unary prior on its
    roll and pitch (:func:`_add_tilt_prior`).
    """
    count = len(current)
    placed = np.array(current)  # stacked once: every scan's batch takes its neighbours' poses from it
    if scheduler is None:
        systems = [_scan_system(models, placed, batch, robust_scale) for batch in batches]
    else:
        relatives = [relative_poses(placed, b.i, b.others) for b in batches]
        parts = scheduler.map(
            _remote_scan_system,
            shared,
            relatives,
            [robust_scale] * len(batches),
            [models.config.max_distance] * len(batches),
        )
        systems = [_ScanSystem(*part) for part in parts]
    ei = np.concatenate([np.full(len(b.others), b.i) for b in batches])
    ej = np.concatenate([b.others for b in batches])
    weight = np.concatenate([b.weights for b in batches])
    blocks = np.concatenate([s.blocks for s in systems])
    gradients = np.concatenate([s.gradients for s in systems])
    sums = np.concatenate([s.sums for s in systems])
    if not (sums[:, 2] > 0).any():
        raise RelaxationError("LUM: no neighbour pair has point pairs with usable normals at the current poses")
    # a pair without point pairs this round has zero blocks and stays in the pattern, which so
    # stays the same from round to round
    blocks = blocks * weight[:, None, None]
    gradients = gradients * weight[:, None]
    diag = np.zeros((count, 6, 6))
    rhs = np.zeros((count, 6))
    np.add.at(diag, ei, blocks[:, :6, :6])
    np.add.at(diag, ej, blocks[:, 6:, 6:])
    np.add.at(rhs, ei, -gradients[:, :6])
    np.add.at(rhs, ej, -gradients[:, 6:])
    unused = [k for k in range(count) if k not in fixed and not diag[k].any()]
    held = frozenset(fixed | set(unused))
    if tilt is not None:
        _add_tilt_prior(tilt, current, held, diag, rhs)
    system = patterns.get(held) if patterns is not None else None
    if system is None:
        system = BlockSystem(count, held, ei, ej)
        if patterns is not None:
            patterns[held] = system
    step = system.solve(_damped(diag, config.damping), np.ascontiguousarray(blocks[:, :6, 6:]), rhs)
    movers = np.array([k for k in range(count) if k not in held], dtype=np.int64)
    update = make_pose(so3_exp(step[movers, 3:]), step[movers, :3])  # every free scan's Exp([ρ, φ]) at once
    moved = dict(zip(movers.tolist(), placed[movers] @ update, strict=True))
    return _Round(moved, float(weight @ sums[:, 0]), float(weight @ sums[:, 1]), _plane_rms(sums))


_ROTATION_FIRST = np.array([3, 4, 5, 0, 1, 2])  # a scan's 6x6 block here is translation first


def _damped(diag: FloatArray, damping: float) -> FloatArray:
    """The scans' diagonal blocks with the directions their pairs leave unconstrained held (a copy).

    Each scan's 6x6 block (translation first) is taken in one unit: its rotation scaled by the
    block's own lever arm, sqrt(rotational / translational trace), the RMS distance at which its
    point pairs turn, so that a turn counts by how far it moves the points. Directions of that
    block with less information than ``damping`` times its strongest get that much (a scan
    seeing one flat wall does not slide along it); the others get none. Levenberg's damping in
    proportion to the whole diagonal, which this replaces, tied every scan to its current pose
    in every direction: a spring per scan, which together outweigh the stiffness of a long
    stretch's bend (falling with the stretch's length) and left a heading error spread over an
    open stretch nearly where registration put it. On the 1,000-scan campus of seed 5 the last
    200 scans, which no loop holds, went from 15.6 to 13.3 cm with it and to 4.4 cm with this
    (docs/scale.md, "An open tail: damping that held the bend").
    """
    translational = np.einsum("nii->n", diag[:, :3, :3])
    rotational = np.einsum("nii->n", diag[:, 3:, 3:])
    lever = np.sqrt(np.where(translational > 0.0, rotational / np.maximum(translational, 1e-300), 1.0))
    lever = np.where(lever > 0.0, lever, 1.0)
    unit = np.ones((len(diag), 6))
    unit[:, 3:] = 1.0 / lever[:, None]  # rotation in radians -> metres at the lever
    scaled = diag * unit[:, :, None] * unit[:, None, :]
    values, vectors = np.linalg.eigh(scaled)
    floor = damping * values[:, -1:] + 1e-9 * max(float(values.max()), 1.0)
    lift = np.maximum(floor - values, 0.0)
    added = np.einsum("nij,nj,nkj->nik", vectors, lift, vectors) / (unit[:, :, None] * unit[:, None, :])
    return diag + added


def _add_tilt_prior(
    tilt: TiltPrior,
    current: Sequence[Matrix],
    held: frozenset[int],
    diag: FloatArray,
    rhs: FloatArray,
) -> None:
    """Add each free scan's measured up to its diagonal block and right-hand side (in place).

    The weight (:meth:`slam6d.attitude.TiltPrior.weights`) is the scan's ratio x the tilt information
    of a typical step: the median over the free scans of half the information all of a scan's
    pairs hold on its tilt (this round's Cauchy and budget weights included; half, as a step lies
    between two scans). :mod:`slam6d.attitude` takes a step's information to stand for the
    registration's per-step tilt error, so that the reading and the pairs mix as measurements of
    those two accuracies would. All of a scan's pairs count, not only the consecutive one: LUM
    pairs each scan with several scans along the path (the bounded neighbour graph), and they all
    report the same systematically biased relative tilt, so together they are what holds a step.
    Weighed against the consecutive pair alone the prior moved the 1,000-scan campus's scans
    less: vertical ATE 9.5 cm instead of 4.9 cm (docs/scale.md, "The inclinometer").
    """
    free = np.ones(len(current), dtype=bool)
    free[list(held)] = False
    rotations = np.array([p[:3, :3] for p in current])
    blocks = diag[free][:, _ROTATION_FIRST][:, :, _ROTATION_FIRST]
    weights = tilt.weights(tilt_information(blocks, measured_ups(rotations[free])) / 2.0)
    prior, gradient, _ = tilt.terms(rotations, free, weights)
    diag[:, 3:, 3:] += prior
    rhs[:, 3:] -= gradient


def _plane_rms(sums: FloatArray) -> float:
    """RMS point-to-plane residual of every point pair, unweighted: comparable between rounds
    whatever their robust scale."""
    count = float(sums[:, 2].sum())
    return float(np.sqrt(sums[:, 0].sum() / count)) if count else float("nan")


def _round_residual(models: ScanModels, current: Sequence[Matrix], batches: Sequence[_ScanBatch]) -> float:
    """The rounds' residual at ``current`` without a step: the query of one more round."""
    placed = np.array(current)
    return rms(
        [
            plane_residuals(models, b.i, place(b.points, b.source, relative_poses(placed, b.i, b.others)))
            for b in batches
        ]
    )


def _steady_move(steps: FloatArray, before: FloatArray | None, shifts: Sequence[float]) -> float:
    """How far a round carried the scans the way the round before did: the mean move times the
    cosine between the two rounds' translation steps (every free scan's, stacked; 0 without a round
    before). Re-pairing's jitter turns from round to round (a cosine near 0); a slow mode, such as
    a Cauchy kernel as tight as the scanner's noise pulling misaligned pairs a little each round,
    keeps its way (0.8-1.0)."""
    if before is None or before.shape != steps.shape or not shifts:
        return 0.0
    norms = float(np.linalg.norm(steps) * np.linalg.norm(before))
    cosine = float(steps.ravel() @ before.ravel()) / norms if norms > 0 else 0.0
    return max(cosine, 0.0) * float(np.mean(shifts))


def _settled(
    config: RelaxationConfig,
    thin: bool,
    shifts: Sequence[float],
    cost: float,
    previous: tuple[float, float] | None,
    steady: float = 0.0,
) -> bool:
    """Whether a round at the final robust scale ends its sample's rounds (``previous``: the robust
    cost and mean move of the sample's round before, if that was at the final scale too).

    ``settle_on="cost"``: the robust cost changed by less than ``chi2_tolerance`` (on the thin
    sample ``coarse_chi2_tolerance``), or no scan moved more than ``settle_fraction`` of the robust
    scale (each scan by its largest point move; re-pairing keeps every scan jittering by a fraction
    of a millimetre, so the cost's test is the one that usually ends it). It fires while the rounds
    still move the scans by millimetres, at a point that depends on the path (module docstring).
    On the full sample it does not fire while the round carried the scans on the way the round
    before did by more than ``steady_tolerance`` (``steady``, :func:`_steady_move`): the cost is
    mostly the scanner's noise, and an indoor OS1-64 walk's rounds moved its scans 1.4 cm each, the
    same way, at a cost changing by under 0.5 % (3.17 cm where it ended, 0.40 cm converged;
    docs/scale.md, "Rounds that stop while the scans still move").
    ``"movement"``: the scans moved on average less than ``tolerance`` (on the thin sample less than
    ``settle_fraction`` of the robust scale, about that sample's own scatter: finer rounds on it only
    move the scans about its own optimum), or the rounds are in re-pairing's noise, moving the scans
    no less than the round before.
    """
    if config.settle_on == "cost":
        if not thin and steady > config.steady_tolerance:
            return False
        tolerance = config.coarse_chi2_tolerance if thin else config.chi2_tolerance
        if previous is not None and abs(previous[0] - cost) <= tolerance * previous[0]:
            return True
        return max(shifts, default=0.0) <= max(config.tolerance, config.settle_fraction * config.robust_scale)
    movement = float(np.mean(shifts)) if shifts else 0.0
    if movement <= (config.settle_fraction * config.robust_scale if thin else config.tolerance):
        return True
    return previous is not None and movement >= previous[1]


class _Accelerator:
    """Anderson's mixing of LUM's rounds (:mod:`slam6d.acceleration`), with its safeguard.

    Each round's plain result is mixed with the rounds' before at the same robust scale and sample
    (the iteration's map changes with either, so the history restarts). A mixed iterate whose
    round then finds a higher robust cost than the round it was mixed from is refused: the poses go
    back to that round's plain result and the history restarts, at the price of the round spent.
    """

    def __init__(self, models: ScanModels, start: Sequence[Matrix], depth: int) -> None:
        self.chart = PoseChart(start)
        # a turn weighed by how far it moves a scan's points: its RMS range
        lever = np.array([np.sqrt(np.mean(np.sum(models.thinned(k, 200) ** 2, axis=1))) for k in range(len(models))])
        metric = np.ones((len(models), 6))
        metric[:, 3:] = lever[:, None]
        self.mixer = AndersonMixer(depth, metric)
        self.key: tuple[int, float] | None = None
        self.pending: tuple[float, dict[int, Matrix]] | None = None  # (cost before, plain poses) of a mixed round

    def reset(self) -> None:
        self.mixer.reset()
        self.key = None
        self.pending = None

    def rejects(self, cost: float, current: list[Matrix]) -> bool:
        """Whether the last mixed iterate fits worse than where it was mixed from; if so, ``current``
        goes back to that round's plain result."""
        pending, self.pending = self.pending, None
        if pending is None or cost <= pending[0]:
            return False
        for k, pose in pending[1].items():
            current[k] = pose
        self.mixer.reset()
        return True

    def mixed(self, current: Sequence[Matrix], last: _Round, key: tuple[int, float]) -> dict[int, Matrix]:
        """The free scans' next poses: ``last``'s plain result mixed with the rounds' before."""
        if key != self.key:
            self.mixer.reset()
            self.key = key
        iterate = self.chart.vectors(current)
        image = iterate.copy()
        movers = np.fromiter(last.moved, dtype=np.int64, count=len(last.moved))
        image[movers] = self.chart.vectors([last.moved[k] for k in movers.tolist()], movers)
        mixed = self.mixer.mix(iterate, image)
        if np.array_equal(mixed, image):
            return last.moved
        self.pending = (last.cost, last.moved)
        poses = self.chart.poses(mixed[movers], movers)
        return dict(zip(movers.tolist(), poses, strict=True))


def lum_relaxation(
    models: ScanModels,
    poses: Sequence[Matrix],
    fixed: Iterable[int] = (0,),
    config: RelaxationConfig = RelaxationConfig(),
    members: Iterable[int] | None = None,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    links: Iterable[tuple[int, int]] = (),
    scheduler: Scheduler | None = None,
    tilt: TiltPrior | None = None,
    observe: Callable[[int, Sequence[Matrix]], None] | None = None,
) -> RelaxationResult:
    """LUM: all scans solved at once from the closest-point pairs of all neighbour pairs (module docstring).

    With a ``scheduler`` (:mod:`slam6d.scheduler`) each round's per-scan blocks are computed by its
    workers: every scan's plane sample (all normals estimated first) and batch are sent once, each
    round only the relative poses; the blocks are those this process would compute.

    The residuals reported come from the rounds' own queries (RMS point-to-plane distance of the
    sampled data points paired within the ICP max distance): before is the first
    round's, at the starting poses; after is the last round's, at the poses it started from when
    that round ended the relaxation by settling (:func:`_settled`, by ``settle_on``), otherwise
    one more query at the final poses. ``links`` (scan pairs
    registered one onto the other) stay in the graph with any point pairs at all
    (:func:`slam6d.relax.neighbour_graph`). ``tilt`` (:class:`slam6d.attitude.TiltPrior`): the
    scans' measured up (an inclinometer), a prior on each free scan's roll and pitch. ``observe(round,
    poses)`` sees every scan's poses after each round (what ``benchmarks/scale.py --rounds`` prints
    the error of, round by round).
    """
    began = time.perf_counter()
    before, current, chosen, fixed_set, pairs = set_up(models, poses, fixed, members, config, links)
    graph_pairs = _strongest(pairs, len(models), config.max_neighbours)
    check_graph(models, graph_pairs, fixed_set, chosen)
    levels = [_Level(models, graph_pairs, config, scheduler)]
    if 0 < config.coarse_fraction < 1:  # the first rounds on a thinner sample (module docstring)
        coarse = replace(
            config,
            pair_points=max(1, round(config.pair_points * config.coarse_fraction)),
            min_round_points=round(config.min_round_points * config.coarse_fraction),
        )
        levels.insert(0, _Level(models, graph_pairs, coarse, scheduler))
    level = 0
    held = fixed_set | (set(range(len(models))) - set(chosen))
    patterns: dict[frozenset[int], BlockSystem] = {}
    first: _Round | None = None
    last: _Round | None = None
    rounds = 0
    settled = False
    previous: tuple[float, float] | None = None  # robust cost and movement of the last round at the final scale
    by_movement = config.settle_on == "movement"
    accelerator = _Accelerator(models, current, config.acceleration_depth) if config.acceleration_depth > 0 else None
    last_steps: FloatArray | None = None  # the last round's translation steps of the free scans (_steady_move)
    for rounds in range(1, config.max_rounds + 1):
        check_cancel(cancel)
        # graduated robustness, when first_scale x the max distance exceeds the final scale: the
        # scale halves from there (by default the rounds start at the final scale: a wider first
        # round barely went farther, and it broke the mixing's history, docs/scale.md)
        scale = config.robust_scale
        if scale > 0:
            scale = max(scale, config.first_scale * 0.5 ** (rounds - 1) * models.config.max_distance)
        batches, shared = levels[level].batches, levels[level].shared
        last = _joint_step(models, current, batches, held, config, scale, scheduler, shared, tilt, patterns)
        # the sums of a thin round, per point as many as the full sample's: chi2 before and after compare
        to_full = levels[-1].points / levels[level].points
        last = replace(last, chi2=last.chi2 * to_full, cost=last.cost * to_full)
        first = first or last
        if accelerator is not None and accelerator.rejects(last.cost, current):
            previous, last_steps = None, None  # the mixed poses fit worse: back to the plain round's, and on
            continue
        moved = []
        shifts = []
        for k, pose in last.moved.items():
            sample = models.thinned(k, 200)
            shift = float(
                np.linalg.norm(transform_points(pose, sample) - transform_points(current[k], sample), axis=1).max()
            )
            shifts.append(shift)
            if shift > config.tolerance:
                moved.append(k)
        thin = level < len(levels) - 1
        final_scale = scale <= config.robust_scale
        steps = np.array([last.moved[k][:3, 3] - current[k][:3, 3] for k in last.moved])
        steady = _steady_move(steps, last_steps, shifts)
        last_steps = steps
        settled = final_scale and _settled(config, thin, shifts, last.cost, previous, steady)
        previous = (last.cost, float(np.mean(shifts)) if shifts else 0.0) if final_scale else None
        # the thin sample settled (or only the full sample's share of the rounds is left): on to the full one
        switching = thin and (settled or rounds >= (config.max_rounds // 2 if by_movement else config.max_rounds - 2))
        taken: dict[int, Matrix] = last.moved
        # a mixed step is only taken where a round follows at the same sample to check it: the
        # rounds never end on poses no query has seen
        if accelerator is not None and not switching and not settled and rounds < config.max_rounds:
            taken = accelerator.mixed(current, last, (level, scale))
        for k, pose in taken.items():
            current[k] = pose
        if progress is not None:
            progress(rounds, last.residual, moved)
        if observe is not None:
            observe(rounds, current)
        if switching:
            last_steps = None
            level += 1
            if accelerator is not None:
                accelerator.reset()
            settled, previous = False, None  # its robust cost is summed over other points
            continue
        if settled:
            break
    assert first is not None and last is not None
    after = carry_forward(before, current, chosen)
    return RelaxationResult(
        poses=after,
        residual_before=first.residual,
        residual_after=last.residual if settled else _round_residual(models, current, levels[-1].batches),
        iterations=rounds,
        method="lum",
        neighbours=graph_pairs,
        chi2_before=first.chi2,
        chi2_after=last.chi2,
        seconds=time.perf_counter() - began,
    )
