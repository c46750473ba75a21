"""What a pipeline run tells as it goes: one event per step, and the report at the end.

:meth:`slam6d.pipeline.Pipeline.step` returns one of these per call, carrying everything the
step computed (the ICP iteration with its pose, pair count and RMS; the octree guess with its
candidates; the loop hypotheses; the relaxation's residual), so a viewer can replay a run
without recomputing geometry. :class:`PipelineReport` is what ``report.json`` holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from slam6d.geometry import Matrix
from slam6d.icp import ICPIteration, ICPResult
from slam6d.initial_guess import GuessResult
from slam6d.loops import LoopHypothesis

__all__ = [
    "Event",
    "Finished",
    "IcpIterated",
    "LoopClosed",
    "LoopsDetected",
    "PipelineReport",
    "RelaxationProgressed",
    "ScanRegistered",
    "ScanSkipped",
    "ScanStarted",
    "ScanSummary",
    "StageFailure",
]


@dataclass
class ScanStarted:
    index: int
    initial: Matrix  # world_from_scan ICP starts from
    guess: GuessResult | None
    model_indices: list[int]
    source: str = "start"  # where ``initial`` came from: start (prediction), octree, features or coarse
    # (the prediction again, ICP coarse to fine)


@dataclass
class IcpIterated:
    index: int
    iteration: ICPIteration
    pose: Matrix  # world_from_scan after this iteration


@dataclass
class ScanRegistered:
    index: int
    pose: Matrix
    result: ICPResult


@dataclass
class ScanSkipped:
    """Scan ``index`` could not be registered (no start led ICP to enough point pairs); it keeps its
    predicted ``pose`` and the next scans are registered on from it, so the run goes on and the map
    falls apart into pieces the operator can bridge, instead of stopping."""

    index: int
    pose: Matrix
    reason: str


@dataclass
class LoopsDetected:
    hypotheses: list[LoopHypothesis]


@dataclass
class LoopClosed:
    loop: LoopHypothesis
    displacement: list[float]  # per scan, metres moved by the error diffusion


@dataclass
class RelaxationProgressed:
    iteration: int
    residual: float
    moved: list[int]


@dataclass
class ScanSummary:
    index: int
    name: str
    points: int
    reduced_points: int
    icp_iterations: int = 0
    rms: float = float("nan")
    fitness: float = float("nan")
    fitness_bar: float = float("nan")  # under it the fit counted as poor and the searches ran (Pipeline.fitness_bar)
    close_fitness: float = float("nan")  # share of its points close to the model's planes (ICPResult.close_fitness)
    converged: bool = False
    octree_guess: bool = False
    seconds: float = 0.0
    start: str = "start"  # the start the kept ICP result came from: start (prediction), octree or features
    starts_tried: list[str] = field(default_factory=list)
    registered: bool = True  # False: no start gave ICP enough pairs; the scan kept its predicted pose
    # how strongly the kept fit's pairs fix its translation in the weakest direction (0 none, 1 every
    # pair: slam6d.icp.translation_constraint) and that direction, a unit vector in the scan's own frame
    weakest_constraint: float = float("nan")
    weakest_direction: list[float] = field(default_factory=list)
    held_translations: int = 0  # of them held where the motion puts them (PipelineConfig.hold_constraint)
    failure: str = ""  # why it was not registered


@dataclass
class StageFailure:
    """Why a run stopped early: the stage that failed (``registration``, ``loops``, ``relaxation``),
    the error's message and class. The poses of the stages before it are kept and written."""

    stage: str
    reason: str
    error: str


@dataclass
class PipelineReport:
    scans: int
    stage_seconds: dict[str, float]
    loops: list[LoopHypothesis]  # verified hypotheses (accepted or not)
    loops_closed: list[tuple[int, int]]
    relaxation: str
    residual_before: float | None  # RMS point-to-plane distance over neighbour pairs, metres
    residual_after: float | None
    chi2_before: float | None
    chi2_after: float | None
    relaxation_iterations: int
    neighbour_pairs: int
    max_range: float
    settings: dict[str, Any]
    peak_memory_bytes: int = 0  # the process's peak resident memory when the run finished
    scan_summaries: list[ScanSummary] = field(default_factory=list)
    registered_scans: int = 0  # scans placed by sequential registration (all of them unless it failed)
    skipped_scans: list[int] = field(default_factory=list)  # scans no start could register (see ScanSkipped)
    failure: StageFailure | None = None  # None when every stage finished
    # connected components of the relaxation's graph when it had more than one, each relaxed on its own
    components: list[list[int]] = field(default_factory=list)


@dataclass
class Finished:
    report: PipelineReport


Event = (
    ScanStarted
    | IcpIterated
    | ScanRegistered
    | ScanSkipped
    | LoopsDetected
    | LoopClosed
    | RelaxationProgressed
    | Finished
)
