"""Which level of detail each scan is shown at: finer for scans near the camera, all within a point budget.

A scan ``d`` metres from the camera covers an area on screen proportional to ``1/d²``, so showing
every scan at the same density on screen needs ``τ/d²`` points of each for some density ``τ``. The
choice takes the largest ``τ`` whose levels fit the budget: each scan gets the coarsest of its levels
(:mod:`slam6d.scan_levels`) that has at least ``τ/d²`` points. As ``τ`` grows a scan moves up a
level when ``τ`` passes ``size of its current level x d²``, so these crossing points, sorted, are the
order in which refinements are bought; the budget buys them until the next one does not fit. Nearer
scans cross first, so they are never shown coarser than farther ones of the same size.

Every scan keeps at least its first level (the whole map stays on screen), and scans asked for in
full (picked for editing) are shown at full resolution whatever their distance; both are paid
from the budget before any refinement.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence

import numpy as np
from numpy.typing import NDArray

NEAR = 1.0  # m: distances below this count as this (a camera inside a scan wants it in full, not more)


def choose_levels(
    level_points: Sequence[Sequence[int]],
    distances: Sequence[float] | NDArray[np.float64],
    budget: int,
    full: Collection[int] = (),
) -> list[int]:
    """Per scan, the index of its level to show (module docstring); ``level_points[k]`` ascending."""
    count = len(level_points)
    levels = [len(level_points[k]) - 1 if k in full else 0 for k in range(count)]
    spent = sum(int(level_points[k][levels[k]]) for k in range(count))
    d2 = np.maximum(np.asarray(distances, dtype=np.float64), NEAR) ** 2
    scans, crossings, costs = [], [], []
    for k in range(count):
        if k in full:
            continue
        sizes = np.asarray(level_points[k], dtype=np.float64)
        scans.append(np.full(len(sizes) - 1, k))
        crossings.append(sizes[:-1] * d2[k])  # τ at which level l+1 is needed
        costs.append(np.diff(sizes))
    if not scans or spent >= budget:
        return levels
    scan_of = np.concatenate(scans)
    order = np.argsort(np.concatenate(crossings), kind="stable")
    total = spent + np.cumsum(np.concatenate(costs)[order])
    bought = int(np.searchsorted(total, budget, side="right"))  # refinements that fit
    raised = np.bincount(scan_of[order[:bought]], minlength=count)
    return [levels[k] + int(raised[k]) for k in range(count)]


def points_at(level_points: Sequence[Sequence[int]], levels: Sequence[int]) -> int:
    """Points shown when each scan is at ``levels``."""
    return sum(int(level_points[k][level]) for k, level in enumerate(levels))
