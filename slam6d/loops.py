"""Loop closing: find scans that revisit a place, verify them, and spread the loop's error back.

After sequential matching the trajectory has drifted; when the robot comes back near an earlier
place, the scans there overlap although they are far apart along the path. Hypotheses come from
the estimated poses alone (two scans closer than a fraction of the laser's range, far apart along
the path), so no scan is ever matched against every earlier one. Each hypothesis is then checked
cheaply by the octree overlap (the fraction of the newer scan's cubes that land on occupied cubes
of the older scan) and then by ICP, whose result must pass every test below before it is accepted.

Fitness and RMS alone accept wrong loops: on a simulated 8-scan loop of 6,000 points per scan the
0-7 loop had fitness 0.33 and RMS 0.127 m at a transform 0.6-1.5 m off, because sparse scans of
a mostly flat scene have several local minima (ICP started at the true pose itself slid 0.2-0.6 m
away). So verification also asks that ICP converged at its final max distance; that the paired
points' normals pin down every direction of translation (the smallest eigenvalue of the sum of
n nᵀ over the pairs, i.e. the number of pairs on a plane facing the worst-constrained direction,
must reach ``min_constraint``: floor-dominated overlaps fail); and that ICP restarted from the
result shifted both ways along that weakest direction comes back within ``consistency``. Each test
names itself in the hypothesis' ``reason`` when it fails.

A verified loop (i, j) tells where scan j should sit relative to scan i. Error diffusion (as in
the seed) distributes that correction over the scans of the loop by path-length fraction:
translation linearly, rotation by quaternion slerp, both about the loop's first scan, so the
trajectory bends smoothly instead of jumping at scan j. Scans after j take the full correction,
which keeps the trajectory continuous.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from slam6d.errors import Cancelled, RegistrationError
from slam6d.geometry import (
    Matrix,
    invert,
    make_pose,
    quaternion_to_rotation,
    rotation_to_quaternion,
    slerp,
    transform_points,
)
from slam6d.icp import ICPConfig, icp
from slam6d.model import ModelIndex
from slam6d.octree import Occupancy, Octree
from slam6d.relax import ScanModels

FloatArray = NDArray[np.float64]


@dataclass
class LoopHypothesis:
    """A candidate loop between an older scan ``i`` and a newer scan ``j``.

    ``transform`` is scan j in scan i's frame: before verification the one implied by the current
    poses, after it the ICP result. ``distance`` and ``path_length`` are metres.
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
    correction: float = 0.0  # how far ICP moved scan j relative to scan i (metres)
    constraint: float = 0.0  # pairs' normals along the worst-constrained translation direction (see module doc)
    disagreement: float = float("nan")  # metres between the ICP result and the restarted ones


@dataclass(frozen=True)
class LoopConfig:
    """Defaults follow the seed's ELCH/LUM settings scaled to metres.

    ``radius_fraction`` x max range bounds how far apart two scans of a loop may be; ``min_path``
    (metres, and ``min_path_factor`` x their distance) keeps consecutive scans, which sequential
    matching already related, from being called a loop.
    """

    radius_fraction: float = 0.25
    min_path: float = 5.0
    min_path_factor: float = 3.0
    min_index_gap: int = 5
    overlap_cube: float = 0.5
    min_overlap: float = 0.2
    min_fitness: float = 0.3
    max_rms: float = 0.15
    min_constraint: float = 50.0
    consistency: float = 0.1  # metres; 0 skips the restarted ICPs
    candidates_per_scan: int = 1
    closing_gap: int = 5  # scans between two loop closings (a revisited stretch gives many loops at once)


