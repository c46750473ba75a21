"""The seed's simultaneous matching: each scan re-matched by ICP against the union of its neighbours.

A queue starts at the first scan of the loop; each scan taken from it is re-matched by ICP against
the union of its neighbours (the neighbour graph of :mod:`slam6d.relax`: more than ``min_pairs``
point pairs), and when it moves by more than ``move_threshold`` its neighbours are queued again.
The first scan stays fixed. Residuals before and after sample every neighbour pair evenly
(:func:`slam6d.relax.pair_residual`).
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence

import numpy as np
from numpy.typing import NDArray

from slam6d import nn
from slam6d.errors import RegistrationError, RelaxationError
from slam6d.geometry import Matrix, transform_points
from slam6d.icp import icp
from slam6d.model import ModelIndex
from slam6d.relax import (
    FloatArray,
    Progress,
    RelaxationConfig,
    RelaxationResult,
    ScanModels,
    adjacency,
    carry_forward,
    check_cancel,
    check_graph,
    measured_result,
    pair_residual,
    set_up,
)

__all__ = ["UnionIndex", "simultaneous_matching"]


class UnionIndex(ModelIndex):
    """Several scans placed in the world as one model (a metascan, or a scan's neighbours).

    Built from the members' own plane samples and normals (estimated once per scan, in its own
    frame, and only rotated here): a union is rebuilt for every scan registered against it, and
    re-estimating normals over the union each time cost several times more than the matching.
    Normals from one scan's points are also not blurred by a misalignment between the members.
    """

    def __init__(self, models: ScanModels, members: Sequence[int], poses: Sequence[Matrix]) -> None:
        self.members = list(members)
        parts = [models.index(k) for k in self.members]
        super().__init__(
            np.concatenate([transform_points(poses[k], models.points[k]) for k in self.members]),
            normal_neighbours=models.config.normal_neighbours,
            normal_voxel_size=models.config.normal_voxel_size,
            backend=models.config.nn_backend,
            threads=models.config.threads,
        )
        offsets = np.cumsum([0] + [len(models.points[k]) for k in self.members])
        samples, normals, usable = [], [], []
        for k, part in zip(self.members, parts, strict=True):
            points, part_normals, part_usable = part.plane_normals()
            samples.append(transform_points(poses[k], points))
            normals.append(part_normals @ np.asarray(poses[k])[:3, :3].T)
            usable.append(part_usable)
        self._sample_indices = np.concatenate([o + p.plane_indices for o, p in zip(offsets, parts, strict=False)])
        self._sample_normals = np.concatenate(normals)
        self._sample_usable = np.concatenate(usable)
        self._sample_index = nn.build_index(np.concatenate(samples), self.backend, self.threads)

    @property
    def plane_indices(self) -> NDArray[np.int64]:
        return self._sample_indices

    @property
    def plane_index(self) -> nn.NeighbourIndex:
        return self._sample_index

    def plane_normals_for(self, sample: NDArray[np.int64]) -> tuple[FloatArray, NDArray[np.bool_]]:
        sample = np.asarray(sample, dtype=np.int64)
        return self._sample_normals[sample], self._sample_usable[sample]

    def plane_normals(self) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        return self._sample_index.points, self._sample_normals, self._sample_usable


def simultaneous_matching(
    models: ScanModels,
    poses: Sequence[Matrix],
    fixed: Iterable[int] = (0,),
    config: RelaxationConfig = RelaxationConfig(),
    members: Iterable[int] | None = None,
    start: int | None = None,
    progress: Progress | None = None,
    cancel: Callable[[], bool] | None = None,
    links: Iterable[tuple[int, int]] = (),
) -> RelaxationResult:
    """The seed's simultaneous matching over the scans ``members`` (default all), see the module docstring."""
    began = time.perf_counter()
    before, current, chosen, fixed_set, pairs = set_up(models, poses, fixed, members, config, links)
    check_graph(models, pairs, fixed_set, chosen)
    adjacent = adjacency(pairs, len(models))
    residual_before = pair_residual(models, current, pairs)
    first = start if start is not None else min(chosen)
    order = [k for k in chosen if k >= first] + [k for k in chosen if k < first]
    queue = deque(k for k in order if k not in fixed_set)
    queued = set(queue)
    pops = 0
    limit = config.max_rounds * len(chosen)
    while queue and pops < limit:
        check_cancel(cancel)
        k = queue.popleft()
        queued.discard(k)
        pops += 1
        if not adjacent[k]:
            continue
        union = UnionIndex(models, adjacent[k], current)
        try:
            result = icp(union, models.points[k], current[k], models.config)
        except RegistrationError as exc:
            raise RelaxationError(f"simultaneous matching: scan {k} no longer matches its neighbours: {exc}") from exc
        sample = models.thinned(k, 500)
        moved = float(
            np.linalg.norm(
                transform_points(result.transform, sample) - transform_points(current[k], sample), axis=1
            ).max()
        )
        current[k] = result.transform
        requeued = []
        if moved > config.move_threshold:
            for n in adjacent[k]:
                if n not in fixed_set and n not in queued:
                    queue.append(n)
                    queued.add(n)
                    requeued.append(n)
        if progress is not None:
            progress(pops, result.rms, [k])
    after = carry_forward(before, current, chosen)
    return measured_result(models, pairs, after, residual_before, pops, "simultaneous", began)
