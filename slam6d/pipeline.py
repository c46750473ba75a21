"""The whole trajectory: sequential matching, loop closing and global relaxation as one steppable run.

Everything happens in one generator (:meth:`Pipeline._events`) that yields an event after every
ICP iteration and every stage step. The workbench calls :meth:`Pipeline.step` to advance by one
event and draws it; :meth:`Pipeline.run` drains the same generator, so the batch command line and
the interactive workbench can never disagree about what the pipeline does.

Stages (after Nüchter et al.):

1. Sequential registration. Scan i starts from the previous registered pose moved by the odometry
   increment (or, without odometry, by the previous motion); the octree search refines that start
   when there is no odometry (``octree_guess="auto"``) or when ICP's fit turns out poor; then ICP
   against the previous scan (pairwise) or against the recently registered scans (metascan: the
   last ``metascan_scans`` stacked, each searched with the kd-tree and normals it got when it was
   added; or, where a scan's rings lie too far apart for its own cubes to hold planes, the last
   ``fused_scans`` joined into one model whose plane sample and normals span their interleaved rings).
2. Loops. For each scan, earlier scans within a fraction of the laser range but far along the path
   are loop hypotheses (a radius index over the positions); the best by octree overlap is matched by ICP
   from its pose-implied start (and from the octree search's winner when that fits poorly) against
   the earlier scan - fused with its neighbours where registration fused - judged against the
   sequence's usual consecutive overlap and fitness, and when accepted its correction is diffused
   over the loop and every loop closed so far is held at once with the registered steps
   (:mod:`slam6d.loops`).
3. Relaxation over the neighbour graph: the seed's simultaneous matching, or LUM-style pose-graph
   least squares (:mod:`slam6d.relax`, :mod:`slam6d.simultaneous`, :mod:`slam6d.lum`).

Each scan is reduced once (one real point per voxel) and its kd-tree is built once; every stage
reuses them.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Generator, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from slam6d.attitude import PLANES_TILT_DEG, RINGS_TILT_DEG, Readings, TiltPrior, heading_only
from slam6d.errors import DisconnectedGraphError, RegistrationError, RelaxationError, Slam6dError
from slam6d.events import (
    Event,
    Finished,
    IcpIterated,
    LoopClosed,
    LoopsDetected,
    PipelineReport,
    RelaxationProgressed,
    ScanRegistered,
    ScanSkipped,
    ScanStarted,
    ScanSummary,
    StageFailure,
)
from slam6d.features import feature_guess
from slam6d.geometry import Matrix, invert, rotation_angle, transform_points
from slam6d.graph_relaxation import GraphEdge, trajectory_graph
from slam6d.icp import ICPConfig, ICPIteration, ICPResult, MotionPrior, icp_iterations, translation_constraint
from slam6d.initial_guess import GuessResult, OctreeSearchConfig, extrapolate_odometry, octree_guess
from slam6d.io.frames import FrameType, write_sequence_frames
from slam6d.loops import (
    LoopCandidates,
    LoopConfig,
    LoopHypothesis,
    diffuse_loop_correction,
    find_loop_hypotheses,
    hold_closed_loops,
    lever_arm,
    loop_correction,
    octree_overlap,
    usual_fit,
    verify,
)
from slam6d.model import ModelIndex, StackedModel, fused_model
from slam6d.octree import Occupancy, Octree, reduce_points
from slam6d.pair import MIN_FITNESS, FitMeasure, Outcome, better_fit, coarse_to_fine, is_poor
from slam6d.relax import Cancelled, RelaxationConfig, RelaxationResult, ScanModels
from slam6d.relaxation_methods import models_icp_config, relax_poses
from slam6d.scan import ScanSequence
from slam6d.scan_store import ScanStore, peak_memory_bytes
from slam6d.scheduler import Scheduler
from slam6d.trace import to_jsonable, write_trace

MATCHING = ("metascan", "pairwise")
FUSE_BELOW_CUBE_SHARE = 0.2  # ModelIndex.smallest_cube_share: VLP-16 outdoors 0.00-0.11, the rest >= 0.27
# Scans are reduced on this many threads, and prepared for matching ahead of the one being registered
# (PREPARE_AHEAD scans) on a second thread.
WORKER_THREADS = min(2, os.cpu_count() or 1)
PREPARE_AHEAD = 3
FITNESS_HISTORY = 5  # registered scans whose median fitness sets the sequence's own bar
PREDICTION_HISTORY = 3  # registered steps whose worst constant-velocity miss says how far to trust it
# Without odometry, a fit pairing under this share of the recent median gets a second, coarse-to-fine
# ICP from the prediction (simulated OS1-64 car: right fits 0.53-0.56, wrong ones 0.32-0.34, i.e.
# 0.63 of the median, above the bar; correct campus VLP-16 fits pair 0.68-1.2 of theirs, so a right
# fit is rechecked now and then, at the cost of one ICP that converges where the first one did)
RECHECK_SHARE = 0.8
# With odometry, a searched start (octree or features) is kept only within this share of the
# odometry step (on top of PipelineConfig.odometry_trust_m / _deg) of the odometry prediction.
ODOMETRY_TRUST_SHARE = 0.1
GUESS_MODES = ("auto", "always", "never")
RELAXATION = ("lum", "graph", "simultaneous", "none")  # see slam6d.relaxation_methods

__all__ = ["Cancelled", "Pipeline", "PipelineConfig", "write_results"]


@dataclass(frozen=True)
class PipelineConfig:
    """Settings of a full run; lengths in metres.

    ``min_fitness`` is the fraction of data points that must find a partner for a sequential match
    to count as good; below it (or when ICP fails) ``octree_guess="auto"`` searches a new start.
    Once ``FITNESS_HISTORY`` scans are registered the bar is ``relative_fitness`` x the median
    fitness of the recent ones, above or below ``min_fitness``: what fraction of the data pairs
    within the max distance depends on the sensor's sampling, not only on the fit. A VLP-16 on a
    car samples the ground in rings 0.5-3 m apart that land elsewhere after a 1-3 m step, so
    correct fits pair 25-45 % of the data (simulated campus, median 37 %); a 30 % bar sent a fifth
    of the scans through both searches, which kept the first fit nearly every time and cost 80 %
    of the registration time. A dense scanner carried through a hall pairs 80-90 % when right
    (BALM hall): there, after a fast hand-held turn without odometry, ICP from the
    constant-velocity prediction ended in the wrong basin (0.2-2.6 m, 8-38° off) pairing 32-41 %,
    which a 30 % bar accepted, and every later prediction inherited the wrong motion. A fit in the
    wrong basin pairs far fewer than the sequence's usual share, whatever that share is: on BALM
    0.4-0.54 of the recent median, while correct campus fits pair 0.68-1.2 of theirs, hence 0.6.
    ``data_voxel_size`` thins the scan being registered (one real point per voxel) while the model
    keeps ``voxel_size``: matching cost follows the data points, accuracy mostly the model's density.
    ``normal_cell_voxels`` > 0 gives sequential registration per-cube normals over cubes of that many
    ``voxel_size`` (:func:`slam6d.normals.cell_normals`, about ten times cheaper than k-NN normals, which
    loop verification and relaxation keep, and which fill in where a cube gives none); 0 uses k-NN
    normals there too. With per-cube normals, data points are paired with the model reduced further,
    to one point per cube of ``sample_voxels`` x ``voxel_size`` (0 = every model point): the plane,
    not the sample point, carries a point-to-plane residual and the normals still come from all the
    model's points, so the smaller tree searched every iteration saves ~10 % of the registration time
    while the ATE before relaxation stays within its usual scatter (benchmark loop 0.40 instead of
    0.48 cm; the same loop simulated with seed 1, 0.33 instead of 0.26 cm). ``metascan_scans`` is
    how many recent scans the metascan stacks, each searched with its own kd-tree and normals (on the
    benchmark loop 3 scans instead of 1 cost 2.5x the registration time for the same ATE after
    relaxation, 0.33 vs 0.35 cm). Where a scan cannot find its planes alone (its smallest cubes hold
    a plane for fewer than ``FUSE_BELOW_CUBE_SHARE`` of its plane sample: a multi-beam lidar
    outdoors) the metascan is instead the last ``fused_scans`` scans joined into one model in the
    newest scan's frame (:func:`slam6d.model.fused_model`: reduced to ``voxel_size`` where they
    overlap, plane sample and cube normals over the union; 0 or 1 turns this off): a car's VLP-16
    puts its rings metres apart, and a scan taken a few metres back puts its rings between them, so
    pairs and planes span interleaved rings instead of pulling roll and pitch by the rings' own
    planes (campus steps matched from the truth: 0.37° RMS tilt against one scan, 0.14° against
    three fused; docs/scale.md, "The rings' own planes"). ``relax_registration_models`` lets LUM rounds
    pair against the sequential-matching models (built already: 0.2 m sample, per-cube normals)
    instead of each whole reduced scan with k-NN normals: ~0.5 s less CPU on the benchmark loop for an
    ATE after relaxation of 0.21 instead of 0.19 cm (0.14 instead of 0.15 cm with seed 1).
    ``registration_epsilon`` is the convergence tolerance of sequential matching (at least the ICP
    ``epsilon``): loop closing and relaxation refine every pose afterwards, so iterating below a
    millimetre there buys nothing (benchmark loop: 15 % less registration time than at 0.5 mm, ATE
    after relaxation 0.187 cm either way; BALM hall RPE 0.53 cm either way).
    ``max_range`` (the laser's reach) bounds loop hypotheses; None estimates it from the scans.
    ``feature_guess`` lets a scan whose ICP still fits poorly after the octree search try the global
    FPFH + RANSAC guess (:mod:`slam6d.features`) too (not with ``octree_guess="never"``).
    ``odometry_trust_m`` / ``odometry_trust_deg`` (plus ``ODOMETRY_TRUST_SHARE`` of the odometry
    step) bound how far a searched start's fit may end from the odometry prediction and still be
    kept: the searches only run where the fit is poor, which in a sharp turn (the campus: 24° in a
    3 m step, a third of the model out of view) happens with the right answer, and there the global
    feature guess can pair a symmetric street the other way round a little better (campus scan 269:
    kept 2.9 m and 153° off an odometry 6 cm and 1.3° off). ``math.inf`` trusts the searches always.
    ``hold_constraint``: a sequential fit's translations that its pairs fix less than this share
    (:func:`slam6d.icp.translation_constraint`) are held (``ICPConfig.hold_below``): at the odometry's
    prediction when there is one, else at the previous scan's position where the motion the
    constant-velocity prediction puts into them is within its recent misses (a hand's sway), and at
    the prediction or the fit where it stands out of them (a car's step; :meth:`Pipeline._motion_prior`,
    :func:`slam6d.icp._held_at`); 0 turns it off. The case: a corridor seen by a VLP-16 or OS1-64 held
    at 1.4 m, whose floor and ceiling lie beyond the beams but for ~1 % of the points. ICP's height
    there follows the normals' noise (from the truth it drifts 5-19 cm) and ended 18-54 cm off from
    the constant-velocity prediction, whose own height is 14-39 cm off (the last step repeated from a
    frame tilted by the hand's wobble); the previous scan's height is off by the hand's sway, a few
    centimetres. The constraint of those fits is 0.3-1.2 % at the right pose but reads 1.7-2.1 % at
    a pose already 42-48 cm off, so the bar sits above that; fits that pair the floor (the HDL-32E's
    walks, every car session) have 5-25 % and are never held. With 1.5 % the matrix's indoor VLP-16
    seed 2 walk still ended 15 cm off; with 2.5 % all four indoor walks without odometry end at
    0.9-3.3 cm (docs/robustness.md, "Indoor hand-held walks without odometry").
    ``residual_gate``: sequential ICP leaves out, each step, the pairs whose point-to-plane residual
    lies more than this many robust standard deviations from the median (``ICPConfig.residual_gate``;
    0, the default, keeps every pair within the max distance). Off by default because LUM, which
    still pairs every point, then relaxes from a start it does not agree with: on the 8-scan test
    loop the final ATE rose 0.38 -> 0.44 cm, BALM's RPE 0.55 -> 0.58 cm (docs/scale.md). Pairs whose model plane is wrong (a cube normal
    over a distant surface's sparse scan lines, an edge) sit centimetres off it even at the true
    pose, and their residuals shrink where the two scans' sampling patterns line up, at zero motion:
    on the dense simulated loop scanned 400 times (24 cm steps) they shortened every step by
    0.44 cm on average (ATE after registration 31 cm, after loop closing 25 cm, which LUM needed 8
    rounds to remove); gated at 4 (``slam6d run --residual-gate 4``), 0.03 cm (ATE after registration 4.2 cm; docs/scale.md, "Short
    steps: pairs off their planes"). Steps of 1 m are too long for the patterns to line up near the
    truth (100 scans: +0.04 cm per step), but the same pairs scatter them (ATE after registration
    7.7 -> 1.8 cm). The gate waits for ICP to converge with every pair (``ICPConfig.residual_gate``).
    ``robust_scale``: sequential ICP, once converged with every pair equally weighted, settles again
    with each pair weighted by Geman-McClure's 1 / (1 + (r / c)²)² of its residual, c this scale in
    metres (``ICPConfig.robust_scale``; 0, the default, keeps least squares). The soft counterpart
    of the gate at a fixed scale: at 0.05 (``slam6d run --robust-scale 0.05``) the dense loop's 24 cm
    steps are no longer pulled short and, unlike the gate, the 8-scan test loop and Kurt3D keep
    their figures; off by default because BALM's RPE still rises 0.547 -> 0.562 cm (docs/scale.md,
    "Short steps: pairs off their planes").
    ``tilt_noise_deg``: the odometry poses' roll and pitch are an inclinometer's readings with this
    noise (degrees), absolute rather than accumulated; each scan's measured up is then a prior on
    its roll and pitch in sequential ICP and in the ``lum`` and ``graph`` relaxations, weighed
    against what the registration's tilt is worth per step: ``registration_tilt_deg`` where a scan
    finds its planes alone (the dense simulated loop: 0.006°), ``fused_registration_tilt_deg`` where
    it is matched against fused scans because its rings lie apart (the campus's VLP-16: 0.1°);
    :mod:`slam6d.attitude` explains the weighting. Loop closings then keep the measured tilt
    (:func:`slam6d.attitude.heading_only`). None (the default) uses no tilt: wheel odometry's zeros
    and a gyro's drifting integral are no measurement of it. ``slam6d run`` sets it from the
    session's declaration (the simulator's ``simulation.json``) or ``--tilt-noise-deg``, a
    session's ``[engine] tilt_noise_deg`` likewise.
    """

    voxel_size: float = 0.1
    data_voxel_size: float = 0.35  # the scan being matched is thinned further
    normal_cell_voxels: float = 4.0
    sample_voxels: float = 2.0
    matching: str = "metascan"
    icp: ICPConfig = field(default_factory=ICPConfig)
    octree_guess: str = "auto"
    loops: bool = True
    loop_closing: bool = True
    relaxation: str = "lum"
    max_range: float | None = None
    metascan_scans: int = 1
    fused_scans: int = 3
    relax_registration_models: bool = True
    registration_epsilon: float = 1e-3
    min_fitness: float = MIN_FITNESS
    relative_fitness: float = 0.6
    guess: OctreeSearchConfig | None = None
    feature_guess: bool = True
    odometry_trust_m: float = 0.3
    odometry_trust_deg: float = 3.0
    hold_constraint: float = 0.025
    residual_gate: float = 0.0
    robust_scale: float = 0.0
    tilt_noise_deg: float | None = None
    registration_tilt_deg: float = PLANES_TILT_DEG
    fused_registration_tilt_deg: float = RINGS_TILT_DEG
    loop: LoopConfig = field(default_factory=LoopConfig)
    relax: RelaxationConfig = field(default_factory=RelaxationConfig)

    def __post_init__(self) -> None:
        if self.matching not in MATCHING:
            raise ValueError(f"matching must be one of {MATCHING}, got {self.matching!r}")
        if self.octree_guess not in GUESS_MODES:
            raise ValueError(f"octree_guess must be one of {GUESS_MODES}, got {self.octree_guess!r}")
        if self.relaxation not in RELAXATION:
            raise ValueError(f"relaxation must be one of {RELAXATION}, got {self.relaxation!r}")
        if not self.voxel_size >= 0:
            raise ValueError(f"voxel_size must be >= 0 (0 = no reduction), got {self.voxel_size}")
        if not (
            self.normal_cell_voxels >= 0
            and self.sample_voxels >= 0
            and self.registration_epsilon >= 0
            and self.data_voxel_size >= 0
        ):
            raise ValueError(
                "normal_cell_voxels, sample_voxels, registration_epsilon and data_voxel_size must be >= 0, got "
                f"{self.normal_cell_voxels}, {self.sample_voxels}, {self.registration_epsilon}, {self.data_voxel_size}"
            )
        if not 0 <= self.relative_fitness <= 1:
            raise ValueError(f"relative_fitness must be in [0, 1], got {self.relative_fitness}")
        if not (self.odometry_trust_m > 0 and self.odometry_trust_deg > 0):
            raise ValueError(
                f"odometry_trust_m and odometry_trust_deg must be positive, got {self.odometry_trust_m},"
                f" {self.odometry_trust_deg}"
            )
        if self.metascan_scans < 1:
            raise ValueError(f"metascan_scans must be at least 1, got {self.metascan_scans}")
        if self.fused_scans < 0:
            raise ValueError(f"fused_scans must be >= 0 (0 or 1 = never fuse), got {self.fused_scans}")
        if not (self.residual_gate >= 0 and math.isfinite(self.residual_gate)):
            raise ValueError(f"residual_gate must be >= 0 (0 = keep every pair), got {self.residual_gate}")
        if not (self.robust_scale >= 0 and math.isfinite(self.robust_scale)):
            raise ValueError(f"robust_scale must be >= 0 metres (0 = least squares), got {self.robust_scale}")
        if self.max_range is not None and not self.max_range > 0:
            raise ValueError(f"max_range must be positive, got {self.max_range}")
        if self.tilt_noise_deg is not None and not (self.tilt_noise_deg > 0 and math.isfinite(self.tilt_noise_deg)):
            raise ValueError(
                f"tilt_noise_deg must be a positive number of degrees (or unset: no inclinometer), got {self.tilt_noise_deg}"
            )
        for name in ("registration_tilt_deg", "fused_registration_tilt_deg"):
            value = getattr(self, name)
            if not (value > 0 and math.isfinite(value)):
                raise ValueError(f"{name} must be a positive number of degrees, got {value}")


# ---------------------------------------------------------------- the pipeline


class Pipeline:
    """A steppable run over a :class:`ScanSequence`; see the module docstring."""

    def __init__(
        self,
        sequence: ScanSequence,
        config: PipelineConfig = PipelineConfig(),
        store: ScanStore | None = None,
        scheduler: Scheduler | None = None,
        readings: Readings | None = None,
    ) -> None:
        """``store``: the scans' points on disk (:mod:`slam6d.scan_store`), read once for the reduction
        instead of from ``sequence``, whose scans then need only their poses and names.
        ``scheduler`` (:mod:`slam6d.scheduler`): where the reduction and LUM's per-scan blocks run
        (a Dask cluster's workers read a store themselves); None keeps everything in this process.
        ``readings``: the inclinometer's readings where they are not the scans' own poses (a session
        registered again from a later revision: :func:`slam6d.session_relaxation.registration_readings`)."""
        if len(sequence) == 0:
            raise Slam6dError("the sequence has no scans")
        self.sequence = sequence
        self.config = config
        self.odometry: list[Matrix] = [scan.pose.copy() for scan in sequence]
        self.has_odometry = [bool(scan.has_pose) for scan in sequence]
        self.poses: list[Matrix] = [p.copy() for p in self.odometry]
        # the odometry's roll and pitch as an inclinometer's readings, where the session has one
        # (each scan's weight is set when registration chooses its model: _model)
        held = readings or Readings(self.odometry, self.has_odometry)
        if len(held.poses) != len(sequence) or len(held.measured) != len(sequence):
            raise Slam6dError(f"readings for {len(held.poses)} scans, the sequence has {len(sequence)}")
        self.tilt = inclinometer_prior(config, held.poses, held.measured)
        self.history: list[list[tuple[Matrix, int]]] = [[(p.copy(), FrameType.ICP_INACTIVE)] for p in self.poses]
        self.registered = 1  # scan 0 anchors the map
        self.done = False
        self.stage = "reduction"
        self.stage_seconds: dict[str, float] = {}
        self.loops: list[LoopHypothesis] = []
        self.loops_closed: list[tuple[int, int]] = []
        self.relaxation_result: RelaxationResult | None = None
        self.report: PipelineReport | None = None
        self.failure: StageFailure | None = None
        self.components: list[list[int]] = []
        self.skipped: list[int] = []  # scans sequential registration could not place (ScanSkipped)
        self.links: list[tuple[int, int]] = []  # (model scan, scan) of every sequential registration
        self._cancel: Callable[[], bool] | None = None
        # the models are reduced already; the scans matched against them lie in their scanners' frames
        self._icp_config = replace(models_icp_config(config.icp, config.voxel_size), facing_pairs=True)
        # sequential matches only need to hand loop closing and relaxation a close start
        self._sequential_config = replace(
            self._icp_config,
            epsilon=max(config.icp.epsilon, config.registration_epsilon),
            hold_below=config.hold_constraint,
            residual_gate=config.residual_gate,
            robust_scale=config.robust_scale,
        )
        # a constant-velocity prediction is off by however much the motion changed (a car easing out
        # of a turn: 4° of yaw); a fit from it that pairs clearly fewer than usual is redone with this
        self._predicted_config = coarse_to_fine(self._sequential_config)
        began = time.perf_counter()

        # The per-scan work here and in _prepare is compiled code and kd-tree builds that release the
        # GIL, so it runs on a second thread beside the main one.
        def reduced_scan(k: int) -> np.ndarray:
            return self._reduce(store.points(k) if store is not None else sequence[k].points)

        self.scheduler = scheduler
        if scheduler is not None:
            voxels = [config.voxel_size] * len(sequence)
            if store is not None:
                folders = [str(store.directory.resolve())] * len(sequence)  # workers may run elsewhere
                reduced = scheduler.map(reduce_stored_scan, folders, range(len(sequence)), voxels)
            else:
                reduced = scheduler.map(reduce_scan, [scan.points for scan in sequence], voxels)
        elif WORKER_THREADS > 1 and len(sequence) > 1:
            with ThreadPoolExecutor(WORKER_THREADS) as pool:
                reduced = list(pool.map(reduced_scan, range(len(sequence))))
        else:
            reduced = [reduced_scan(k) for k in range(len(sequence))]
        sizes = store.counts if store is not None else [len(scan) for scan in sequence]
        self.models = ScanModels(reduced, self._icp_config)
        self._worker = ThreadPoolExecutor(1) if WORKER_THREADS > 1 else None
        self._preparing: dict[int, Future[tuple[ModelIndex, np.ndarray]]] = {}
        self.summaries = [
            ScanSummary(k, scan.name or f"scan{k:03d}", int(sizes[k]), len(reduced[k]))
            for k, scan in enumerate(sequence)
        ]
        self._add_time("reduction", time.perf_counter() - began)
        self._occupancy: dict[int, Occupancy] = {}
        self._max_range: float | None = None
        self._lever_arm: float | None = None
        self._events_gen: Iterator[Event] = self._events()

    # -- public stepping API

    def step(self) -> Event:
        """Advance by the smallest step (one ICP iteration, one loop, one relaxation round)."""
        if self.done:
            raise StopIteration("the pipeline has finished")
        began = time.perf_counter()
        event = next(self._events_gen)
        self._add_time(self.stage, time.perf_counter() - began)  # the stage that produced the event
        if isinstance(event, Finished):
            self.done = True
        return event

    def step_scan(self) -> list[Event]:
        """Advance until the next scan is registered (or the next stage event once all are)."""
        events = []
        while not self.done:
            event = self.step()
            events.append(event)
            if isinstance(
                event, ScanRegistered | ScanSkipped | LoopClosed | LoopsDetected | RelaxationProgressed | Finished
            ):
                break
        return events

    def run(
        self,
        progress: Callable[[str, int, int], None] | None = None,
        cancel: Callable[[], bool] | None = None,
    ) -> PipelineReport:
        """Run to the end; ``progress(stage, done, total)``; raises :class:`Cancelled` when ``cancel()`` turns true.

        A stage that fails (or a cancellation) raises, but only after :attr:`report` has been made
        with :attr:`PipelineReport.failure` naming the stage and the reason: the poses of the stages
        before it stay in :attr:`poses` for :func:`write_results`.
        """
        self._cancel = cancel
        count = len(self.sequence)
        while not self.done:
            if cancel is not None and cancel():
                cancelled = Cancelled(f"run cancelled during {self.stage}")
                self._fail(cancelled)
                raise cancelled
            event = self.step()
            if progress is None:
                continue
            if isinstance(event, ScanRegistered | ScanSkipped):
                progress("registration", event.index + 1, count)
            elif isinstance(event, LoopsDetected) and event.hypotheses:
                progress("loops", event.hypotheses[0].j + 1, count)
            elif isinstance(event, RelaxationProgressed):
                progress("relaxation", event.iteration, max(event.iteration, self.config.relax.max_rounds))
            elif isinstance(event, Finished):
                progress("done", count, count)
        assert self.report is not None
        return self.report

    # -- helpers

    def _add_time(self, stage: str, seconds: float) -> None:
        self.stage_seconds[stage] = self.stage_seconds.get(stage, 0.0) + seconds

    def _reduce(self, points: np.ndarray) -> np.ndarray:
        return reduce_scan(points, self.config.voxel_size)

    def reduced_points(self, index: int) -> np.ndarray:
        return self.models.points[index]

    def _data_points(self, index: int) -> np.ndarray:
        """Scan ``index`` thinned to ``data_voxel_size``, as it is matched against a model."""
        return self._prepared(index)[1]

    def _prepared(self, index: int) -> tuple[ModelIndex, np.ndarray]:
        """Scan ``index``'s registration model (kd-tree and normals built) and its thinned data points.

        Neither depends on any pose, so they are made ahead on the worker thread while ICP runs on
        the main one (``_prefetch``); asking for one not started yet makes it here.
        """
        future = self._preparing.get(index)
        if future is None:
            future = Future()
            future.set_result(self._prepare(index))
            self._preparing[index] = future
        return future.result()

    def _prefetch(self, indices: range) -> None:
        for index in indices:
            if self._worker is not None and index not in self._preparing and index < len(self.sequence):
                self._preparing[index] = self._worker.submit(self._prepare, index)

    def _prepare(self, index: int) -> tuple[ModelIndex, np.ndarray]:
        model = registration_model(self.models.index(index), self.config)
        # every normal now (per cube, k-NN where a cube gives none), so that ICP on the main thread
        # never waits for one: estimating them there, on demand, was a fifth of the registration time
        model.plane_normals()
        points = self.models.points[index]
        size = self.config.data_voxel_size
        data = points[reduce_points(points, size)] if size > self.config.voxel_size else points
        return model, data

    def _finish_preparing(self) -> None:
        """Stop the worker once the work started ahead is done, so no thread touches the models after
        registration (an error there belongs to a scan no match needed, and is raised if one does)."""
        if self._worker is not None:
            self._worker.shutdown(wait=True)
            self._worker = None

    def max_range(self) -> float:
        """The laser's reach: configured, or the median over scans of each scan's 99th-percentile range."""
        if self.config.max_range is not None:
            return float(self.config.max_range)
        if self._max_range is None:  # asked by the loop stage and the report
            ranges = [np.percentile(np.sqrt(np.einsum("ij,ij->i", p, p)), 99) for p in self.models.points]
            self._max_range = float(np.median(ranges))
        return self._max_range

    def _set_pose(self, index: int, pose: Matrix, flag: int) -> None:
        self.poses[index] = np.array(pose, dtype=np.float64)
        self.history[index].append((self.poses[index].copy(), flag))

    def _carry_unregistered(self, index: int) -> None:
        """Scans not registered yet follow the newest registered one by their odometry increments."""
        anchor = self.poses[index] @ invert(self.odometry[index])
        for k in range(index + 1, len(self.poses)):
            self.poses[k] = anchor @ self.odometry[k] if self.has_odometry[k] else self.poses[index].copy()

    def _fail(self, error: Slam6dError) -> None:
        """Record why the run stops and make the report of what it has (see :meth:`run`)."""
        self.failure = StageFailure(self.stage, str(error), type(error).__name__)
        self.done = True
        self._finish_preparing()
        self.report = self._make_report()

    # -- the generator

    def _events(self) -> Iterator[Event]:
        try:
            yield from self._stages()
        except Slam6dError as error:  # Cancelled included; the stages' results so far are kept
            self._fail(error)
            raise
        self.stage = "finished"
        self.report = self._make_report()
        yield Finished(self.report)

    def _stages(self) -> Iterator[Event]:
        self.stage = "registration"
        self.history[0].append((self.poses[0].copy(), FrameType.ICP))
        for index in range(1, len(self.sequence)):
            self._prefetch(range(index - 1, index + PREPARE_AHEAD))
            yield from self._register(index)
        self._finish_preparing()
        if self.config.loops and len(self.sequence) > 2:
            self.stage = "loops"
            yield from self._loop_stage()
        if self.config.relaxation != "none" and len(self.sequence) > 1:
            self.stage = "relaxation"
            yield from self._relax_stage()
        elif self.skipped:  # nothing else could tell that the map fell apart
            self.stage = "registration"
            raise RegistrationError(
                f"{len(self.skipped)} scan(s) could not be registered: {self.summaries[self.skipped[0]].failure}"
                + (" ..." if len(self.skipped) > 1 else "")
            )

    def _odometry_step(self, index: int) -> bool:
        """Whether odometry relates scan ``index`` to the one before it."""
        return self.has_odometry[index] and self.has_odometry[index - 1]

    def _start_pose(self, index: int) -> Matrix:
        prev = self.poses[index - 1]
        if self._odometry_step(index):
            return extrapolate_odometry(self.odometry[index - 1], prev, self.odometry[index])
        if index >= 2:  # constant velocity: repeat the last motion
            return prev @ invert(self.poses[index - 2]) @ prev
        return prev.copy()

    def registration_model(self, index: int) -> ModelIndex:
        """Scan ``index`` as a sequential-matching model: its kd-tree (shared with the loop and
        relaxation stages, built once) and its normals (per cube when ``normal_cell_voxels`` > 0)."""
        return self._prepared(index)[0]

    def _model(self, index: int) -> tuple[ModelIndex, Matrix, list[int]]:
        """Model for scan ``index``: (index, world_from_model, scans in it)."""
        if self.config.matching == "pairwise":
            return self.registration_model(index - 1), self.poses[index - 1], [index - 1]
        fusing = fuses_scans(self.config, index, self._needs_fusing)
        if self.tilt is not None:  # what the fit's tilt is worth, for weighing the inclinometer against it
            self.tilt.registered_with(index, registration_tilt_deg(self.config, fusing))
        if fusing:
            fused = list(range(max(0, index - self.config.fused_scans), index))
            return self._fused_model(fused), self.poses[index - 1], fused
        members = list(range(max(0, index - self.config.metascan_scans), index))
        stack = StackedModel([self.registration_model(k) for k in members], [self.poses[k] for k in members])
        return stack, np.eye(4), members

    def _needs_fusing(self, index: int) -> bool:
        """Whether scan ``index`` alone leaves its planes to the scans' rings: its smallest cubes hold
        a plane for fewer than ``FUSE_BELOW_CUBE_SHARE`` of its plane sample (a multi-beam lidar
        outdoors). Dense and close-range scans find their planes alone, and a fused model costs
        them time for nothing (BALM's hall: RPE 0.57 instead of 0.54 cm, registration ~3x)."""
        return needs_fusing(self.registration_model(index))

    def _fused_model(self, members: list[int]) -> ModelIndex:
        """The metascan as one model (``fused_scans``): :func:`slam6d.model.fused_model` of the
        members' reduced scans at their current poses, in the last member's frame."""
        like = self.registration_model(members[-1])
        return fused_model(
            [self.models.points[k] for k in members],
            [self.poses[k] for k in members],
            like.normal_neighbours,
            like.normal_voxel_size,
            like.backend,
            like.threads,
            like.normal_cell,
            self.config.voxel_size,
        )  # normals per cube at first use, k-NN ones only where a pair needs them

    def _search_centre(self, index: int, start_world: Matrix) -> Matrix:
        """Where the octree search for scan ``index`` is centred: the start (``start_world``), but
        without odometry with the previous scan's attitude instead of the start's.

        The search's angular window (``OctreeSearchConfig.yaw_range``, ±48°, and ``tilt_range``)
        is the turn and tilt a platform may make between two scans. Without odometry the start
        repeats the last turn and the last change of tilt, and the search only runs when ICP from
        that start fitted poorly - which on a hand-held walk is when the turn did *not* repeat:
        the window centred on the repeated turn is then shifted by it, and a turn of the other sense
        falls outside (indoor VLP-16 seed 2, 30 scans: scan 15 predicted 62° off after a 45° turn,
        octree winner 3.6 m / 90° off; scan 29 87° off, winner 1.1 m / 35° off), leaving it to the
        feature guess (FPFH + RANSAC, 1-4 s of CPU per scan with open3d's import). Centred on no
        turn, the window holds any turn up to its range whatever the last one was; a car's steady
        turn (a few degrees a scan) lies well inside it either way. The translation stays the start's:
        the window (±2.4 m) is centred on the repeated step, and a car's 1-3 m step must not
        fall out of it. With odometry the start is the odometry's, centred on as before."""
        if self._odometry_step(index):
            return start_world
        centre = start_world.copy()
        centre[:3, :3] = self.poses[index - 1][:3, :3]
        return centre

    def _loop_model(self, index: int) -> ModelIndex:
        """Scan ``index`` as loop verification matches a revisit against it, in its own frame.

        Where sequential registration fuses (the scan cannot find its planes alone), the scans on
        either side of it fused with it (``fused_scans`` of them, scan ``index`` last, so the union
        lies in its frame); otherwise the scan's own model. Two reasons, both measured on the
        1,000-scan campus (docs/scale.md, "Which revisits close, and what keeps them closed"): one
        VLP-16 scan pairs a revisit's points far more sparsely than the fused metascan registration
        matched against, so its ICP fitness fell under a bar scaled by registration's fitness
        (0.4 x 0.58) on revisits whose relative pose was right to 1-5 cm; and its rings' own planes
        tilt the match (the loops closed were 0.1-0.6° off the true relative tilt), which the
        closing then swings the rest of the path by. Fused, the loop's fitness is measured as the
        bar's scale was.
        """
        count = self.config.fused_scans
        if count <= 1 or not self._needs_fusing(index):
            return self.models.index(index)
        first = min(max(0, index - count // 2), max(0, len(self.sequence) - count))
        members = [k for k in range(first, min(first + count, len(self.sequence))) if k != index] + [index]
        return self._fused_model(members)

    def _guess(self, index: int, start_world: Matrix) -> GuessResult:
        """Octree search against the previous scan (own frame) around :meth:`_search_centre`; returns
        the guess in world coordinates."""
        prev = self.poses[index - 1]
        centre = self._search_centre(index, start_world)
        result = octree_guess(
            self.models.points[index - 1], self.models.points[index], invert(prev) @ centre, self.config.guess
        )
        result.transform = prev @ result.transform
        return result

    def _feature_guess(self, index: int) -> Matrix:
        """The global FPFH + RANSAC guess against the previous scan, in world coordinates."""
        prev = self.poses[index - 1]
        return prev @ feature_guess(self.models.points[index - 1], self.models.points[index]).transform

    def _run_icp(
        self,
        index: int,
        model: ModelIndex,
        world_from_model: Matrix,
        start_world: Matrix,
        config: ICPConfig | None = None,
    ) -> Generator[Event, None, Outcome]:
        """Yield one event per ICP iteration; the generator's return value is the ICPResult (or the error).
        ``config``: the sequential ICP settings unless given."""
        data = self._data_points(index)
        model_from_world = invert(world_from_model)
        iterations: list[ICPIteration] = []
        config = config or self._sequential_config
        # what the scans barely fix keeps the odometry's prediction (the start); without odometry see
        # _motion_prior and PipelineConfig.hold_constraint
        prior = None if self._odometry_step(index) else self._motion_prior(index, model_from_world)
        try:
            tilt = None if self.tilt is None else self.tilt.for_fit(index, world_from_model)
            for iteration in icp_iterations(model, data, model_from_world @ start_world, config, prior, tilt):
                iterations.append(iteration)
                pose = world_from_model @ iteration.transform
                self._set_pose(index, pose, FrameType.ICP)
                yield IcpIterated(index, iteration, pose)
        except RegistrationError as exc:
            return exc
        return ICPResult.from_iterations(iterations, len(data), self._icp_config.method, world_from_model)

    def _motion_prior(self, index: int, model_from_world: Matrix) -> MotionPrior:
        """Where scan ``index`` was and where constant velocity puts it (in the model's frame), and how
        far constant velocity missed the last ``PREDICTION_HISTORY`` registered steps (the largest
        miss, None before any): what a sequential fit without odometry holds the translations its
        pairs barely fix at (:func:`slam6d.icp._held_at`). Every try of the scan gets the same prior,
        also one started from a search's winner: the prior is the motion model's, whatever the start."""
        misses = []
        for k in range(max(2, index - PREDICTION_HISTORY), index):
            if not {k - 2, k - 1, k} & set(self.skipped):
                before, last = self.poses[k - 2], self.poses[k - 1]
                predicted = last @ invert(before) @ last
                misses.append(float(np.linalg.norm(predicted[:3, 3] - self.poses[k][:3, 3])))
        return MotionPrior(
            (model_from_world @ self.poses[index - 1])[:3, 3],
            (model_from_world @ self._start_pose(index))[:3, 3],
            max(misses) if misses else None,
        )

    def _search_first(self, index: int) -> bool:
        """Whether the octree search runs before the first ICP of scan ``index``: always with
        ``octree_guess="always"``; with ``auto`` only when there is neither odometry nor a previous
        motion to extrapolate (the second scan, or the one after a scan that could not be registered).
        Otherwise ICP starts from the prediction and the searches run only if its fit is poor: a
        search costs more than the ICP it spares, and a good prediction is worth more than a search."""
        if self.config.octree_guess != "auto":
            return self.config.octree_guess == "always"
        motion_known = index >= 2 and (index - 1) not in self.skipped
        return not self.has_odometry[index] and not motion_known

    def _recent_fitness(self, index: int, measure: FitMeasure = "fitness") -> list[float]:
        """``measure`` (``fitness`` or ``close_fitness``) of the registered scans among the
        ``FITNESS_HISTORY`` before scan ``index``."""
        recent = (
            getattr(self.summaries[k], measure)
            for k in range(max(1, index - FITNESS_HISTORY), index)
            if k not in self.skipped
        )
        return [value for value in recent if math.isfinite(value)]

    def fitness_bar(self, index: int) -> float:
        """The fitness under which scan ``index``'s ICP counts as poor: ``min_fitness`` until
        ``FITNESS_HISTORY`` scans are registered, then ``relative_fitness`` x the median fitness of
        the last ones (see :class:`PipelineConfig`)."""
        recent = self._recent_fitness(index)
        if len(recent) < FITNESS_HISTORY:
            return self.config.min_fitness
        return self.config.relative_fitness * float(np.median(recent))

    @staticmethod
    def _is_poor(outcome: Outcome, bar: float) -> bool:
        """Whether a sequential fit calls for the searches: it failed, paired under ``bar``, or did not
        converge within its iterations. A run still moving after ``max_iterations`` has not found a
        minimum (indoor VLP-16 seed 2, scan 5: 50 iterations from a prediction 45° off in heading,
        67 cm / 7° off and pairing 0.64 when stopped, where the truth pairs 0.91); the searches find
        one or the best of all the tries is kept anyway."""
        return is_poor(outcome, bar) or (isinstance(outcome, ICPResult) and not outcome.converged)

    def _better_fit(self, index: int, first: Outcome, second: Outcome, bar: float) -> Outcome:
        """The try to keep of two at scan ``index``: one that converged over one still moving when its
        iterations ran out, unless the converged one pairs under ``bar`` (the fitness bar); else
        :func:`slam6d.pair.better_fit` (a success, then more of it close to the model; with
        odometry, the higher fitness).

        A run stopped mid-slide has found no minimum, so its fitness is a snapshot that says nothing
        of where it would settle (:meth:`_is_poor` counts it poor for the same reason). Compared by
        fitness alone, the coarse-to-fine retry of the indoor HDL-32E walk's last scan (seed 2, 30
        scans), started from a prediction 88° off, stopped after 50 iterations 1.4 m / 82° off
        pairing 0.60 and replaced the feature guess's converged fit, 1.1 cm off pairing 0.56 (the
        truth's own fit pairs 0.56 there). But a converged fit under the bar found a poor minimum, and
        one still sliding along a corridor may be centimetres from the truth: the indoor OS1-64 walk
        (seed 2, 30 scans, its files re-rounded by 0.1 mm), scan 21 from a prediction 33° off
        converged 67 cm / 37° off pairing 0.16, while the octree winner's, the feature guess's and
        the coarse retry's runs all ended 5-7 cm / 0.2° off, pairing 0.68, still moving.

        Why fitness with odometry: a searched fit is kept only near the odometry's prediction there
        (:meth:`_near_odometry`), so both tries lie in its basin, where closeness finds nothing the
        fitness misses. Measured on the 1,000-scan campus, closeness changed one choice (scan 46: two
        fits 1.0 cm / 0.06° from the true step, both pairing 0.31), and a revisit of the campus's
        ramp (47, 89), right to 1.8 cm, then failed the loops' 0.15 m rms bar by 0.3 mm
        (docs/robustness.md, "Fits that pair as much in the wrong place")."""
        if isinstance(first, ICPResult) and isinstance(second, ICPResult) and first.converged != second.converged:
            converged = first if first.converged else second
            if converged.fitness >= bar:
                return converged
        return better_fit(first, second, "fitness" if self._odometry_step(index) else "close_fitness")

    def _clearly_under_recent(self, index: int, outcome: Outcome, measure: FitMeasure = "fitness") -> bool:
        """Whether a fit of scan ``index`` that passed the bar still has its ``measure`` (``fitness``
        or ``close_fitness``) under ``RECHECK_SHARE`` of the recent median (any history at all,
        unlike the bar): worth another try."""
        recent = self._recent_fitness(index, measure)
        if isinstance(outcome, RegistrationError) or not recent:
            return False
        return float(getattr(outcome, measure)) < RECHECK_SHARE * float(np.median(recent))

    def _doubtful(self, index: int, outcome: Outcome) -> bool:
        """Whether a fit without odometry that passed the bar still lies clearly less close to the
        model than the recent fits (:attr:`slam6d.icp.ICPResult.close_fitness` under
        ``RECHECK_SHARE`` of theirs): a fit that pairs as much as they did, but in a wrong basin, is
        worth the octree search that a poor fit gets. The case: a hand-held VLP-16 walk indoors, scan
        6 converged from a prediction 37° off at 40 cm / 20° off pairing 0.71 (the true fit 0.69),
        with 0.37 of its points within 5 cm of their planes against 0.49-0.50 for the scans before it
        (docs/robustness.md, "Fits that pair as much in the wrong place"). With odometry the start is
        the odometry's, not a repeated turn, and a searched fit is kept only near it
        (:meth:`_near_odometry`): on the 1,000-scan campus the check searched right fits (its VLP-16
        fits' closeness varies as much as their fitness), for 3 s more and 4.65 cm instead of 4.13."""
        return not self._odometry_step(index) and self._clearly_under_recent(index, outcome, "close_fitness")

    @staticmethod
    def _weak_along_motion(outcome: Outcome) -> bool:
        """Whether a fit's barely fixed translations carry the motion the prediction expects
        (``ICPIteration.weak_along_motion``): its position along its way rests on a few pairs, and so
        does its heading. The case: a car easing out of a turn on open ground (outdoor HDL-32E seed
        2, 30 scans, scan 3), both horizontal translations on 2 % of the pairs, the prediction 3.9°
        off in yaw from the repeated turn; ICP ended 3.8° off pairing 0.50, no fewer than the two fits
        before it (0.50, 0.58), while the truth's fit pairs 0.73 and coarse to fine finds it."""
        return not isinstance(outcome, RegistrationError) and outcome.iterations[-1].weak_along_motion

    def _register(self, index: int) -> Iterator[Event]:
        """ICP from the prediction (odometry, else constant velocity); when it fits poorly (or fails),
        ICP again from the octree winner and then from the feature guess, keeping the best fit.
        Without odometry, a kept fit pairing under ``RECHECK_SHARE`` of the recent ones, or one whose
        barely fixed translations carry the predicted motion, is tried once more from the prediction,
        coarse to fine."""
        began = time.perf_counter()
        cfg = self.config
        start = predicted = self._start_pose(index)
        guess = None
        source = "start"
        if self._search_first(index):
            guess = self._guess(index, start)
            start, source = guess.transform, "octree"
        bar = self.summaries[index].fitness_bar = self.fitness_bar(index)
        model, world_from_model, members = self._model(index)
        yield ScanStarted(index, start.copy(), guess, members, source)
        outcome = yield from self._run_icp(index, model, world_from_model, start)
        tries: list[tuple[str, Outcome]] = [(source, outcome)]
        if (
            (self._is_poor(outcome, bar) or self._doubtful(index, outcome))
            and cfg.octree_guess == "auto"
            and guess is None
        ):
            guess = self._guess(index, start)
            yield ScanStarted(index, guess.transform.copy(), guess, members, "octree")
            second = yield from self._run_icp(index, model, world_from_model, guess.transform)
            tries.append(("octree", second))
            if self._near_odometry(index, predicted, second):
                outcome = self._better_fit(index, outcome, second, bar)
        if self._is_poor(outcome, bar) and cfg.feature_guess and cfg.octree_guess != "never":
            features = self._feature_guess(index)
            yield ScanStarted(index, features.copy(), None, members, "features")
            third = yield from self._run_icp(index, model, world_from_model, features)
            tries.append(("features", third))
            if self._near_odometry(index, predicted, third):
                outcome = self._better_fit(index, outcome, third, bar)
        if not self.has_odometry[index] and (
            self._clearly_under_recent(index, outcome) or self._weak_along_motion(outcome)
        ):
            # Without odometry the prediction repeats the last motion; where that changed (a car
            # easing out of a turn: 4° of yaw), ICP at the sequential max distance alone can settle
            # a few degrees off in a wrong basin that still pairs more than the bar asks, or than the
            # few previous fits did. ICP again from the prediction, coarse to fine, and keep the
            # better fit. Not the first try: on the hand-held indoor walks a 1 m first stage pairs
            # the wrong walls of a room.
            yield ScanStarted(index, predicted.copy(), None, members, "coarse")
            coarse = yield from self._run_icp(index, model, world_from_model, predicted, self._predicted_config)
            tries.append(("coarse", coarse))
            outcome = self._better_fit(index, outcome, coarse, bar)
        self.summaries[index].start = next(name for name, tried in tries if tried is outcome)
        self.summaries[index].starts_tried = [name for name, _ in tries]
        summary = self.summaries[index]
        if isinstance(outcome, RegistrationError):
            # the run goes on from the prediction: the scans after it still register among themselves,
            # and relaxation names the pieces (components) that result
            reason = f"scan {index} ({summary.name}) could not be registered: {outcome}"
            self._set_pose(index, predicted, FrameType.ICP_INACTIVE)
            self._carry_unregistered(index)
            self.registered = index + 1
            self.skipped.append(index)
            summary.registered, summary.failure = False, reason
            summary.octree_guess = guess is not None
            summary.seconds = time.perf_counter() - began
            yield ScanSkipped(index, self.poses[index].copy(), reason)
            return
        self._set_pose(index, outcome.transform, FrameType.ICP)
        self._carry_unregistered(index)
        self.registered = index + 1
        self.links.append((members[-1], index))
        summary.icp_iterations = len(outcome.iterations)
        summary.rms, summary.fitness, summary.converged = outcome.rms, outcome.fitness, outcome.converged
        summary.close_fitness = outcome.close_fitness
        self._measure_constraint(index, model, world_from_model)
        summary.held_translations = outcome.iterations[-1].held
        summary.octree_guess = guess is not None
        summary.seconds = time.perf_counter() - began
        yield ScanRegistered(index, self.poses[index].copy(), outcome)

    def _measure_constraint(self, index: int, model: ModelIndex, world_from_model: Matrix) -> None:
        """Record how strongly the pairs of scan ``index``'s kept fit fix its translation in the
        weakest direction (``ScanSummary.weakest_constraint``, ``weakest_direction`` in the scan's frame).

        The fitness says how much of the scan paired, not whether the pairs fix all six unknowns: a
        corridor fits well while its height rests on a few floor and ceiling points (see
        :func:`slam6d.icp.translation_constraint`), so the report names such scans for the operator."""
        model_from_scan = invert(world_from_model) @ self.poses[index]
        moved = transform_points(model_from_scan, self._data_points(index))
        found, _, _, normals = model.plane_pairs(moved, self._sequential_config.max_distance)
        if len(found) < 6:
            return
        constraint = translation_constraint(moved[found], normals)
        weakest = model_from_scan[:3, :3].T @ constraint.directions[:, 0]
        weakest *= 1.0 if weakest[np.argmax(np.abs(weakest))] > 0 else -1.0  # a direction, not a sign
        summary = self.summaries[index]
        summary.weakest_constraint = float(constraint.values[0])
        summary.weakest_direction = [round(float(v), 4) for v in weakest]

    def _near_odometry(self, index: int, predicted: Matrix, outcome: Outcome) -> bool:
        """Whether a searched start's fit may be kept: always without odometry on both scans (or
        when it failed, which ``better_fit`` never keeps), else only when it ends within the
        odometry's trust of the prediction (``PipelineConfig.odometry_trust_m`` / ``_deg``, plus
        ``ODOMETRY_TRUST_SHARE`` of the odometry step's own length and turn)."""
        if isinstance(outcome, RegistrationError) or not (self.has_odometry[index] and self.has_odometry[index - 1]):
            return True
        step = invert(self.odometry[index - 1]) @ self.odometry[index]
        off = invert(predicted) @ outcome.transform
        shift_limit = self.config.odometry_trust_m + ODOMETRY_TRUST_SHARE * float(np.linalg.norm(step[:3, 3]))
        turn_limit = math.radians(self.config.odometry_trust_deg) + ODOMETRY_TRUST_SHARE * rotation_angle(step[:3, :3])
        return float(np.linalg.norm(off[:3, 3])) <= shift_limit and rotation_angle(off[:3, :3]) <= turn_limit

    def _lever(self) -> float:
        """:func:`slam6d.loops.lever_arm` of the reduced scans, measured once."""
        if self._lever_arm is None:
            self._lever_arm = lever_arm(self.models.points)
        return self._lever_arm

    def _occupancy_of(self, index: int) -> Occupancy:
        if index not in self._occupancy:
            cube = self.config.loop.overlap_cube
            self._occupancy[index] = Octree(self.models.points[index], cube).occupancy(cube)
        return self._occupancy[index]

    def _overlap_at(self, i: int, j: int, transform: Matrix) -> float:
        """Scan j's overlap with scan i at ``transform``, measured as the loop candidates' and the
        sequence's usual overlap are (scan i's occupancy, scan j's model points)."""
        return octree_overlap(self._occupancy_of(i), self.models.points[j], transform)

    def _loop_stage(self) -> Iterator[Event]:
        cfg = self.config.loop
        max_range = self.max_range()
        # the scale of the loop gates: consecutive pairs as registration related them
        fitness = [summary.fitness for summary in self.summaries]
        usual = usual_fit(self.poses, self._occupancy_of, self.models.points, fitness, self.links)
        index = LoopCandidates(self.poses, max_range, cfg)  # rebuilt whenever a closing moves the poses
        last_closed = -(10**9)  # a revisited stretch offers many loops at once: one closing covers them
        registered = [p.copy() for p in self.poses]  # the steps every closing keeps (hold_closed_loops)
        closed: list[LoopHypothesis] = []
        for j in range(2, len(self.sequence)):
            if j - last_closed < cfg.closing_gap:
                continue
            if self._cancel is not None and self._cancel():
                raise Cancelled("run cancelled during loop detection")
            candidates = find_loop_hypotheses(
                self.poses[: j + 1],
                max_range,
                cfg,
                self._occupancy_of,
                self.models.points,
                last_only=1,
                candidates=index,
            )
            tried: list[LoopHypothesis] = []
            for hyp in candidates[: cfg.candidates_per_scan]:
                # the thinned data scan, as in sequential matching: verification runs ICP three times
                tried.append(
                    verify(
                        hyp,
                        self._loop_model(hyp.i),
                        self._data_points(j),
                        self._icp_config,
                        cfg,
                        usual,
                        overlap_at=partial(self._overlap_at, hyp.i, j),
                    )
                )
            if not tried:
                continue
            self.loops.extend(tried)
            yield LoopsDetected(tried)
            accepted = [h for h in tried if h.accepted]
            if accepted and self.config.loop_closing:
                loop = accepted[0]
                before = [p.copy() for p in self.poses]
                closed.append(loop)
                correction = loop_correction(self.poses, loop)
                if self.tilt is not None:  # the measured tilt stays (attitude.heading_only)
                    correction = heading_only(correction, self.poses[loop.j][:3, 3])
                corrected = hold_closed_loops(
                    registered,
                    closed,
                    diffuse_loop_correction(self.poses, loop.i, loop.j, correction),
                    self._lever(),
                    self.tilt,
                )
                displacement = []
                for k, pose in enumerate(corrected):
                    moved = float(np.linalg.norm(pose[:3, 3] - before[k][:3, 3]))
                    displacement.append(moved)
                    if k > loop.i:
                        self._set_pose(k, pose, FrameType.ELCH)
                self.loops_closed.append((loop.i, loop.j))
                last_closed = j
                index = LoopCandidates(self.poses, max_range, cfg)
                yield LoopClosed(loop, displacement)

    def _relax_stage(self) -> Iterator[Event]:
        progress: list[RelaxationProgressed] = []

        def record(iteration: int, residual: float, moved: list[int]) -> None:
            progress.append(RelaxationProgressed(iteration, residual, moved))

        share_registration_models(self.models, self.config, self.config.relaxation, self.registration_model)
        # the graph method relaxes over the trajectory and the loops this run accepted
        edges = trajectory_graph(
            len(self.sequence), [GraphEdge(h.i, h.j, h.transform) for h in self.loops if h.accepted]
        )

        def relax(fixed: tuple[int, ...], members: list[int] | None = None) -> RelaxationResult:
            return relax_poses(
                self.config.relaxation,
                self.models,
                self.poses,
                edges,
                fixed=fixed,
                config=self.config.relax,
                progress=record,
                cancel=self._cancel,
                members=members,
                links=self.links,  # a sequential registration is an edge, however sparse the overlap
                scheduler=self.scheduler,
                tilt=self.tilt if self.config.relaxation != "simultaneous" else None,
            )

        disconnected: DisconnectedGraphError | None = None
        try:
            result = relax(fixed=(0,))
        except DisconnectedGraphError as error:
            disconnected = error
            self.components = error.components
            result = self._relax_components(relax, error.components)
        self.relaxation_result = result
        flag = FrameType.LUM if self.config.relaxation in ("lum", "graph") else FrameType.ICP
        for k, pose in enumerate(result.poses):
            self._set_pose(k, pose, flag)
        yield from progress
        if not progress:
            yield RelaxationProgressed(result.iterations, result.residual_after, [])
        if disconnected is not None:  # each part is relaxed, but they are not one map: the stage failed
            raise disconnected

    def _relax_components(
        self,
        relax: Callable[..., RelaxationResult],
        components: list[list[int]],
    ) -> RelaxationResult:
        """Relax every connected component of more than one scan on its own, anchored at its first scan.

        Scans of the other components keep their poses (the relaxation would otherwise carry them along
        with the correction of the scan before them). A component that cannot be relaxed (e.g. a
        singular graph) keeps its poses too. The residuals reported are RMS over the relaxed components.
        """
        poses = [p.copy() for p in self.poses]
        parts: list[RelaxationResult] = []
        for component in components:
            if len(component) < 2:
                continue
            try:
                part = relax(fixed=(component[0],), members=component)
            except Cancelled:
                raise
            except RelaxationError:
                continue
            for k in component:
                poses[k] = part.poses[k]
            parts.append(part)

        def combined(values: list[tuple[float | None, int]]) -> float:
            known = [(v, n) for v, n in values if v is not None and np.isfinite(v) and n > 0]
            total = sum(n for _, n in known)
            return float(np.sqrt(sum(v * v * n for v, n in known) / total)) if total else float("nan")

        sizes = [max(len(part.neighbours), 1) for part in parts]
        return RelaxationResult(
            poses=poses,
            residual_before=combined([(part.residual_before, n) for part, n in zip(parts, sizes, strict=True)]),
            residual_after=combined([(part.residual_after, n) for part, n in zip(parts, sizes, strict=True)]),
            iterations=max((part.iterations for part in parts), default=0),
            method=self.config.relaxation,
            neighbours=[pair for part in parts for pair in part.neighbours],
            chi2_before=None,
            chi2_after=None,
            seconds=sum(part.seconds for part in parts),
        )

    def _make_report(self) -> PipelineReport:
        r = self.relaxation_result
        return PipelineReport(
            scans=len(self.sequence),
            stage_seconds=dict(self.stage_seconds),
            loops=list(self.loops),
            loops_closed=list(self.loops_closed),
            relaxation=self.config.relaxation,
            residual_before=r.residual_before if r else None,
            residual_after=r.residual_after if r else None,
            chi2_before=r.chi2_before if r else None,
            chi2_after=r.chi2_after if r else None,
            relaxation_iterations=r.iterations if r else 0,
            neighbour_pairs=len(r.neighbours) if r else 0,
            max_range=self.max_range(),
            peak_memory_bytes=peak_memory_bytes(),
            settings=to_jsonable(self.config),
            scan_summaries=list(self.summaries),
            registered_scans=self.registered - len(self.skipped),
            skipped_scans=list(self.skipped),
            failure=self.failure,
            components=[list(c) for c in self.components],
        )


def holds_inclinometer(config: PipelineConfig, has_odometry: Sequence[bool]) -> bool:
    """Whether registration, relaxation and loop closing hold the scans' tilt to the odometry's
    readings: ``config.tilt_noise_deg`` declares an inclinometer and some scan's file carried a pose."""
    return config.tilt_noise_deg is not None and any(has_odometry)


def inclinometer_prior(config: PipelineConfig, odometry: list[Matrix], has_odometry: list[bool]) -> TiltPrior | None:
    """The odometry's roll and pitch as an inclinometer's readings (:class:`slam6d.attitude.TiltPrior`)
    where ``config.tilt_noise_deg`` says the odometry carries one and some scan has odometry; None
    otherwise. Every scan is weighed as one finding its planes alone until
    :func:`registration_tilt_deg` says how it was registered."""
    noise = config.tilt_noise_deg
    if noise is None or not holds_inclinometer(config, has_odometry):
        return None
    return TiltPrior.from_poses(odometry, has_odometry, noise, config.registration_tilt_deg)


def registration_model(shared: ModelIndex, config: PipelineConfig) -> ModelIndex:
    """A scan's sequential-matching model over its reduced points' ``shared`` model (same kd-tree):
    per-cube normals over cubes of ``normal_cell_voxels`` x ``voxel_size`` and a plane sample of one
    point per ``sample_voxels`` x ``voxel_size`` cube, where those are set; ``shared`` itself otherwise."""
    cell = config.normal_cell_voxels * config.voxel_size
    if cell <= 0 or len(shared.plane_indices) != len(shared.points):
        return shared
    return ModelIndex(
        shared.points,
        normal_neighbours=shared.normal_neighbours,
        normal_voxel_size=config.sample_voxels * config.voxel_size,
        backend=shared.backend,
        threads=shared.threads,
        normal_cell=cell,
        index=shared.index,
        viewpoint=np.zeros(3),  # reduced scans stay in their own frame: the scanner at the origin
    )


def share_registration_models(
    models: ScanModels, config: PipelineConfig, method: str, registration: Callable[[int], ModelIndex] | None = None
) -> None:
    """Let ``method``'s rounds pair against each scan's registration model (per-cube normals, a
    plane sample of ``sample_voxels``) instead of the k-NN normals of its whole reduced scan: for
    ``lum`` with ``relax_registration_models``, the one choice of ``slam6d run``'s relaxation,
    ``slam6d relax`` and the workbench's Relax. ``registration(k)`` is scan k's model where it is
    built already (a run's, from registration); else it is built here over ``models.index(k)``
    (same kd-tree), every normal estimated as registration estimates them.

    Relaxing again has to pair as the run did: on a VLP-16's rings the k-NN normals are poor, and
    LUM against them moved the 250-scan campus's run (ATE 3.48 cm) to 15.6 cm, against the
    registration models to 2.6 cm (docs/scale.md, "Relaxing a registered session again").
    ``graph`` and ``simultaneous`` match by ICP and only report residuals against these models,
    which the run never changed for them either."""
    if method != "lum" or not config.relax_registration_models:
        return
    for k in range(len(models)):
        if registration is not None:
            model = registration(k)
        else:
            model = registration_model(models.index(k), config)
            model.plane_normals()
        if model is not models.index(k):
            models.share_plane_model(k, model)


def needs_fusing(model: ModelIndex) -> bool:
    """Whether a scan whose registration model is ``model`` leaves its planes to the scans' rings:
    its smallest cubes hold a plane for fewer than ``FUSE_BELOW_CUBE_SHARE`` of its plane sample (a
    multi-beam lidar outdoors)."""
    share = model.smallest_cube_share
    return share is not None and share < FUSE_BELOW_CUBE_SHARE


def fuses_scans(config: PipelineConfig, index: int, needs: Callable[[int], bool]) -> bool:
    """Whether sequential matching registers scan ``index`` against the last ``fused_scans`` scans
    fused into one model: metascan matching, and the scan before it leaves its planes to its rings
    (``needs(index - 1)``, :func:`needs_fusing` of that scan's registration model)."""
    return config.matching != "pairwise" and config.fused_scans > 1 and index >= 2 and needs(index - 1)


def registration_tilt_deg(config: PipelineConfig, fused: bool) -> float:
    """What the tilt of a scan's registration is worth per step (:mod:`slam6d.attitude`): matched
    against fused scans or finding its planes alone."""
    return config.fused_registration_tilt_deg if fused else config.registration_tilt_deg


def reduce_scan(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """One real point per ``voxel_size`` cube (0 = every point): the copy every stage works on."""
    return points if voxel_size <= 0 else points[reduce_points(points, voxel_size)]


def reduce_stored_scan(directory: str, index: int, voxel_size: float) -> np.ndarray:
    """:func:`reduce_scan` of scan ``index`` of the store at ``directory``, read where this runs
    (a cluster worker reads the store itself instead of receiving the full cloud)."""
    return reduce_scan(ScanStore(directory, budget=2**62).points(index), voxel_size)


def write_results(pipeline: Pipeline, out_dir: Path | str, extra: dict[str, Any] | None = None) -> dict[str, Path]:
    """Write ``poses_kitti.txt`` (input units and frame), one ``.frames`` per scan, and ``report.json``."""
    from slam6d.io.poses import write_kitti_poses

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    convention = pipeline.sequence.convention
    poses_path = out / "poses_kitti.txt"
    write_kitti_poses(poses_path, [convention.pose_to_native(p) for p in pipeline.poses])
    write_sequence_frames(out, pipeline.history, convention)
    report = to_jsonable(pipeline.report) if pipeline.report is not None else {}
    report["convention"] = convention.name
    if extra:
        report.update(to_jsonable(extra))
    report_path = out / "report.json"
    write_trace(report_path, report)
    return {"poses": poses_path, "report": report_path}
