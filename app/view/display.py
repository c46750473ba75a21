"""What the 3D view draws, computed without any viewer: point budgets, colours, graph lines.

Scans are drawn in their own frame with the pose on the scene node, so the points are sent once
and a pose change costs a few bytes. Local coordinates stay small, which is what makes float16
safe; world coordinates of a map far from the origin would quantise to centimetres or worse.
"""

from __future__ import annotations

import colorsys
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from slam6d.geometry import Matrix
from slam6d.nn import build_index
from slam6d.octree import reduce_points

# A 1280x800 view of a whole map covers ~0.5M pixels: 750k points fill it (42 % of the canvas on the
# 77 x 100k benchmark session, against 47 % at 1.5M), at half the transfer and frame cost of 1.5M.
DEFAULT_BUDGET = 750_000
COARSE_BUDGET = 200_000  # an older revision's whole map (app.view.revision_view): ~0.5 s per software frame
# The first look at a session's whole map (one cloud, app.view.scene_stream): a software renderer draws
# ~0.5M points per second, and the page draws it while it is still mounting the view; 100k points are
# 100 per scan of a 1,000-scan campus, below the scans' coarsest level (taken as an even prefix).
FIRST_LOOK_BUDGET = 100_000
PLAYBACK_BUDGET = 10_000  # the map around the current pair while stepping plays: frames must stay cheap
EDGE_SHADES = 10  # steps of the edge residual scale
FLOAT16_SAFE_EXTENT = 32.0  # metres: float16 spacing stays under 1.6 cm up to here

# one palette wherever a pair being matched is shown (stepping, replay, octree guess cubes)
DATA_SCAN = (255, 120, 0)  # the scan being matched
MODEL_SCANS = (60, 140, 255)  # the scans it is matched against

_RAMP = np.array(  # perceptually ordered blue -> cyan -> green -> yellow -> red
    [[48, 18, 59], [40, 160, 230], [60, 220, 120], [250, 200, 40], [200, 30, 20]], dtype=np.float64
)


def display_indices(points: NDArray[np.float64], voxel_size: float, cap: int) -> NDArray[np.int64]:
    """One real point per voxel, then an even thinning down to ``cap`` if still too many."""
    keep = reduce_points(points, voxel_size) if voxel_size > 0 and len(points) > 1 else np.arange(len(points))
    if len(keep) > cap:
        keep = keep[np.linspace(0, len(keep) - 1, max(cap, 1)).astype(np.int64)]
    return keep


def precision_for(points: NDArray[np.floating]) -> str:
    extent = float(np.abs(points).max()) if len(points) else 0.0
    return "float16" if extent <= FLOAT16_SAFE_EXTENT else "float32"


def scan_color(index: int) -> tuple[int, int, int]:
    """Distinct, stable colours: hues spaced by the golden ratio."""
    r, g, b = colorsys.hsv_to_rgb((index * 0.61803398875) % 1.0, 0.65, 0.95)
    return int(r * 255), int(g * 255), int(b * 255)


def rgb(colour: NDArray[np.uint8]) -> tuple[int, int, int]:
    """One row of a colour array as the plain-int triple viser's handles take for a single colour."""
    r, g, b = (int(c) for c in colour)
    return r, g, b


def ramp(values: NDArray[np.float64], low: float, high: float) -> NDArray[np.uint8]:
    """Map values to the colour ramp; NaN becomes grey (no data)."""
    span = high - low if high > low else 1.0
    t = np.clip((np.asarray(values, dtype=np.float64) - low) / span, 0.0, 1.0) * (len(_RAMP) - 1)
    lower = np.floor(np.nan_to_num(t)).astype(np.int64).clip(0, len(_RAMP) - 2)
    frac = (np.nan_to_num(t) - lower)[:, None]
    colors = _RAMP[lower] * (1 - frac) + _RAMP[lower + 1] * frac
    colors[~np.isfinite(values)] = 150.0
    return colors.astype(np.uint8)


def world_heights(local: NDArray[np.floating], pose: Matrix) -> NDArray[np.float64]:
    return np.asarray(local, dtype=np.float64) @ pose[2, :3] + pose[2, 3]


def height_range(clouds: Sequence[NDArray[np.floating]], poses: Sequence[Matrix]) -> tuple[float, float]:
    """2nd-98th percentile of world heights, so a stray point does not wash out the ramp."""
    samples = [world_heights(c[:: max(1, len(c) // 2000)], p) for c, p in zip(clouds, poses, strict=True) if len(c)]
    if not samples:
        return 0.0, 1.0
    z = np.concatenate(samples)
    return float(np.percentile(z, 2)), float(np.percentile(z, 98))


def residuals(clouds: Sequence[NDArray[np.floating]], poses: Sequence[Matrix], neighbours: int = 8) -> list[NDArray]:
    """Per point: distance to the nearest point of any *other* scan (NaN when none among the k nearest).

    This is what "residual" means to a person looking at the map: where scans disagree.
    """
    world = [np.asarray(c, np.float64) @ p[:3, :3].T + p[:3, 3] for c, p in zip(clouds, poses, strict=True)]
    labels = np.concatenate([np.full(len(w), k) for k, w in enumerate(world)])
    stacked = np.concatenate(world)
    if len(stacked) < 2:
        return [np.full(len(w), np.nan) for w in world]
    index = build_index(stacked)
    k = min(neighbours, len(stacked))
    dist, idx = index.knn(stacked, k)
    dist, idx = dist.reshape(len(stacked), k), idx.reshape(len(stacked), k)
    other = (idx >= 0) & (labels[np.clip(idx, 0, None)] != labels[:, None])
    first = np.where(other.any(axis=1), other.argmax(axis=1), -1)
    result = np.where(first >= 0, dist[np.arange(len(stacked)), np.clip(first, 0, None)], np.nan)
    bounds = np.concatenate([[0], np.cumsum([len(w) for w in world])])
    return [result[bounds[k] : bounds[k + 1]] for k in range(len(world))]


def segments(pairs: Sequence[tuple[int, int]], poses: Sequence[Matrix]) -> NDArray[np.float32]:
    """(N, 2, 3) line segments between scan positions, relative to the first scan's position.

    The caller places the segment node at that position, keeping these coordinates small.
    """
    if not pairs:
        return np.zeros((0, 2, 3), np.float32)
    origin = poses[0][:3, 3]
    return np.array([[poses[i][:3, 3] - origin, poses[j][:3, 3] - origin] for i, j in pairs], dtype=np.float32)


def edge_colours(residuals: Sequence[float], scale: float) -> NDArray[np.uint8]:
    """(N, 2, 3) colours of graph edges by their residual from 0 (cyan) to ``scale`` metres (red).

    An edge whose scans have no point pairs at all (NaN) is drawn at the top of the ramp:
    scans joined by an edge that do not overlap are as wrong as an edge gets, not "no data".
    """
    values = np.asarray(residuals, dtype=np.float64).reshape(-1)
    values = np.where(np.isfinite(values), np.minimum(values, scale), scale)
    values = np.round(values / scale * EDGE_SHADES) * scale / EDGE_SHADES  # a few shades: one line node each
    # from the ramp's cyan up: its dark blue end would vanish against the dark background
    colours = ramp(values, -scale / 3, scale)
    return np.repeat(colours[:, None, :], 2, axis=1)


def pair_colours(current: int | None, model: Sequence[int]) -> dict[int, tuple[int, int, int]]:
    """The highlight of a scan being matched (``current``) and its model scans; none when no scan is."""
    return {} if current is None else {**dict.fromkeys(model, MODEL_SCANS), current: DATA_SCAN}
