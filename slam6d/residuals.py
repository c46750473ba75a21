"""How well scans joined by pose-graph edges agree: the residual measures every edit is judged by.

The workbench compares a :class:`ResidualSummary` before and after every edit that moves scans and
warns (:func:`residual_jump`) when it clearly got worse; the 3D view colours each edge by its
:func:`plane_residual`; relaxation and loop closing report :func:`displacements`. They are engine
functions so a script, a benchmark and the workbench measure the same thing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from slam6d.geometry import Matrix, invert, transform_points
from slam6d.icp import FloatArray
from slam6d.model import ModelIndex
from slam6d.relax import ScanModels
from slam6d.trace import to_jsonable

# An edit "makes residuals jump" when the summary RMS grows by this factor and by at least this
# many metres, or when the paired fraction of the edges drops by more than RESIDUAL_JUMP_OVERLAP.
RESIDUAL_JUMP_FACTOR = 1.5
RESIDUAL_JUMP_METRES = 0.02
RESIDUAL_JUMP_OVERLAP = 0.15

__all__ = [
    "RESIDUAL_JUMP_FACTOR",
    "RESIDUAL_JUMP_METRES",
    "RESIDUAL_JUMP_OVERLAP",
    "ResidualSummary",
    "displacements",
    "plane_residual",
    "residual_jump",
    "residual_summary",
]


@dataclass
class ResidualSummary:
    """How well the scans joined by graph edges agree: closest-point RMS and paired fraction."""

    rms: float  # metres, over all pairs of all edges within ``max_distance``
    paired: float  # mean over edges of the fraction of data points with a partner
    edges: list[dict[str, float]]  # per edge: i, j, rms, paired, plane
    max_distance: float

    def as_dict(self) -> dict[str, Any]:
        return to_jsonable(self.__dict__)


def plane_residual(model: ModelIndex, data: FloatArray, max_distance: float) -> float:
    """Upper quartile of the point-to-plane distances of ``data`` (in the model's frame) to ``model``,
    over the points with a partner within ``max_distance``.

    This tells a good edge from a bad one on any scan density: closest-point distances between well
    aligned scans still grow with the point spacing and with the parts that do not overlap (on the
    demo session 0.33 m aligned against 0.38 m at the odometry), while the distance along the
    surface normal stays near the range noise (1 cm there, 6-10 cm at the odometry). The upper
    quartile rather than the median: a scan slid sideways over flat ground keeps its ground points
    on the ground plane, and those can be half of a scan. NaN where no point of ``data`` has a
    partner with a usable normal.
    """
    distances = np.abs(model.plane_residuals(data, max_distance))
    return float(np.percentile(distances, 75)) if len(distances) else float("nan")


def residual_summary(
    models: ScanModels, poses: Sequence[Matrix], edges: Sequence[tuple[int, int]], sample: int = 1500
) -> ResidualSummary:
    """Per edge, scan j's thinned points against scan i's; pairs count within 4x the ICP max distance.

    The wider reach keeps the RMS meaningful after a bad edit: with the ICP distance itself, a scan
    dragged a metre away would simply lose its pairs and its RMS would look no worse.
    """
    reach = 4.0 * models.config.max_distance
    total, count, per_edge = 0.0, 0, []
    for i, j in edges:
        data = transform_points(invert(poses[i]) @ poses[j], models.thinned(j, sample))
        dist, idx = models.index(i).nearest(data, reach)
        ok = idx >= 0
        squares = float(np.sum(dist[ok] ** 2))
        total += squares
        count += int(ok.sum())
        per_edge.append(
            {
                "i": i,
                "j": j,
                "rms": float(np.sqrt(squares / ok.sum())) if ok.any() else float("nan"),
                "paired": float(ok.mean()) if len(ok) else 0.0,
                "plane": plane_residual(models.index(i), data, models.config.max_distance),
            }
        )
    rms = float(np.sqrt(total / count)) if count else float("nan")
    paired = float(np.mean([e["paired"] for e in per_edge])) if per_edge else 0.0
    return ResidualSummary(rms, paired, per_edge, reach)


def residual_jump(before: ResidualSummary, after: ResidualSummary) -> str | None:
    """A warning naming the worst edge when ``after`` is clearly worse than ``before``, else None."""
    worse_rms = (
        np.isfinite(before.rms)
        and np.isfinite(after.rms)
        and after.rms > RESIDUAL_JUMP_FACTOR * before.rms
        and after.rms - before.rms > RESIDUAL_JUMP_METRES
    )
    lost_overlap = before.paired - after.paired > RESIDUAL_JUMP_OVERLAP
    if not (worse_rms or lost_overlap):
        return None
    changes = [
        (a["rms"] - b["rms"] if np.isfinite(a["rms"]) and np.isfinite(b["rms"]) else 0.0, b["paired"] - a["paired"], a)
        for b, a in zip(before.edges, after.edges, strict=True)
    ]
    worst = max(changes, key=lambda c: (c[1] > RESIDUAL_JUMP_OVERLAP, c[0] + c[1]))[2]
    return (
        f"residuals jumped: RMS {before.rms:.3f} m -> {after.rms:.3f} m, paired {before.paired:.0%} -> "
        f"{after.paired:.0%} (worst edge {worst['i']}-{worst['j']}); undo if this was not intended"
    )


def displacements(before: Sequence[Matrix], after: Sequence[Matrix]) -> list[float]:
    """How far each scan's origin moved (metres) from ``before`` to ``after``."""
    return [
        float(np.linalg.norm(np.asarray(a)[:3, 3] - np.asarray(b)[:3, 3])) for b, a in zip(before, after, strict=True)
    ]
