"""Global relaxation by name: the one call behind ``slam6d run --relaxation``, ``slam6d relax`` and the workbench.

=================  ==========================================================================
name               what it does
=================  ==========================================================================
``lum``            :func:`slam6d.lum.lum_relaxation`: one joint point-to-plane step per round
                   over every overlapping pair (found from the scans, not from a graph)
``graph``          :func:`slam6d.graph_relaxation.graph_relaxation`: ICP per edge of a given
                   graph (sequential, accepted loops, edges added by hand), then a pose-graph solve
``simultaneous``   :func:`slam6d.simultaneous.simultaneous_matching`: the seed's queue of ICP
                   matches of each scan against the union of its overlapping neighbours
=================  ==========================================================================

Every caller builds its scan models with :func:`reduced_models` (the pipeline's reduction and
ICP settings), so the same poses, graph and ``[engine]`` settings relax to the same poses whether
the command line or the workbench asks.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from slam6d.attitude import TiltPrior
from slam6d.errors import Slam6dError
from slam6d.geometry import Matrix
from slam6d.graph_relaxation import GraphEdge, graph_relaxation
from slam6d.icp import FloatArray, ICPConfig
from slam6d.lum import lum_relaxation
from slam6d.octree import reduce_points
from slam6d.posegraph import connected_components
from slam6d.relax import Progress, RelaxationConfig, RelaxationResult, ScanModels, neighbour_graph
from slam6d.simultaneous import simultaneous_matching

if TYPE_CHECKING:
    from slam6d.scheduler import Scheduler

RELAXATION_METHODS = ("lum", "graph", "simultaneous")

__all__ = ["RELAXATION_METHODS", "models_icp_config", "reduced_models", "relax_poses", "relaxation_components"]


def models_icp_config(icp: ICPConfig, voxel_size: float) -> ICPConfig:
    """ICP settings for scans reduced to ``voxel_size`` already: no further data thinning, and the
    plane sample is every point (sharing the scan's kd-tree) when the normal voxel is no coarser."""
    config = replace(icp, data_voxel_size=0.0)
    if 0 < config.normal_voxel_size <= voxel_size:
        config = replace(config, normal_voxel_size=0.0)
    return config


def reduced_models(points: Sequence[FloatArray], voxel_size: float, icp: ICPConfig) -> ScanModels:
    """Each scan reduced to one real point per ``voxel_size`` cube, as the pipeline reduces its models."""
    reduced = [p[reduce_points(p, voxel_size)] if voxel_size > 0 else p for p in points]
    return ScanModels(reduced, models_icp_config(icp, voxel_size))


def relax_poses(
    method: str,
    models: ScanModels,
    poses: Sequence[Matrix],
    edges: Sequence[GraphEdge] = (),
    fixed: Iterable[int] = (0,),
    config: RelaxationConfig = RelaxationConfig(),
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    edge_progress: Callable[[int, int], None] | None = None,
    members: Iterable[int] | None = None,
    links: Iterable[tuple[int, int]] = (),
    scheduler: Scheduler | None = None,
    tilt: TiltPrior | None = None,
) -> RelaxationResult:
    """Relax ``poses`` with the method named (table above); ``edges`` is the graph ``graph`` relaxes over.

    ``members`` restricts the relaxation to those scans (one connected component; the others keep
    their poses); ``links`` are pairs registered to each other (a sequential registration), kept as
    neighbours by ``lum`` and ``simultaneous`` however little they overlap (``graph`` has them as
    edges already). ``progress(round, residual, moved)`` after each round; ``edge_progress(done,
    total)`` after each edge's ICP (``graph`` only); :class:`~slam6d.errors.Cancelled` when
    ``cancel()`` turns true. A ``scheduler`` (:mod:`slam6d.scheduler`) spreads ``lum``'s per-scan
    blocks over a cluster; the other methods run here. ``tilt`` (:class:`slam6d.attitude.TiltPrior`,
    an inclinometer's readings) is a prior on each scan's roll and pitch in ``lum`` and ``graph``;
    ``simultaneous`` refuses it rather than ignore a measurement it was handed.
    """
    fixed = list(fixed)
    current = [np.asarray(p, dtype=np.float64) for p in poses]
    links = list(links)
    if method == "lum":
        return lum_relaxation(
            models,
            current,
            fixed=fixed,
            config=config,
            members=members,
            progress=progress,
            cancel=cancel,
            links=links,
            scheduler=scheduler,
            tilt=tilt,
        )
    if tilt is not None and method == "simultaneous":
        raise Slam6dError(
            "relaxation 'simultaneous' has no tilt prior; the inclinometer's readings need 'lum' or 'graph'"
        )
    if method == "simultaneous":
        return simultaneous_matching(
            models, current, fixed=fixed, config=config, members=members, progress=progress, cancel=cancel, links=links
        )
    if method == "graph":
        if members is not None:  # the other scans hold still, and only the component's own edges count
            chosen = set(members)
            fixed = sorted(set(fixed) | (set(range(len(current))) - chosen))
            edges = [e for e in edges if e.i in chosen and e.j in chosen]
        return graph_relaxation(models, current, edges, fixed, config, progress, cancel, edge_progress, tilt)
    raise Slam6dError(f"unknown relaxation '{method}'; known: {', '.join(RELAXATION_METHODS)}")


def relaxation_components(
    method: str,
    models: ScanModels | None,
    poses: Sequence[Matrix],
    edges: Sequence[GraphEdge] = (),
    config: RelaxationConfig = RelaxationConfig(),
    links: Iterable[tuple[int, int]] = (),
) -> list[list[int]]:
    """The connected components of the graph ``method`` would relax over at ``poses`` (scans sorted,
    components ordered by their first scan; one component when relaxation can tie every scan together).

    ``graph`` relaxes over ``edges``; ``lum`` and ``simultaneous`` over the overlapping pairs they
    find at the current poses (:func:`slam6d.relax.neighbour_graph` with the relaxation's own
    criterion and bound) plus ``links``. These are the components a relaxation refuses (or relaxes
    one by one in ``slam6d run``), so an operator can see before relaxing which pieces need a bridge.
    ``models`` may be None for ``graph``, which needs no scan (a caller spares building them).
    """
    if method == "graph":
        pairs = [(e.i, e.j) for e in edges]
    elif method in ("lum", "simultaneous"):
        if models is None:
            raise Slam6dError(f"{method} finds its graph from the scans: their models are needed")
        found = neighbour_graph(models, poses, config.min_pairs, links=links, per_scan=config.neighbours_per_scan).pairs
        pairs = [(p.i, p.j) for p in found]
    else:
        raise Slam6dError(f"unknown relaxation '{method}'; known: {', '.join(RELAXATION_METHODS)}")
    return connected_components(len(poses), pairs)
