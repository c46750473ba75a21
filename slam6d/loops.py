"""Loop closing: find scans that revisit a place, verify them, and spread the loop's error back.

After sequential matching the trajectory has drifted; when the robot comes back near an earlier
place, the scans there overlap although they are far apart along the path. Hypotheses come from
the estimated poses alone (two scans closer than a fraction of the laser's range, found through a
radius index over the scan positions, far apart along the path), so no scan is ever matched against
every earlier one.

Each hypothesis starts where the drifted poses put scan j relative to scan i, and that start is
refined by the octree search (:func:`slam6d.initial_guess.octree_guess`, as the seed verifies loops
"with the octree method") *before* anything is judged: after a metre and two degrees of drift a
car's VLP-16 revisit overlaps its earlier scan 0.05-0.15 at the pose-implied start and 0.15-0.48
once the search has put it back (simulated campus), so gating the drifted start refused every loop
that mattered. The gates are then judged against what consecutive scans of the same sequence
usually score (:class:`UsualFit`), not against fixed numbers: a VLP-16's correct consecutive fits
pair 25-45 % of the data where a dense scanner's pair 80 %.

Fitness and RMS alone accept wrong loops: on a simulated 8-scan loop of 6,000 points per scan the
0-7 loop had fitness 0.33 and RMS 0.127 m at a transform 0.6-1.5 m off, because sparse scans of
a mostly flat scene have several local minima (ICP started at the true pose itself slid 0.2-0.6 m
away). So verification also asks that ICP converged at its final max distance; that the paired
points' normals pin down every direction of translation (the smallest eigenvalue of the sum of
n nᵀ over the pairs, i.e. the number of pairs on a plane facing the worst-constrained direction,
must reach ``min_constraint``: floor-dominated overlaps fail); and that ICP restarted from the
result shifted both ways along that weakest direction comes back within ``consistency``.
Repetitive structure (a row of equal blocks, a parking deck's grid of columns) fits equally well
one period away, so two more guards refuse what a single match cannot tell apart: the search's
coarsest level must not score a second placement at least two cubes away nearly as high as its
winner (``ambiguity``), and the correction must stay within the drift the path between the two
scans can have accumulated (``drift_floor`` + ``drift_per_metre`` x path). Each test names itself in
the hypothesis' ``reason`` when it fails.

A verified loop (i, j) tells where scan j should sit relative to scan i. Error diffusion (as in
the seed) distributes that correction over the scans of the loop by path-length fraction: the
rotation by quaternion slerp, and the positions re-chained from each step turned by its scan's
share of it, what remains of the translation spread linearly; so the trajectory bends smoothly
instead of jumping at scan j, and a height error that a steady pitch drift built up along the
path is taken out where it arose (:func:`diffuse_loop_correction`). Scans after j take the full
correction, which keeps the trajectory continuous. Diffusion moves only the scans after i, so a
later loop that starts inside an earlier one pulls the earlier loop's ends apart again; the
pipeline therefore solves every loop closed so far and the registered steps as one pose graph
after each closing, from the diffused poses (:func:`hold_closed_loops`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from slam6d.attitude import TiltPrior
from slam6d.errors import Cancelled, RegistrationError
from slam6d.geometry import (
    Matrix,
    invert,
    make_pose,
    nearest_rotation,
    path_lengths,
    quaternion_to_rotation,
    rotation_to_quaternion,
    slerp,
    transform_points,
)
from slam6d.icp import ICPConfig, ICPResult, icp
from slam6d.initial_guess import GuessResult, OctreeSearchConfig, config_for, octree_guess
from slam6d.model import ModelIndex
from slam6d.nn import RadiusIndex
from slam6d.octree import Occupancy, Octree
from slam6d.pair import better_fit, coarse_to_fine
from slam6d.posegraph import PoseEdge, optimize_pose_graph
from slam6d.relax import ScanModels

FloatArray = NDArray[np.float64]


@dataclass
class LoopHypothesis:
    """A candidate loop between an older scan ``i`` and a newer scan ``j``.

    ``transform`` is scan j in scan i's frame: before verification the one implied by the current
    poses, after it the ICP result. ``distance`` and ``path_length`` are metres. ``start_overlap`` is
    the octree overlap at the pose-implied start (it only ranks the candidates), ``overlap`` the one
    verification judged (after the search); ``searched`` how far the octree search moved scan j
    (mean point displacement, metres; 0 when ICP from the start was kept) and ``ambiguity`` the best
    score of a placement at least two coarse cubes from the match over the match's own (see
    :func:`placement_ambiguity`; NaN when an earlier test refused the loop).
    """

    i: int
    j: int
    distance: float
    path_length: float
    overlap: float = 0.0
    fitness: float = 0.0
    rms: float = float("nan")
    transform: Matrix | None = None
    accepted: bool = False
    reason: str = ""
    correction: float = 0.0  # how far verification moved scan j relative to scan i (metres)
    constraint: float = 0.0  # pairs' normals along the worst-constrained translation direction (see module doc)
    disagreement: float = float("nan")  # metres between the ICP result and the restarted ones
    start_overlap: float = 0.0
    searched: float = 0.0
    ambiguity: float = float("nan")


@dataclass(frozen=True)
class UsualFit:
    """What consecutive scans of the sequence usually score (medians): the scale of the loop gates.

    How many of a scan's cubes or points find a partner depends on the sensor's sampling as much as
    on the fit: consecutive fits of a car's VLP-16 pair 25-45 % of the data, a dense terrestrial
    scanner's 80 % or more. A revisit seen from a few metres away and the other direction pairs
    less than its consecutive neighbours do, a wrong placement far less.
    """

    overlap: float
    fitness: float


@dataclass(frozen=True)
class LoopConfig:
    """Defaults follow the seed's ELCH/LUM settings scaled to metres.

    ``radius_fraction`` x max range bounds how far apart two scans of a loop may be; ``min_path``
    (metres, and ``min_path_factor`` x their distance) keeps consecutive scans, which sequential
    matching already related, from being called a loop. ``min_overlap`` and ``min_fitness`` are the
    bars when the sequence's usual scores are unknown; given a :class:`UsualFit` the bar is
    ``relative_overlap`` / ``relative_fitness`` x the usual score when that is lower. ``search``
    refines every start with the octree search (``guess`` its settings, None = the defaults scaled
    to the scan). ``ambiguity`` is the highest share of the winner's score a second placement may
    reach (1 turns the test off); ``drift_floor`` + ``drift_per_metre`` x path length bounds the
    correction a loop may bring (mean displacement of scan j's points, metres; ``drift_per_metre`` 0
    turns it off). A tenth of the path is loose on purpose: the wheel odometry of the tests' 8-scan
    loop moved scan 7's points 3 m (1.6 m and 19°) over 46 m, and the bound is only there to refuse
    what no drift could explain, not to judge ICP-registered sequences that drift far less.
    """

    radius_fraction: float = 0.25
    min_path: float = 5.0
    min_path_factor: float = 3.0
    min_index_gap: int = 5
    overlap_cube: float = 0.5
    min_overlap: float = 0.2
    min_fitness: float = 0.3
    relative_overlap: float = 0.4
    relative_fitness: float = 0.4
    max_rms: float = 0.15
    min_constraint: float = 50.0
    consistency: float = 0.1  # metres; 0 skips the restarted ICPs
    search: bool = True
    guess: OctreeSearchConfig | None = None
    ambiguity: float = 0.85
    drift_floor: float = 0.5
    drift_per_metre: float = 0.1
    candidates_per_scan: int = 1
    closing_gap: int = 5  # scans between two loop closings (a revisited stretch gives many loops at once)

    def __post_init__(self) -> None:
        if not (0 <= self.relative_overlap <= 1 and 0 <= self.relative_fitness <= 1):
            raise ValueError(
                f"loop.relative_overlap and loop.relative_fitness must be in [0, 1], got {self.relative_overlap},"
                f" {self.relative_fitness}"
            )
        if not 0 < self.ambiguity <= 1:
            raise ValueError(f"loop.ambiguity must be in (0, 1], got {self.ambiguity}")
        if self.drift_floor < 0 or self.drift_per_metre < 0:
            raise ValueError(
                f"loop.drift_floor and loop.drift_per_metre must be >= 0, got {self.drift_floor}, {self.drift_per_metre}"
            )

    def overlap_bar(self, usual: UsualFit | None) -> float:
        """The overlap a refined hypothesis needs (see the class docstring)."""
        return self.min_overlap if usual is None else min(self.min_overlap, self.relative_overlap * usual.overlap)

    def fitness_bar(self, usual: UsualFit | None) -> float:
        """The ICP fitness a loop needs (see the class docstring)."""
        return self.min_fitness if usual is None else min(self.min_fitness, self.relative_fitness * usual.fitness)


class LoopCandidates:
    """Which earlier scans may close a loop with a given scan, through a :class:`~slam6d.nn.RadiusIndex`
    over the positions.

    Built once per set of poses (the pipeline rebuilds it after each closing, which moves the
    poses): each query touches only the scans in the slab within reach instead of computing the
    distance to every earlier position.
    """

    def __init__(self, poses: Sequence[Matrix], max_range: float, config: LoopConfig = LoopConfig()) -> None:
        if max_range <= 0:
            raise ValueError(f"max_range must be positive, got {max_range}")
        self.poses = list(poses)
        self.config = config
        self.radius = config.radius_fraction * max_range
        self.positions = np.array([p[:3, 3] for p in self.poses]).reshape(-1, 3)
        self.travelled = path_lengths(self.poses) if self.poses else np.zeros(0)
        self._nearby = RadiusIndex(self.positions) if len(self.positions) else None

    def of(self, j: int) -> list[LoopHypothesis]:
        """Earlier scans near scan ``j`` in space and far from it along the path, nearest first."""
        if self._nearby is None:
            return []
        cfg = self.config
        near = self._nearby.within(self.positions[j], self.radius)
        older = near[near <= j - cfg.min_index_gap]
        dist = np.linalg.norm(self.positions[older] - self.positions[j], axis=1)
        path = self.travelled[j] - self.travelled[older]
        ok = (path >= cfg.min_path) & (path >= cfg.min_path_factor * dist)
        order = np.lexsort((older[ok], dist[ok]))
        return [
            LoopHypothesis(int(i), j, float(d), float(t), transform=invert(self.poses[i]) @ self.poses[j])
            for i, d, t in zip(older[ok][order], dist[ok][order], path[ok][order], strict=True)
        ]


def find_loop_hypotheses(
    poses: Sequence[Matrix],
    max_range: float,
    config: LoopConfig = LoopConfig(),
    occupancies: Sequence[Occupancy] | Callable[[int], Occupancy] | None = None,
    points: Sequence[FloatArray] | None = None,
    last_only: int | None = None,
    candidates: LoopCandidates | None = None,
) -> list[LoopHypothesis]:
    """Candidate loops from poses alone, best first per newer scan.

    With ``occupancies`` (each scan's cubes, own frame; a list or a function of the scan index,
    so they can be built on demand) and ``points`` (own frame) each candidate's ``start_overlap`` is
    computed and ranks them; nothing is refused for it, since the start has drifted (the search in
    :func:`verify` puts it back first). ``last_only`` restricts the newer scan to the last one
    (online use); ``candidates`` reuses a :class:`LoopCandidates` already built over ``poses``.
    """
    index = candidates if candidates is not None else LoopCandidates(poses, max_range, config)
    newest = range(len(poses) - 1, len(poses)) if last_only else range(len(poses))
    found: list[LoopHypothesis] = []
    for j in newest:
        near = index.of(j)
        if occupancies is not None and points is not None:
            for hyp in near:
                occupancy = occupancies(hyp.i) if callable(occupancies) else occupancies[hyp.i]
                assert hyp.transform is not None
                hyp.start_overlap = octree_overlap(occupancy, points[j], hyp.transform)
        # prefer high overlap at the start, then the nearest scan (nearest first already: a stable sort)
        near.sort(key=lambda h: -h.start_overlap)
        found.extend(near)
    return found


def usual_fit(
    poses: Sequence[Matrix],
    occupancies: Callable[[int], Occupancy],
    points: Sequence[FloatArray],
    fitness: Sequence[float] | Callable[[int], float],
    pairs: Sequence[tuple[int, int]] | None = None,
    samples: int = 25,
) -> UsualFit | None:
    """Median overlap and fitness of (at most ``samples``, spread evenly) consecutive pairs at their
    current poses; None when there are none. ``pairs`` are the (model scan, scan) pairs sequential
    registration related (default: every (k-1, k)); ``fitness`` their fitness, as registration found
    it (a list by scan) or measured here (a function of the scan)."""
    chosen = list(pairs) if pairs is not None else [(k - 1, k) for k in range(1, len(poses))]
    if not chosen:
        return None
    picked = [chosen[int(k)] for k in np.unique(np.linspace(0, len(chosen) - 1, min(samples, len(chosen))).round())]
    overlaps = [octree_overlap(occupancies(a), points[b], invert(poses[a]) @ poses[b]) for a, b in picked]
    scores = [fitness(b) if callable(fitness) else fitness[b] for _, b in picked]
    finite = [f for f in scores if np.isfinite(f)]
    if not finite:
        return None
    return UsualFit(float(np.median(overlaps)), float(np.median(finite)))


def pair_fitness(model: ModelIndex, data_points: FloatArray, transform: Matrix, max_distance: float) -> float:
    """Share of the data points with a model point within ``max_distance`` at ``transform``: ICP's
    fitness without running ICP (the pose is already the registered one)."""
    _, partner = model.nearest(transform_points(transform, np.asarray(data_points, dtype=np.float64)), max_distance)
    return float(np.count_nonzero(partner >= 0) / max(len(partner), 1))


def placement_ambiguity(model: Octree, data_points: FloatArray, transform: Matrix, search: OctreeSearchConfig) -> float:
    """:func:`search_ambiguity` of the coarsest level of the octree search about ``transform`` (the
    level alone: ~0.03 s for a VLP-16 scan), whatever found the placement."""
    coarsest = replace(search, cube_sizes=search.cube_sizes[:1])
    return search_ambiguity(octree_guess(model, data_points, transform, coarsest))


def search_ambiguity(guess: GuessResult) -> float:
    """Best score of the search's coarsest level at least two cubes (any axis) from its winner's
    translation, over the winner's score (0 when the level has no such placement).

    A place that only repetitive structure identifies - equal blocks along a street, a deck's grid
    of columns - scores as well one period away: the match cannot be told from its alias. On the
    simulated campus correct revisits score 0.55-0.65 there.
    """
    level = guess.levels[0].candidates
    scores = level.scores.reshape(*level.scores.shape[:3], -1).max(axis=3)  # best rotation per shift
    if scores.max() <= 0:
        return 1.0
    cells = np.indices(scores.shape).reshape(3, -1).T
    winner = np.array(np.unravel_index(np.argmax(scores), scores.shape))
    apart = np.abs(cells - winner).max(axis=1) >= 2
    return float(scores.ravel()[apart].max() / scores.max()) if apart.any() else 0.0


def octree_overlap(model: Occupancy, data_points: FloatArray, transform: Matrix) -> float:
    """Fraction of the data scan's occupied cubes that fall on occupied model cubes."""
    moved = transform_points(transform, data_points)
    keys = np.unique(model.keys_of(moved))
    keys = keys[keys >= 0]
    if len(keys) == 0:
        return 0.0
    return float(np.count_nonzero(model.key_set.contains(keys)) / len(keys))


