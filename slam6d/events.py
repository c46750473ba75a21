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
    "ScanStarted",
    "ScanSummary",
]


@dataclass
class ScanStarted:
    index: int
    initial: Matrix  # world_from_scan ICP starts from
    guess: GuessResult | None
    model_indices: list[int]


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
    converged: bool = False
    octree_guess: bool = False
    seconds: float = 0.0


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


@dataclass
class Finished:
    report: PipelineReport


Event = ScanStarted | IcpIterated | ScanRegistered | LoopsDetected | LoopClosed | RelaxationProgressed | Finished
