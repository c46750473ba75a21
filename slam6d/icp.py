"""Pairwise registration by ICP: closest points within a max distance, then the rigid motion that fits them.

Two error metrics are offered. ``point_to_point`` is the paper's: the closed-form least-squares
rotation from the SVD of the cross-covariance of the paired points (Arun, Huang and Blostein 1987).
It is robust but converges linearly, so near the optimum it needs many iterations. ``point_to_plane``
minimises the distance of each data point to the tangent plane of its model partner (normals from
the model's k nearest neighbours, estimated on demand and cached in the :class:`slam6d.model.ModelIndex`),
linearised for small rotations; it slides along walls and floors instead of being held back by the sampling of the model,
and converges in a few iterations. It is the default because it is 3-6x faster in
``benchmarks/pair.py`` at the same useful accuracy (about 0.1 mm on an exact 100k-point copy, and
within the reference's own uncertainty on a real pair).

:func:`translation_constraint` says how strongly a set of point-to-plane pairs fixes the translation
in each direction, for telling a good fit from one whose many pairs leave a direction to a handful.
Along such a direction ICP's minimum is set by the normals' noise, not by the scene, and ICP drifts
there (a corridor seen by a 16-beam lidar: 5-19 cm in height from the truth itself). With
``ICPConfig.hold_below`` the converged run checks its pairs; translations fixed less than that are
put back where the caller's :class:`MotionPrior` has them (the start's position without one: the
odometry's prediction) and held there while ICP settles the rotation and the other translations
again, with a fresh iteration budget. A prior knows where the scan was and where its motion model
puts it; the motion the model puts into the held translations is kept when it stands out of the
model's recent error (a car along a street its pairs barely fix goes on), else taken as that error
and left out (the height of a hand-held scanner in a corridor stays), see :func:`_held_at`.

Everything here works with ``transform`` = ``model_from_data``: ``model ≈ transform_points(T, data)``.
:func:`icp_iterations` yields one :class:`ICPIteration` per step so the workbench can show each
correspondence set; :func:`icp` runs it to the end.

Convergence rule: an iteration's update is ``Δ = T_k · T_{k-1}⁻¹``; a distance stage has converged
when ``|t(Δ)| <= epsilon`` (metres) and ``angle(R(Δ)) <= epsilon`` (radians), or when ``T_k`` is that
close to one of the stage's previous three poses: with a hard max distance the pair set can flip
between two or three states forever (one point entering and leaving), and such a cycle cannot
improve any further. The stages of a coarse-to-fine ``distance_schedule`` before the last use
``max(epsilon, stage_epsilon)`` instead, because they only need to bring the scans within reach of
the next, tighter distance. After the last stage (``max_distance``) the run is converged.
``max_iterations`` caps the iterations of all stages together.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from slam6d import nn
from slam6d.attitude import ScanTilt, tilt_information, tilt_normal_equations
from slam6d.errors import RegistrationError
from slam6d.geometry import cross_rows, make_pose, rotation_angle, so3_exp, transform_points
from slam6d.model import NORMAL_NEIGHBOURS, NORMAL_VOXEL_SIZE, ModelIndex
from slam6d.octree import reduce_points

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

METHODS = ("point_to_plane", "point_to_point")
# metres: the narrowest residual gate (ICPConfig.residual_gate), so that exact synthetic data, whose
# residuals near the optimum are all but zero, keep their pairs
RESIDUAL_GATE_FLOOR = 1e-3
_CYCLE = 4  # the convergence test compares with the previous pose and the three before it (cycles)
# A pair counts as close (ICPIteration.close) within this share of the stage's max distance: 5 cm of
# the default 25 cm, a few times a lidar's range noise (see ICPResult.close_fitness for why)
CLOSE_SHARE = 0.2


@dataclass(frozen=True)
class ICPConfig:
    """How a pair is registered. Distances in metres; the defaults suit robot scans of rooms,
    buildings and streets (scale them down for small objects such as the Stanford bunny).

    ``data_voxel_size`` > 0 reduces the data scan to one real point per voxel before matching (the
    model keeps full resolution, so accuracy is kept while the per-iteration search shrinks; 10 cm is
    3DTK's usual ``-r 10``); 0 matches every data point. Point-to-plane matches against the model
    reduced to ``normal_voxel_size`` voxels and estimates normals there from ``normal_neighbours``
    neighbours (see :class:`slam6d.model.ModelIndex` for why).
    ``threads`` bounds the worker threads of the search and the numba kernels.

    ``epsilon`` (see the module docstring for the exact rule) defaults to 0.1 mm / 0.006°: on real
    scans the update does not shrink below that, because single pairs keep entering and leaving the
    max distance, and iterating on changes nothing measurable. Point-to-point converges linearly: its
    updates shrink slowly while it still creeps towards the optimum, so give it 1e-5 or less (on the
    BALM pair 1e-4 stops it 0.1° short, 1e-5 within 0.07° of the reference).

    ``hold_below`` > 0 (point-to-plane only): once converged, the translations the pairs fix less
    than this (:func:`translation_constraint`) are held where the caller's :class:`MotionPrior` says
    and ICP settles the rest again (see the module docstring); 0 lets ICP end wherever it drifted
    along them.

    ``residual_gate`` > 0 (point-to-plane only): each step leaves out the pairs whose signed
    point-to-plane residual lies more than this many robust standard deviations (1.4826 x the
    median absolute deviation) from the median residual (never closer than ``RESIDUAL_GATE_FLOOR``);
    0 keeps every pair within ``max_distance``. The gate only applies once the run has converged
    with every pair, and the run then settles again: from a start still off, the residuals of the
    pairs that fix the offset are what is off, and a car's start 10-50 cm off on open ground, whose
    horizontal position rests on the few pairs with walls and poles among thousands on the road,
    lost exactly those (the robustness matrix's outdoor HDL-32E without odometry, seed 2: 3.8 m
    instead of 0.5 cm). Why the gate: a pair whose model plane is wrong (a cube normal
    fitted over a distant surface's sparse scan lines, an edge, a crown) sits centimetres off its
    plane at the true pose, and with the same scanner's sampling pattern on both sides those
    residuals shrink where the patterns line up - at zero motion. Kept, they pulled the 24 cm steps of
    the dense simulated loop (400 scans) 0.44 cm short on average even from the true pose; gated at
    4, 0.005 cm (docs/scale.md, "Short steps: pairs off their planes"). ``pairs`` (and so the fitness) still
    counts every pair found within ``max_distance``: how much of the scan overlaps the model.

    ``robust_scale`` c > 0 (point-to-plane only): once the run has converged with every pair equally
    weighted, it settles again with each pair weighted by Geman-McClure's 1 / (1 + (r / c)²)² of its
    residual r (iteratively reweighted: the weights are taken afresh each step); 0 keeps least
    squares. It waits for convergence as the gate does, for the same reason. The soft counterpart of
    the gate, at a fixed scale instead of the pairs' own spread: a pair 2c off its plane weighs 1/25,
    3c 1/100. Why another rule: the pairs off their planes are not only wrong cube normals. On the
    first 80 scans of the dense 400-scan loop, each matched from the truth, the 24 cm steps came out
    0.35 cm short with the cube normals and still 0.25 cm short with the simulator's exact surface
    normals at the model points: far from the scanner its lines lie 0.4-0.8 m apart, and a data
    point between two of the model's lines finds its closest model point on another surface (the
    face of a pilaster 12 cm in front of its wall, a wall beside the ground), centimetres off along
    the normal, by an amount that shrinks where the two scans' patterns line up. No test on the
    normals removes that; a weight on the residual does: from the truth -0.004 cm at c = 5 cm,
    -0.056 cm with Cauchy's weight at 5 cm (LUM's kernel, whose influence falls off only as c²/r).
    Off by default: BALM's RPE rose 0.547 -> 0.562 cm with it (docs/scale.md, "Short steps: pairs off
    their planes").

    ``facing_pairs`` (point-to-plane only): the data are a scan in its scanner's own frame (the
    scanner at the origin), so each step tells the model where the data scanner stands and the model
    leaves out pairs with planes its scanners saw from the other side (a thin wall's far face;
    :meth:`slam6d.model.ModelIndex.plane_pairs`). Off for data in any other frame (a metascan in
    world coordinates), where the origin is no scanner.
    """

    max_distance: float = 0.25
    max_iterations: int = 50
    epsilon: float = 1e-4
    method: str = "point_to_plane"
    distance_schedule: tuple[float, ...] = ()
    stage_epsilon: float = 1e-4
    min_pairs: int = 20
    normal_neighbours: int = NORMAL_NEIGHBOURS
    normal_voxel_size: float = NORMAL_VOXEL_SIZE
    data_voxel_size: float = 0.1
    threads: int = 2
    nn_backend: str = nn.DEFAULT_BACKEND
    hold_below: float = 0.0
    facing_pairs: bool = False
    residual_gate: float = 0.0
    robust_scale: float = 0.0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown ICP method {self.method!r}; choose from {METHODS}")
        if not (self.max_distance > 0 and math.isfinite(self.max_distance)):
            raise ValueError(f"max_distance must be a positive number of metres, got {self.max_distance}")
        if self.max_iterations < 1:
            raise ValueError(f"max_iterations must be at least 1, got {self.max_iterations}")
        if self.epsilon < 0:
            raise ValueError(f"epsilon must not be negative, got {self.epsilon}")
        if self.min_pairs < 6:
            raise ValueError(f"min_pairs must be at least 6 (a rigid motion has 6 unknowns), got {self.min_pairs}")
        if self.normal_neighbours < 3:
            raise ValueError(f"normal_neighbours must be at least 3, got {self.normal_neighbours}")
        if self.normal_voxel_size < 0:
            raise ValueError(f"normal_voxel_size must be >= 0 (0 = raw points), got {self.normal_voxel_size}")
        if self.data_voxel_size < 0:
            raise ValueError(f"data_voxel_size must be >= 0 (0 = full resolution), got {self.data_voxel_size}")
        schedule = self.distance_schedule
        if any(not (d > 0 and math.isfinite(d)) for d in schedule):
            raise ValueError(f"distance_schedule entries must be positive, got {schedule}")
        if any(b > a for a, b in itertools.pairwise(schedule)):
            raise ValueError(f"distance_schedule must go from coarse to fine (non-increasing), got {schedule}")
        if schedule and schedule[-1] < self.max_distance:
            raise ValueError(f"distance_schedule {schedule} goes below max_distance {self.max_distance}")
        if not 0 <= self.hold_below < 1:
            raise ValueError(f"hold_below must be in [0, 1), got {self.hold_below}")
        if not (self.residual_gate >= 0 and math.isfinite(self.residual_gate)):
            raise ValueError(f"residual_gate must be >= 0 (0 = keep every pair), got {self.residual_gate}")
        if not (self.robust_scale >= 0 and math.isfinite(self.robust_scale)):
            raise ValueError(f"robust_scale must be >= 0 metres (0 = least squares), got {self.robust_scale}")

    def stages(self) -> tuple[float, ...]:
        """The max distances used in order: the schedule, always ending at ``max_distance``."""
        schedule = tuple(float(d) for d in self.distance_schedule)
        if not schedule or schedule[-1] != self.max_distance:
            schedule = (*schedule, float(self.max_distance))
        return schedule


@dataclass
class ICPIteration:
    """One ICP step. ``pairs``/``rms`` describe the correspondences found at the start of the step
    (Euclidean pair distances, for either method); ``transform`` is model_from_data after the step."""

    index: int
    transform: FloatArray
    pairs: int
    rms: float
    max_distance: float
    step_translation: float = 0.0  # |t(Δ)| of this step's update, metres
    step_rotation: float = 0.0  # angle(R(Δ)) of this step's update, radians
    converged: bool = False  # True on the step that met the convergence rule of the last stage
    held: int = 0  # translations held (ICPConfig.hold_below), 0 = none
    # the converged fit's barely fixed translations carry motion the prior predicts beyond its misses
    # (MotionPrior.moves_along): its position along the way rests on a few pairs
    weak_along_motion: bool = False
    # of the pairs, those within CLOSE_SHARE x max_distance of their partner's plane (point-to-plane)
    # or of their partner (point-to-point)
    close: int = 0


@dataclass
class ICPResult:
    """Outcome of :func:`icp`. ``pairs``/``rms`` are those of the last iteration (measured at its start,
    so within one update of ``transform``; within ``epsilon`` when converged). ``fitness`` is the
    fraction of the (reduced) data points that found a partner.

    ``close_fitness`` is the fraction that lie close to the model (``ICPIteration.close``: within
    ``CLOSE_SHARE`` of the max distance of their partner's plane). Why a second measure: the
    fitness counts a pair 20 cm off as one 1 cm off, and a wrong basin can pair as many points as the
    right one. The case measured: a hand-held VLP-16 walk indoors (30 scans, seed 1, its files
    re-rounded by 0.1 mm), scan 6 from a prediction 37° off converged 40 cm / 20° off pairing 0.71
    of its points, the true fit 0.69; within 5 cm of their planes 0.37 against 0.49
    (docs/robustness.md, "Fits that pair as much in the wrong place"). What sits off its plane by
    a few centimetres at the right pose is noise and sampling, by tens of centimetres a wrong one.
    """

    transform: FloatArray
    iterations: list[ICPIteration]
    converged: bool
    pairs: int
    rms: float
    fitness: float
    data_points: int
    method: str
    max_distance: float = field(default=0.0)
    close_fitness: float = field(default=0.0)

    @classmethod
    def from_iterations(
        cls, iterations: list[ICPIteration], data_points: int, method: str, frame: FloatArray | None = None
    ) -> ICPResult:
        """The result a finished iteration trace amounts to; ``frame`` (e.g. world_from_model) is
        applied to the last transform when the model was matched in a frame of its own."""
        last = iterations[-1]
        return cls(
            transform=last.transform if frame is None else frame @ last.transform,
            iterations=iterations,
            converged=last.converged,
            pairs=last.pairs,
            rms=last.rms,
            fitness=last.pairs / max(data_points, 1),
            data_points=data_points,
            method=method,
            max_distance=last.max_distance,
            close_fitness=last.close / max(data_points, 1),
        )


def _as_model(model: ModelIndex | FloatArray, config: ICPConfig) -> ModelIndex:
    if isinstance(model, ModelIndex):
        return model
    return ModelIndex(
        model,
        normal_neighbours=config.normal_neighbours,
        normal_voxel_size=config.normal_voxel_size,
        backend=config.nn_backend,
        threads=config.threads,
    )


def _as_data(data: FloatArray) -> FloatArray:
    data = np.ascontiguousarray(data, dtype=np.float64)
    if data.ndim != 2 or data.shape[1] != 3:
        raise ValueError(f"data points must be an (N, 3) array, got shape {data.shape}")
    return data


def _as_transform(transform: FloatArray) -> FloatArray:
    """A float64 copy; a rotation that is not quite orthonormal (poses stored with few digits) is
    replaced by the nearest rotation, so that the result stays a rigid motion."""
    t = np.array(transform, dtype=np.float64)
    if t.shape != (4, 4):
        raise ValueError(f"transform must be 4x4, got shape {t.shape}")
    r = t[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-12:
        u, _, vt = np.linalg.svd(r)
        if np.linalg.det(u @ vt) < 0:
            raise ValueError("transform's 3x3 part is a reflection, not a rotation")
        t[:3, :3] = u @ vt
    return t


# ---------------------------------------------------------------- the two error metrics


def point_to_point_step(data: FloatArray, model: FloatArray) -> FloatArray:
    """Rigid motion minimising sum |R d + t - m|² over paired points (Arun et al.: SVD of the cross-covariance)."""
    dc = data.mean(axis=0)
    mc = model.mean(axis=0)
    h = (data - dc).T @ (model - mc)
    u, _, vt = np.linalg.svd(h)
    d = np.eye(3)
    d[2, 2] = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0  # guard against a reflection on degenerate sets
    rotation = vt.T @ d @ u.T
    return make_pose(rotation, mc - rotation @ dc)


def point_to_plane_step(
    data: FloatArray,
    model: FloatArray,
    normals: FloatArray,
    held: FloatArray | None = None,
    scanner: FloatArray | None = None,
    tilt: tuple[FloatArray, FloatArray, float] | None = None,
    weights: FloatArray | None = None,
) -> FloatArray:
    """Small rigid motion minimising sum ((R d + t - m)·n)², linearised (R ≈ I + [ω]×) and solved in one go.

    Solved about the centroid of the data pairs, which keeps the 6x6 system well conditioned when the
    scan sits far from the origin (a metascan in world coordinates). ``held`` (unit columns): translations
    the motion must not have; it then turns about ``scanner`` (the data scan's origin, model frame), so
    that the scanner's position along them stays exactly where it is. ``tilt`` = (the inclinometer's
    up as the current transform carries it into the model frame, the world's up in the model frame,
    ratio) adds the measured tilt as a prior weighing ``ratio`` x the pairs' own tilt information
    (:mod:`slam6d.attitude`). ``weights`` (one per pair) scales each pair's squared residual
    (``ICPConfig.robust_scale``); None weighs them all alike.
    """
    centre = data.mean(axis=0) if held is None or scanner is None else np.asarray(scanner, dtype=np.float64)
    p = data - centre
    q = model - centre
    residual = np.einsum("ij,ij->i", p - q, normals)
    jac = np.empty((len(p), 6))
    cross_rows(p, normals, out=jac[:, :3])
    jac[:, 3:] = normals
    weighted = jac if weights is None else jac * weights[:, None]
    a = weighted.T @ jac
    b = -(weighted.T @ residual)
    if tilt is not None:
        reading, up, ratio = tilt
        prior, pull = tilt_normal_equations(reading, up, ratio * tilt_information(a, reading))
        a[:3, :3] += prior
        b[:3] += pull
    if held is not None:  # solve in what the held translations leave free: the rest of a full QR
        fixed = np.zeros((6, held.shape[1]))
        fixed[3:] = held
        free = np.linalg.qr(fixed, mode="complete")[0][:, held.shape[1] :]
        x = free @ np.linalg.lstsq(free.T @ a @ free, free.T @ b, rcond=None)[0]
    else:
        try:
            x = np.linalg.solve(a, b)
        except np.linalg.LinAlgError:
            x = np.linalg.lstsq(a, b, rcond=None)[0]
    rotation = so3_exp(x[:3])
    # the update is about `centre`: p' = R (p - c) + c + t
    return make_pose(rotation, centre + x[3:] - rotation @ centre)


# ---------------------------------------------------------------- how well the pairs fix the motion

# Under this a translation counts as barely fixed. On the simulated hand-held indoor walks without
# odometry (VLP-16, OS1-64, seeds 1-2), at the poses registration kept: fits within 5 cm of the truth
# 0.7-25 % (all but one over 1.1 %), the corridor fits 18-54 cm off in height 0.4-1.2 %.
WEAK_CONSTRAINT = 0.01


@dataclass(frozen=True)
class TranslationConstraint:
    """How strongly point-to-plane pairs fix a translation in each direction, weakest first.

    ``values[k]`` belongs to the unit direction ``directions[:, k]``: the eigenvalue, per pair, of
    the linearised point-to-plane normal equations reduced to the translation with the rotation
    solved for too (the Schur complement), i.e. the mean squared displacement along the model's
    normals that a unit translation that way causes once the best rotation has absorbed what it can:
    1 if every pair's normal lay along it, 0 if no pair constrains it.
    """

    values: FloatArray
    directions: FloatArray


def translation_constraint(data: FloatArray, normals: FloatArray) -> TranslationConstraint:
    """The :class:`TranslationConstraint` of point-to-plane pairs: the paired ``data`` points and the
    model's ``normals`` at their partners, one frame (where the pairs are and how their planes face
    decides it, not how far apart they are).

    What it is for: a fit can pair 80 % of a scan and still leave one direction to a handful of
    points. A corridor seen by a 16- or 64-beam lidar held at chest height is the case measured: the
    walls fix the sideways motion and the heading, only the floor and ceiling fix the height, and they
    lie beyond the lowest and highest beams but for about 1 % of the points; ICP started from the truth
    drifts 5-19 cm in height there (docs/robustness.md, "Indoor hand-held walks without odometry").
    """
    data = np.asarray(data, dtype=np.float64)
    if len(data) < 6:
        raise ValueError(f"a rigid motion has 6 unknowns; {len(data)} pairs cannot fix it")
    p = data - data.mean(axis=0)
    jac = np.hstack([np.cross(p, normals), normals])
    a = jac.T @ jac / len(p)
    rotation, translation, mixed = a[:3, :3], a[3:, 3:], a[:3, 3:]
    reduced = translation - mixed.T @ np.linalg.lstsq(rotation, mixed, rcond=None)[0]
    values, directions = np.linalg.eigh((reduced + reduced.T) / 2)
    return TranslationConstraint(np.maximum(values, 0.0), directions)


# ---------------------------------------------------------------- ICP


@dataclass(frozen=True)
class MotionPrior:
    """What a scan's motion model says about where it is, for the translations ICP holds because its
    pairs barely fix them (``ICPConfig.hold_below``; :func:`_held_at` decides between the two).

    ``previous``: where the data scanner was before this motion; ``predicted``: where the motion
    model puts it now (both in the model frame, metres); ``error``: how far the same model's
    predictions of the last steps were off (metres), None when it has predicted nothing yet.
    Sequential registration without odometry passes the previous scan's position, the
    constant-velocity prediction and its recent misses (``slam6d.pipeline.Pipeline._motion_prior``).
    """

    previous: FloatArray
    predicted: FloatArray
    error: float | None = None

    def __post_init__(self) -> None:
        for name in ("previous", "predicted"):
            value = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise ValueError(f"MotionPrior.{name} must be a finite 3-vector (metres), got {value}")
            object.__setattr__(self, name, value)
        if self.error is not None and not (self.error >= 0 and math.isfinite(self.error)):
            raise ValueError(f"MotionPrior.error must be a finite distance >= 0 (metres) or None, got {self.error}")

    @property
    def miss(self) -> float:
        """How far the prediction may be off: ``error``, or without one the share of the predicted
        step more than 45° away from a direction (cos 45° x its length)."""
        if self.error is not None:
            return self.error
        return math.cos(math.radians(45.0)) * float(np.linalg.norm(self.predicted - self.previous))

    def moves_along(self, directions: FloatArray) -> bool:
        """Whether the predicted motion within the span of ``directions`` (orthonormal columns) stands
        out of :attr:`miss`: real motion there, not the model's miss. The length of a projection onto
        a span is the same whatever orthonormal basis of it is given."""
        return float(np.linalg.norm(directions.T @ (self.predicted - self.previous))) > self.miss


def _pairs(
    model: ModelIndex,
    moved: FloatArray,
    max_distance: float,
    point_to_plane: bool,
    scanner: FloatArray | None = None,
) -> tuple[IndexArray, FloatArray, FloatArray, FloatArray | None]:
    """(data_idx, paired model points, distances, model normals or None).

    Point-to-plane pairs with the plane sample and drops pairs whose normal is unusable, and with
    ``scanner`` (the data scanner in the model frame) those on a face the model saw from the other side.
    """
    if not point_to_plane:
        dist, idx = model.nearest(moved, max_distance)
        data_idx = np.flatnonzero(idx >= 0)
        return data_idx, model.points[idx[data_idx]], dist[data_idx], None
    return model.plane_pairs(moved, max_distance, scanner)


def icp_iterations(
    model: ModelIndex | FloatArray,
    data: FloatArray,
    initial: FloatArray = np.eye(4),
    config: ICPConfig = ICPConfig(),
    prior: MotionPrior | None = None,
    tilt: ScanTilt | None = None,
) -> Iterator[ICPIteration]:
    """Run ICP one step at a time (see the module docstring for the convergence rule).

    ``tilt``: the data scan's measured up (an inclinometer; :class:`slam6d.attitude.ScanTilt`), a
    prior on its roll and pitch in every point-to-plane step (point-to-point ignores it).

    ``prior``: where the data scan's origin was and where its motion model puts it (model frame); the
    translations ``config.hold_below`` holds stay where :func:`_held_at` says from it. None keeps the
    start's position along them. Raises :class:`RegistrationError` when a step finds fewer than
    ``config.min_pairs`` pairs.
    """
    data = _prepare_data(data, config)
    return _iterate(_as_model(model, config), data, _as_transform(initial), config, prior, tilt)


def _prepare_data(data: FloatArray, config: ICPConfig) -> FloatArray:
    data = _as_data(data)
    if config.data_voxel_size > 0 and len(data):
        data = data[reduce_points(data, config.data_voxel_size)]
    return data


def _small(motion: FloatArray, tolerance: float) -> bool:
    return float(np.linalg.norm(motion[:3, 3])) <= tolerance and rotation_angle(motion[:3, :3]) <= tolerance


def _settled(steps: list[FloatArray], tolerance: float) -> bool:
    """Whether the newest pose is within ``tolerance`` of one of the previous ``_CYCLE`` poses of the stage.

    The motion from ``T_{k-m}`` to ``T_k`` is the product of the last m steps. Composing the steps
    (always exact rotations) rather than comparing poses keeps the test exact even when the initial
    pose came from a file with a slightly non-orthonormal rotation.
    """
    motion = np.eye(4)
    for step in reversed(steps[-_CYCLE:]):
        motion = motion @ step
        if _small(motion, tolerance):
            return True
    return False


def _held_at(held: FloatArray, prior: MotionPrior, fitted: FloatArray) -> FloatArray | None:
    """Where the data scan's origin stays along the translations its pairs barely fix (the unit
    columns of ``held``, an orthonormal basis of them), given the ``prior`` and where ICP converged
    (``fitted``); None where the fit stays as it is.

    * The motion the prior predicts within them does not stand out of its model's recent misses
      (:meth:`MotionPrior.moves_along`): that motion is the model's miss, not the platform's (a hand's
      last step repeated from a frame tilted by its wobble puts 5-40 cm into a corridor's height,
      where the hand moved a few centimetres), and the fit there follows the normals' noise (a
      corridor's height: 5-19 cm from the truth itself). The previous position is kept.
    * It stands out, and the fit is within those misses of the prediction there: the motion is real
      and the pairs, few as they are, measured it as well as the prediction could (a car's 2 m step
      on open ground whose horizontal translations rest on 2 % of the pairs each, the prediction 8 cm
      off as the car speeds up, ICP from the truth 1.4 cm). The fit stays; such a fit says so
      (``ICPIteration.weak_along_motion``), and sequential registration tries it again coarse to
      fine, since its heading rests on the same few pairs.
    * It stands out and the fit left the prediction by more: the pairs let the scan slide (a
      featureless tunnel) or stick to where the scanner was (the same car's next scan, in a run
      without that retry: 1.3 m back towards it). The prediction is kept.

    Why the span and not each direction: within a span of two or more barely fixed translations the
    eigenvectors that make up ``held`` are any rotation of each other, so a rule deciding per
    direction depends on that chance basis (the rule before this one took a direction more than 45°
    from the step as across it and kept the previous position there: the car's 2 m step, 72° from
    one of them, lost its 0.6 m share; docs/robustness.md). The lengths compared here are of
    projections onto the span, and the position kept (``held @`` the value returned) is the previous
    or predicted one projected onto it: the same whatever the basis."""
    if not prior.moves_along(held):
        return held.T @ prior.previous
    if float(np.linalg.norm(held.T @ (np.asarray(fitted, dtype=np.float64) - prior.predicted))) <= prior.miss:
        return None
    return held.T @ prior.predicted


def _iterate(
    model: ModelIndex,
    data: FloatArray,
    transform: FloatArray,
    config: ICPConfig,
    prior: MotionPrior | None = None,
    tilt: ScanTilt | None = None,
) -> Iterator[ICPIteration]:
    point_to_plane = config.method == "point_to_plane"
    start = transform[:3, 3].copy()
    stages = config.stages()
    stage = 0
    steps: list[FloatArray] = []  # updates of the current stage, newest last
    held: FloatArray | None = None  # translations held (unit columns), once checked
    budget = config.max_iterations  # iterations left; holding translations starts a new count
    weak_along_motion = False  # see ICPIteration
    gating = False  # the residual gate applies once the run has converged with every pair (ICPConfig)
    index = 0
    while budget > 0:
        budget -= 1
        max_distance = stages[stage]
        last_stage = stage == len(stages) - 1
        tolerance = config.epsilon if last_stage else max(config.epsilon, config.stage_epsilon)
        moved = transform_points(transform, data)
        scanner = transform[:3, 3] if config.facing_pairs else None
        data_idx, paired_model, dist, normals = _pairs(model, moved, max_distance, point_to_plane, scanner)
        if len(data_idx) < config.min_pairs:
            usable = " with a usable model normal" if point_to_plane else ""
            raise RegistrationError(
                f"ICP iteration {index}: only {len(data_idx)} of {len(data)} data points have a model point"
                f"{usable} within {max_distance:g} m (need {config.min_pairs}); the scans do not overlap"
                " enough or the initial pose is too far off"
            )
        rms = float(np.sqrt(np.mean(dist * dist)))
        pairs = len(data_idx)
        off = dist if normals is None else np.abs(np.einsum("ij,ij->i", moved[data_idx] - paired_model, normals))
        close = int(np.count_nonzero(off <= CLOSE_SHARE * max_distance))
        weights = None
        if normals is not None and gating:
            if config.residual_gate > 0:
                data_idx, paired_model, normals = gate_residuals(
                    moved[data_idx], data_idx, paired_model, normals, config.residual_gate
                )
            if config.robust_scale > 0:
                weights = robust_weights(moved[data_idx], paired_model, normals, config.robust_scale)
        if normals is not None:
            carried = None if tilt is None else (transform[:3, :3] @ tilt.reading, tilt.up, tilt.ratio)
            step = point_to_plane_step(moved[data_idx], paired_model, normals, held, transform[:3, 3], carried, weights)
        else:
            step = point_to_point_step(moved[data_idx], paired_model)
        transform = step @ transform
        step_t = float(np.linalg.norm(step[:3, 3]))
        step_r = rotation_angle(step[:3, :3])
        steps.append(step)
        stage_done = _settled(steps, tolerance)
        finished = stage_done and last_stage
        robust = config.residual_gate > 0 or config.robust_scale > 0
        if finished and not gating and robust and normals is not None:
            gating, steps, finished = True, [], False  # settle again without the pairs off their planes
        if finished and held is None and config.hold_below > 0 and normals is not None:
            # converged: which translations do the pairs barely fix? Those go back to where the prior
            # (else the start) has them and stay there while ICP settles the rest (see the module docstring)
            constraint = translation_constraint(transform_points(step, moved[data_idx]), normals)
            weak = constraint.directions[:, constraint.values < config.hold_below]
            weak_along_motion = weak.size > 0 and prior is not None and prior.moves_along(weak)
            keep: FloatArray | None = None
            if weak.size:
                keep = weak.T @ start if prior is None else _held_at(weak, prior, transform[:3, 3])
            if keep is not None:
                held = weak
                transform[:3, 3] -= held @ (held.T @ transform[:3, 3] - keep)
                steps, budget, finished = [], config.max_iterations, False
        yield ICPIteration(
            index=index,
            transform=transform.copy(),
            pairs=pairs,
            rms=rms,
            max_distance=max_distance,
            step_translation=step_t,
            step_rotation=step_r,
            converged=finished,
            held=0 if held is None else held.shape[1],
            weak_along_motion=weak_along_motion,
            close=close,
        )
        index += 1
        if finished:
            return
        if stage_done and not last_stage:
            stage += 1
            steps = []


def gate_residuals(
    moved: FloatArray, data_idx: IndexArray, partners: FloatArray, normals: FloatArray, gate: float
) -> tuple[IndexArray, FloatArray, FloatArray]:
    """The point-to-plane pairs (``moved[i]`` with ``partners[i]``, ``normals[i]``) whose signed
    residual lies within ``gate`` robust standard deviations of the median residual (at least
    ``RESIDUAL_GATE_FLOOR``): ``(data_idx, partners, normals)`` of those kept (see
    ``ICPConfig.residual_gate``). Robust because the pairs left out are a minority whose size
    does not set the width."""
    residuals = np.einsum("ij,ij->i", moved - partners, normals)
    if len(residuals) == 0:
        return data_idx, partners, normals
    centre = float(np.median(residuals))
    spread = 1.4826 * float(np.median(np.abs(residuals - centre)))
    kept = np.abs(residuals - centre) <= max(gate * spread, RESIDUAL_GATE_FLOOR)
    return data_idx[kept], partners[kept], normals[kept]


def robust_weights(moved: FloatArray, partners: FloatArray, normals: FloatArray, scale: float) -> FloatArray:
    """Geman-McClure's weight 1 / (1 + (r / ``scale``)²)² of each point-to-plane pair's residual r
    (see ``ICPConfig.robust_scale``)."""
    residuals = np.einsum("ij,ij->i", moved - partners, normals)
    return 1.0 / (1.0 + (residuals / scale) ** 2) ** 2


def icp(
    model: ModelIndex | FloatArray,
    data: FloatArray,
    initial: FloatArray = np.eye(4),
    config: ICPConfig = ICPConfig(),
) -> ICPResult:
    """Register ``data`` to ``model``: returns model_from_data and the per-iteration trace."""
    data = _prepare_data(data, config)
    iterations = list(_iterate(_as_model(model, config), data, _as_transform(initial), config))
    return ICPResult.from_iterations(iterations, len(data), config.method)


def count_pairs(model: ModelIndex | FloatArray, data: FloatArray, transform: FloatArray, max_distance: float) -> int:
    """How many data points, placed by ``transform``, have a model point within ``max_distance``."""
    model = model if isinstance(model, ModelIndex) else ModelIndex(model)
    _, idx = model.nearest(transform_points(_as_transform(transform), _as_data(data)), max_distance)
    return int(np.count_nonzero(idx >= 0))


def correspondences(
    model: ModelIndex | FloatArray, data: FloatArray, transform: FloatArray, max_distance: float, limit: int = 2000
) -> tuple[IndexArray, IndexArray]:
    """Closest-point pairs (data_idx, model_idx) within ``max_distance``, at most ``limit`` of them,
    spread evenly over the data so a drawing of them shows the whole overlap."""
    model = model if isinstance(model, ModelIndex) else ModelIndex(model)
    _, idx = model.nearest(transform_points(_as_transform(transform), _as_data(data)), max_distance)
    data_idx = np.flatnonzero(idx >= 0)
    if limit >= 0 and len(data_idx) > limit:
        data_idx = data_idx[np.linspace(0, len(data_idx) - 1, limit).round().astype(np.int64)]
    return data_idx, idx[data_idx]