def verify(
    hypothesis: LoopHypothesis,
    model: ModelIndex,
    data_points: FloatArray,
    icp_config: ICPConfig,
    config: LoopConfig = LoopConfig(),
    usual: UsualFit | None = None,
    model_octree: Octree | None = None,
    overlap_at: Callable[[Matrix], float] | None = None,
) -> LoopHypothesis:
    """Match scan j against scan i (own frames) from the pose-implied start, refined by the octree
    search when ICP from there fits poorly; accept only when overlap, ambiguity, fitness, RMS,
    convergence, constraint, drift and consistency all pass (see the module docstring). ``usual``
    scales the overlap and fitness bars; ``model_octree`` is scan i's octree when the caller keeps
    one (built here otherwise, only when the search or the overlap needs it). ``overlap_at`` measures
    the overlap at a placement the way ``usual`` was measured (the same occupancy and points), so the
    refined overlap and its bar compare like with like; without it, scan i's octree and the data points.

    Every gate judges the refined placement, never the drifted start. ICP runs first from the start
    and the search only when that fit is poor (as in sequential registration): a close start is
    worth more than a search, and on the sparse 6,000-point loop of the tests the search's winner
    was a well-constrained wrong minimum 0.6 m off that ICP from the start did not reach (it stopped
    where the constraint test refuses it). ICP runs coarse to fine from four times its max distance,
    because the drift a loop is meant to remove is usually larger than the tolerance used between
    consecutive scans; the restarted ICPs only run for a loop that passed all other tests.
    """
    if hypothesis.reason:
        return hypothesis
    start = hypothesis.transform if hypothesis.transform is not None else np.eye(4)
    data_points = np.asarray(data_points, dtype=np.float64)
    d = icp_config.max_distance
    cfg = coarse_to_fine(icp_config)
    fitness_bar = config.fitness_bar(usual)
    verdict = replace(hypothesis, transform=start)
    result: ICPResult | RegistrationError
    try:
        result = icp(model, data_points, start, cfg)
    except RegistrationError as exc:
        result = exc
    search = config.guess or config_for(model.points)  # the default search scaled to a small scan
    tree = model_octree
    if config.search and (isinstance(result, RegistrationError) or result.fitness < fitness_bar):
        tree = tree if tree is not None else Octree(model.points, search.cube_sizes[-1])
        guess = octree_guess(tree, data_points, start, search)
        try:
            searched = icp(model, data_points, guess.transform, cfg)
        except RegistrationError as exc:
            searched_result: ICPResult | RegistrationError = exc
        else:
            searched_result = searched
        if (
            not isinstance(searched_result, RegistrationError)
            and better_fit(result, searched_result) is searched_result
        ):
            result = searched_result
            verdict.searched = _pose_change(start, guess.transform, data_points)[0]
    if isinstance(result, RegistrationError):
        return replace(verdict, accepted=False, reason=f"ICP failed: {result}")
    moved, _ = _pose_change(start, result.transform, data_points)
    verdict = replace(verdict, fitness=result.fitness, rms=result.rms, transform=result.transform, correction=moved)
    tree = tree if tree is not None else Octree(model.points, search.cube_sizes[-1])
    if overlap_at is not None:
        verdict.overlap = overlap_at(result.transform)
    else:
        verdict.overlap = octree_overlap(tree.occupancy(config.overlap_cube), data_points, result.transform)
    verdict.constraint, weakest = translation_constraint(model, data_points, result.transform, d)
    allowed = config.drift_floor + config.drift_per_metre * hypothesis.path_length

    def refusal() -> str:
        """The first test the loop fails ("" when it passes them all), cheapest first; the ambiguity
        and the restarts fill in their fields of ``verdict`` only when they run."""
        if verdict.overlap < config.overlap_bar(usual):
            return f"overlap {verdict.overlap:.2f} < {config.overlap_bar(usual):.2f}"
        if result.fitness < fitness_bar:
            return f"ICP fitness {result.fitness:.2f} < {fitness_bar:.2f}"
        if result.rms > config.max_rms:
            return f"ICP rms {result.rms:.3f} m > {config.max_rms} m"
        if not result.converged:
            return f"ICP did not converge at {d:g} m within {cfg.max_iterations} iterations"
        if verdict.constraint < config.min_constraint:
            return (
                f"the overlap does not pin down the translation: {verdict.constraint:.0f} pairs along the weakest"
                f" direction < {config.min_constraint:g}"
            )
        # a hand-drawn edge has no path between its scans, hence no prior on how far they drifted
        if config.drift_per_metre > 0 and hypothesis.path_length > 0 and moved > allowed:
            return (
                f"the correction ({moved:.2f} m) is more than {hypothesis.path_length:.0f} m of path can have"
                f" drifted ({allowed:.2f} m)"
            )
        if config.ambiguity < 1:
            verdict.ambiguity = placement_ambiguity(tree, data_points, result.transform, search)
            if verdict.ambiguity > config.ambiguity:
                return (
                    f"ambiguous: a placement two cubes from the match scores {verdict.ambiguity:.0%} of it"
                    f" (> {config.ambiguity:.0%}; repetitive structure)"
                )
        if config.consistency > 0:
            verdict.disagreement = _second_opinion(model, data_points, result.transform, weakest, cfg)
            if not verdict.disagreement <= config.consistency:
                return (
                    f"ICP restarted {cfg.stages()[0]:g} m off along the weakest direction lands"
                    f" {verdict.disagreement:.2f} m away (> {config.consistency:g} m): the match is ambiguous"
                )
        return ""

    verdict.reason = refusal()
    verdict.accepted = not verdict.reason
    return verdict