def path_lengths(poses: Sequence[Matrix]) -> FloatArray:
    """Cumulative distance travelled along the trajectory, one value per scan (0 at scan 0)."""
    positions = np.array([p[:3, 3] for p in poses])
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def find_loop_hypotheses(
    poses: Sequence[Matrix],
    max_range: float,
    config: LoopConfig = LoopConfig(),
    occupancies: Sequence[Occupancy] | Callable[[int], Occupancy] | None = None,
    points: Sequence[FloatArray] | None = None,
    last_only: int | None = None,
) -> list[LoopHypothesis]:
    """Candidate loops from poses alone, best first per newer scan.

    With ``occupancies`` (each scan's cubes, own frame; a list or a function of the scan index,
    so they can be built on demand) and ``points`` (own frame) the overlap is
    computed and candidates below ``config.min_overlap`` are kept but marked rejected, so the trace
    shows why they were not tried. ``last_only`` restricts the newer scan to the last one (online use).
    """
    if max_range <= 0:
        raise ValueError(f"max_range must be positive, got {max_range}")
    positions = np.array([p[:3, 3] for p in poses])
    travelled = path_lengths(poses)
    radius = config.radius_fraction * max_range
    newest = range(len(poses) - 1, len(poses)) if last_only else range(len(poses))
    found: list[LoopHypothesis] = []
    for j in newest:
        older = np.arange(0, max(0, j - config.min_index_gap + 1))
        if len(older) == 0:
            continue
        dist = np.linalg.norm(positions[older] - positions[j], axis=1)
        path = travelled[j] - travelled[older]
        ok = (dist <= radius) & (path >= config.min_path) & (path >= config.min_path_factor * dist)
        candidates = []
        for i in older[ok]:
            rel = invert(poses[i]) @ poses[j]
            hyp = LoopHypothesis(int(i), j, float(dist[i]), float(path[i]), transform=rel)
            if occupancies is not None and points is not None:
                occupancy = occupancies(int(i)) if callable(occupancies) else occupancies[i]
                hyp.overlap = octree_overlap(occupancy, points[j], rel)
                if hyp.overlap < config.min_overlap:
                    hyp.reason = f"overlap {hyp.overlap:.2f} < {config.min_overlap}"
            candidates.append(hyp)
        # prefer high overlap, then the oldest scan (the longest loop carries the most drift)
        candidates.sort(key=lambda h: (bool(h.reason), -h.overlap, h.i))
        found.extend(candidates)
    return found


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
) -> LoopHypothesis:
    """Match scan j against scan i (own frames) from the pose-implied start; accept only when fitness,
    RMS, convergence, constraint and consistency all pass (see the module docstring).

    ICP runs coarse to fine from four times its max distance, because the drift a loop is meant to
    remove is usually larger than the tolerance used between consecutive scans. The cheap tests come
    first: the restarted ICPs only run for a loop that passed all others.
    """
    if hypothesis.reason:
        return hypothesis
    start = hypothesis.transform if hypothesis.transform is not None else np.eye(4)
    d = icp_config.max_distance
    schedule = tuple(s for s in (4 * d, 2 * d) if not icp_config.distance_schedule) or icp_config.distance_schedule
    cfg = replace(icp_config, distance_schedule=schedule)
    try:
        result = icp(model, data_points, start, cfg)
    except RegistrationError as exc:
        return replace(hypothesis, accepted=False, reason=f"ICP failed: {exc}")
    moved, _ = _pose_change(start, result.transform, data_points)
    verdict = replace(
        hypothesis,
        fitness=result.fitness,
        rms=result.rms,
        transform=result.transform,
        correction=moved,
    )
    verdict.constraint, weakest = translation_constraint(model, data_points, result.transform, d)
    if result.fitness < config.min_fitness:
        verdict.reason = f"ICP fitness {result.fitness:.2f} < {config.min_fitness}"
    elif result.rms > config.max_rms:
        verdict.reason = f"ICP rms {result.rms:.3f} m > {config.max_rms} m"
    elif not result.converged:
        verdict.reason = f"ICP did not converge at {d:g} m within {cfg.max_iterations} iterations"
    elif verdict.constraint < config.min_constraint:
        verdict.reason = (
            f"the overlap does not pin down the translation: {verdict.constraint:.0f} pairs along the weakest"
            f" direction < {config.min_constraint:g}"
        )
    elif config.consistency > 0:
        verdict.disagreement = _second_opinion(model, data_points, result.transform, weakest, cfg)
        if not verdict.disagreement <= config.consistency:
            verdict.reason = (
                f"ICP restarted {cfg.stages()[0]:g} m off along the weakest direction lands"
                f" {verdict.disagreement:.2f} m away (> {config.consistency:g} m): the match is ambiguous"
            )
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


def diffuse_loop_correction(
    poses: Sequence[Matrix],
    i: int,
    j: int,
    correction: Matrix,
    pivot: FloatArray | None = None,
) -> list[Matrix]:
    """Spread a world-frame ``correction`` of scan j over scans i+1..j by path-length fraction.

    The correction is split into a rotation about ``pivot`` (scan i's position by default) and a
    translation; scan k gets fraction f_k = path(i..k) / path(i..j) of both (slerp / linear). Scan i
    and earlier stay put; scans after j get the full correction so the trajectory stays continuous.
    """
    if not 0 <= i < j < len(poses):
        raise ValueError(f"loop ({i}, {j}) is not inside 0..{len(poses) - 1} with i < j")
    pivot = np.asarray(poses[i][:3, 3] if pivot is None else pivot, dtype=np.float64)
    rotation = correction[:3, :3]
    # correction(x) = R (x - pivot) + pivot + shift
    shift = correction[:3, 3] + rotation @ pivot - pivot
    q = rotation_to_quaternion(rotation)
    identity = np.array([1.0, 0.0, 0.0, 0.0])
    travelled = path_lengths(poses)
    span = travelled[j] - travelled[i]
    out = [np.array(p, dtype=np.float64) for p in poses]
    for k in range(i + 1, len(poses)):
        f = 1.0  # after the loop: the full correction
        if k <= j:
            f = (travelled[k] - travelled[i]) / span if span > 1e-12 else (k - i) / (j - i)
        r = quaternion_to_rotation(slerp(identity, q, f))
        partial = make_pose(r, pivot + f * shift - r @ pivot)
        out[k] = partial @ poses[k]
    return out


def detect_loops(
    models: ScanModels,
    poses: Sequence[Matrix],
    config: LoopConfig = LoopConfig(),
    max_range: float | None = None,
    progress: Callable[[int, int], None] | None = None,
    cancel: Callable[[], bool] | None = None,
) -> list[LoopHypothesis]:
    """Loop hypotheses over a whole trajectory at once, the best per newer scan verified by ICP.

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
    verified = []
    for n, hyp in enumerate(chosen):
        if cancel is not None and cancel():
            raise Cancelled("loop detection cancelled")
        verified.append(verify(hyp, models.index(hyp.i), models.points[hyp.j], models.config, config))
        if progress is not None:
            progress(n + 1, len(chosen))
    return verified
