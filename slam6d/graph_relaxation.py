"""Relaxation over a given pose graph: ICP per edge, then one pose-graph solve, in rounds.

The third relaxation method beside :func:`slam6d.lum.lum_relaxation` (one joint point-to-plane
step over every overlapping pair, no ICP per edge) and :func:`slam6d.simultaneous.simultaneous_matching`.
Here the edges are not found from overlap but given: the trajectory's sequential edges, the loops a
run (or a person) accepted, and edges added by hand, minus the ones deleted. That is what the
workbench edits, and what ``slam6d run --relaxation graph`` builds from its own run. Each round
matches every edge by ICP (:func:`slam6d.lum.match_edge`, with LUM's information matrix from the
point pairs; in the first round a loop starts from its stored ICP transform, so the loop's drift is
what the solve distributes) and then solves all poses at once (:func:`slam6d.posegraph.optimize_pose_graph`);
rounds repeat from the new poses until no scan moves more than ``config.tolerance``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from slam6d.attitude import TiltPrior
from slam6d.errors import RegistrationError, RelaxationError
from slam6d.geometry import Matrix, invert
from slam6d.lum import match_edge, pair_information
from slam6d.posegraph import check_connected, optimize_pose_graph
from slam6d.relax import (
    NeighbourPair,
    Progress,
    RelaxationConfig,
    RelaxationResult,
    ScanModels,
    check_cancel,
    measured_result,
    pair_residual,
)

__all__ = ["GraphEdge", "graph_information", "graph_relaxation", "trajectory_graph"]


@dataclass(frozen=True)
class GraphEdge:
    """Scans i and j should agree; ``transform`` (scan j in scan i's frame, as ICP found it) starts a loop's match."""

    i: int
    j: int
    transform: Matrix | None = None


def trajectory_graph(count: int, loops: Iterable[GraphEdge] = ()) -> list[GraphEdge]:
    """The sequential edges of a trajectory of ``count`` scans, then ``loops``."""
    return [GraphEdge(k, k + 1) for k in range(count - 1)] + list(loops)


def graph_relaxation(
    models: ScanModels,
    poses: Sequence[Matrix],
    edges: Sequence[GraphEdge],
    fixed: Iterable[int] = (0,),
    config: RelaxationConfig = RelaxationConfig(),
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    edge_progress: Callable[[int, int], None] | None = None,
    tilt: TiltPrior | None = None,
) -> RelaxationResult:
    """Relax ``poses`` over ``edges`` (module docstring); ``fixed`` scans stay where they are.
    ``tilt``: the scans' measured up (an inclinometer), a prior on each pose's roll and pitch in
    every solve (:func:`slam6d.posegraph.optimize_pose_graph`).

    ``progress(round, chi², moved)`` after each round, ``edge_progress(done, total)`` after each
    edge's ICP; :class:`~slam6d.errors.Cancelled` when ``cancel()`` turns true. Refuses with
    :class:`RelaxationError` a graph in which some scan is not tied to a fixed one, and an edge
    whose scans no longer match.
    """
    began = time.perf_counter()
    fixed = sorted(set(fixed))
    check_connected(len(poses), [(e.i, e.j) for e in edges], fixed)
    pairs = [NeighbourPair(e.i, e.j, 0) for e in edges]
    current = [np.array(p, dtype=np.float64) for p in poses]
    residual_before = pair_residual(models, current, pairs)
    chi2: list[float] = []
    rounds = 0
    total = config.max_rounds * len(edges)
    for rounds in range(1, config.max_rounds + 1):
        measured = []
        for n, edge in enumerate(edges):
            check_cancel(cancel)
            placed = list(current)
            if rounds == 1 and edge.transform is not None:
                placed[edge.j] = current[edge.i] @ np.asarray(edge.transform)
            try:
                measured.append(match_edge(models, placed, NeighbourPair(edge.i, edge.j, 0), config))
            except RegistrationError as exc:
                raise RelaxationError(f"graph relaxation: scans {edge.i} and {edge.j} no longer match: {exc}") from exc
            if edge_progress is not None:
                edge_progress((rounds - 1) * len(edges) + n + 1, total)
        result = optimize_pose_graph(current, measured, fixed=fixed, max_iterations=20, tilt=tilt)
        if not result.converged and not np.isfinite(result.residual_after):
            raise RelaxationError("the pose-graph solver did not converge")
        chi2.append(result.residual_after)
        shifts = [float(np.linalg.norm(a[:3, 3] - b[:3, 3])) for a, b in zip(result.poses, current, strict=True)]
        current = [np.asarray(p) for p in result.poses]
        if progress is not None:
            progress(rounds, result.residual_after, [k for k, s in enumerate(shifts) if s > config.tolerance])
        if max(shifts) <= config.tolerance:
            break
    return measured_result(models, pairs, current, residual_before, rounds, "graph", began, chi2)


def graph_information(
    models: ScanModels, poses: Sequence[Matrix], edges: Sequence[GraphEdge], config: RelaxationConfig
) -> list[Matrix]:
    """Per edge, LUM's information matrix of the relative pose at ``poses`` (canonical frame), without re-matching:
    how well the scans' overlap pins that edge down, as a g2o export states it."""
    return [
        pair_information(models, NeighbourPair(e.i, e.j, 0), invert(poses[e.i]) @ poses[e.j], config) for e in edges
    ]