def translation_constraint(
    model: ModelIndex, data_points: FloatArray, transform: Matrix, max_distance: float
) -> tuple[float, FloatArray]:
    """Smallest eigenvalue of the sum of n nᵀ over the point-to-plane pairs at ``transform``, and its
    direction (model frame).

    It counts how many pairs (weighted by how squarely their planes face it) resist a shift in the
    worst direction: a floor plus a little wall gives thousands of pairs but a handful against
    sliding along the wall, and ICP's answer along that direction is then noise or a local minimum.
    """
    moved = transform_points(transform, np.asarray(data_points, dtype=np.float64))
    _, _, _, normals = model.plane_pairs(moved, max_distance)
    if len(normals) == 0:
        return 0.0, np.array([1.0, 0.0, 0.0])
    values, vectors = np.linalg.eigh(normals.T @ normals)
    return float(values[0]), vectors[:, 0]


def _second_opinion(
    model: ModelIndex, data_points: FloatArray, first: Matrix, weakest: FloatArray, cfg: ICPConfig
) -> float:
    """Largest mean point distance between ``first`` and ICP restarted from ``first`` shifted by the
    coarsest max distance both ways along the weakest-constrained direction.

    A well-defined minimum pulls both restarts back; on a plateau or between two minima at least one
    ends elsewhere. Cheaper than an octree search (a second full search cost seconds per loop on
    90k-point scans) and aimed at exactly the direction the pairs constrain least.
    """
    reach = cfg.stages()[0]
    worst = 0.0
    for sign in (1.0, -1.0):
        shifted = make_pose(np.eye(3), sign * reach * weakest) @ first
        try:
            again = icp(model, data_points, shifted, cfg)
        except RegistrationError:
            return float("inf")
        worst = max(worst, _pose_change(first, again.transform, data_points)[0])
    return worst


def _pose_change(before: Matrix, after: Matrix, points: FloatArray) -> tuple[float, float]:
    """Mean and max displacement of a scan's points between two placements (metres)."""
    sample = points[:: max(1, len(points) // 500)]
    shift = np.linalg.norm(transform_points(after, sample) - transform_points(before, sample), axis=1)
    return float(shift.mean()), float(shift.max())


def loop_correction(poses: Sequence[Matrix], loop: LoopHypothesis) -> Matrix:
    """World-frame correction that moves scan j to where the verified loop says it belongs."""
    if loop.transform is None:
        raise ValueError("the loop has no transform")
    return poses[loop.i] @ loop.transform @ invert(poses[loop.j])


def diffuse_loop_correction(poses: Sequence[Matrix], i: int, j: int, correction: Matrix) -> list[Matrix]:
    """Spread a world-frame ``correction`` of scan j over scans i+1..j by path-length fraction.

    Scan k gets fraction f_k = path(i..k) / path(i..j) of the correction's rotation (slerp), and
    its position follows from the corrected rotations: each step's translation keeps its direction
    in the frame of the scan it starts from (turned by that scan's share of the rotation), and
    what the re-chained path still misses of the corrected scan j's position is added linearly by
    f_k. Scan i and earlier stay put; scans after j get the full correction, so the trajectory
    stays continuous.

    Why the path is re-chained rather than every scan turned rigidly about scan i by its share
    (the simpler diffusion): a registration that tilts every step by the same small pitch climbs a
    height that grows with the square of the distance, and interpolating the end's correction
    linearly over the path - what the rigid turn amounts to for the positions - left a bulge of
    about a quarter of scan j's vertical error in the middle of the loop (1.1 m of 3.9 m over
    130 m with 0.1° per step, ``tests/test_loops.py``); turning each step where its tilt arose
    leaves 8 cm. The same holds for a heading drift.
    """
    if not 0 <= i < j < len(poses):
        raise ValueError(f"loop ({i}, {j}) is not inside 0..{len(poses) - 1} with i < j")
    rotation = correction[:3, :3]
    q = rotation_to_quaternion(rotation)
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    travelled = path_lengths(poses)
    span = travelled[j] - travelled[i]
    out = [np.array(p, dtype=np.float64) for p in poses]
    turns = [np.eye(3)]  # the rotation share of scans i..j
    chained = [np.asarray(poses[i][:3, 3], dtype=np.float64)]
    fractions = [0.0]
    for k in range(i + 1, j + 1):
        f = (travelled[k] - travelled[i]) / span if span > 1e-12 else (k - i) / (j - i)
        fractions.append(f)
        # the step from scan k-1 keeps its direction in scan k-1's frame, turned by that scan's share
        chained.append(chained[-1] + turns[-1] @ (poses[k][:3, 3] - poses[k - 1][:3, 3]))
        turns.append(quaternion_to_rotation(slerp(identity, q, f)))
    target = rotation @ poses[j][:3, 3] + correction[:3, 3]
    missing = target - chained[-1]
    for n, k in enumerate(range(i + 1, j + 1), start=1):
        out[k] = make_pose(turns[n] @ poses[k][:3, :3], chained[n] + fractions[n] * missing)
    for k in range(j + 1, len(poses)):  # after the loop: the full correction
        out[k] = correction @ poses[k]
    if i + 1 < len(out):  # back on SO(3): later loops compose with these (see nearest_rotation)
        moved = np.stack(out[i + 1 :])
        moved[:, :3, :3] = nearest_rotation(moved[:, :3, :3])
        out[i + 1 :] = list(moved)
    return out


def lever_arm(points: Sequence[FloatArray], samples: int = 25) -> float:
    """How far a scan's points lie from its origin (metres): the median over (at most ``samples``,
    spread evenly) scans of their RMS distance, the arm by which a turn moves them; it weighs the
    rotations in :func:`hold_closed_loops`."""
    if not len(points):
        raise ValueError("no scans to measure a lever arm on")
    picked = np.unique(np.linspace(0, len(points) - 1, min(samples, len(points))).round().astype(int))
    arms = [float(np.sqrt(np.mean(np.einsum("ij,ij->i", points[k], points[k])))) for k in picked]
    return max(float(np.median(arms)), 1e-3)


def hold_closed_loops(
    registered: Sequence[Matrix],
    loops: Sequence[LoopHypothesis],
    poses: Sequence[Matrix],
    lever: float,
    tilt: TiltPrior | None = None,
) -> list[Matrix]:
    """Poses that keep every closed loop and the registered steps between them at once.

    Error diffusion closes one loop by moving only the scans after its first scan i, so a later
    loop whose scan i lies inside an earlier loop pulls that earlier loop's ends apart again. On the
    1,000-scan simulated campus, after 51 closings the loops' ends were up to 2 m (height) and 30 cm
    (across) from where their verified transforms put them; the relaxation, which finds its pairs
    from overlap at the poses it starts from, no longer saw those revisits at all and left them
    1.8 m apart (docs/scale.md, "Which revisits close, and what keeps them closed"). Here the
    registered steps (scan k in scan k-1's frame, as sequential registration left them) and every
    verified loop (scan j in scan i's frame) are one pose graph
    (:func:`slam6d.posegraph.optimize_pose_graph`), solved from ``poses`` (the diffused ones:
    close to the optimum) with scan 0 held. Each edge weighs the same, its rotation by ``lever``
    squared (metres: the RMS distance of a scan's points from its origin, so a turn counts by how
    far it moves the scan's points, as a loop's correction is measured; :func:`lever_arm`): loops are verified by
    the same ICP as the steps and are no better known, and the solve spreads each loop's mismatch
    over the steps between its ends as far as the other loops allow. A loop over n steps so keeps
    about 1/(n+1) of its own mismatch (the campus's loops span 50-700 steps: they are kept to 0.4 cm
    at the median). Hence only for registered steps: the workbench's *Close loops* diffuses alone,
    since a session's poses there may be odometry or hand moves, which a verified loop outweighs.

    ``tilt``: the inclinometer's readings (:class:`slam6d.attitude.TiltPrior`), held in this solve as
    in registration and relaxation; without them the loops' own relative tilts (0.1-0.2° off on the
    campus's ring scans) would tilt the stretches between them again.
    """
    if lever <= 0:
        raise ValueError(f"lever must be positive, got {lever}")
    if len(registered) != len(poses):
        raise ValueError(f"{len(registered)} registered poses for {len(poses)} poses")
    information = np.diag([1.0, 1.0, 1.0, lever**2, lever**2, lever**2])
    edges = [
        PoseEdge(k - 1, k, invert(registered[k - 1]) @ registered[k], information) for k in range(1, len(registered))
    ]
    for loop in loops:
        if loop.transform is None:
            raise ValueError(f"loop ({loop.i}, {loop.j}) has no transform")
        edges.append(PoseEdge(loop.i, loop.j, np.asarray(loop.transform, dtype=np.float64), information))
    return [np.asarray(p) for p in optimize_pose_graph(poses, edges, fixed=(0,), tilt=tilt).poses]


def detect_loops(
    models: ScanModels,
    poses: Sequence[Matrix],
    config: LoopConfig = LoopConfig(),
    max_range: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> list[LoopHypothesis]:
    """Loop hypotheses over a whole trajectory at once, the best per newer scan verified (searched,
    then ICP), judged against the consecutive pairs' usual overlap and fitness at the current poses.

    What a person asks for after a run ("find the loops from these poses"), unlike the pipeline's
    online loop stage, which looks back from each new scan as it arrives. ``max_range`` None
    estimates the laser's reach as the pipeline does: a typical scan's extent.
    ``progress(done, total)`` counts verified hypotheses; :class:`~slam6d.errors.Cancelled` when
    ``cancel()`` turns true.
    """
    cube = config.overlap_cube
    occupancies: dict[int, Occupancy] = {}

    def occupancy(k: int) -> Occupancy:
        if k not in occupancies:
            occupancies[k] = Octree(models.points[k], cube).occupancy(cube)
        return occupancies[k]

    reach = max_range or float(np.median([models.extent(k) for k in range(len(models))]))
    best: dict[int, LoopHypothesis] = {}
    for hyp in find_loop_hypotheses(poses, reach, config, occupancy, models.points):  # best first per newer scan
        best.setdefault(hyp.j, hyp)
    chosen = [best[j] for j in sorted(best)]
    usual = None
    if chosen:  # consecutive scans as they sit now: registered, so at ICP's own fitness

        def fitness(k: int) -> float:
            return pair_fitness(
                models.index(k - 1), models.points[k], invert(poses[k - 1]) @ poses[k], models.config.max_distance
            )

        usual = usual_fit(poses, occupancy, models.points, fitness)
    verified = []
    for n, hyp in enumerate(chosen):
        if cancel is not None and cancel():
            raise Cancelled("loop detection cancelled")
        verified.append(verify(hyp, models.index(hyp.i), models.points[hyp.j], models.config, config, usual))
        if progress is not None:
            progress(n + 1, len(chosen))
    return verified
