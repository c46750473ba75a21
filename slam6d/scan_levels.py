"""Levels of detail of every scan, computed once and kept on disk: a prefix of each scan is a coarser copy.

A map of 1,000 scans x 100,000 points cannot go to a browser whole (a software renderer draws about
half a million points per second), and choosing a thinned copy per scan each time the camera moves
must not touch every point. So each scan's points are stored once in a *progressive order*: the
first 128 points spread over the whole scan, the first 512 spread four times as densely, and so on
up to all of them. Level ``l`` of a scan is then simply its first ``level_points[l]`` points, read
with one file read and without any computation, and a finer level contains the coarser one.

The order comes from an octree over the scan: points are sorted along a Morton curve of a 1 cm grid,
so every octree cell at every depth is a contiguous run, and each point gets a fixed random priority.
A point's depth is the coarsest depth at which it has the lowest priority in its cell; points are
ordered by depth, then priority. The lowest-priority point of a cell is also the lowest of the child
cell holding it, so every depth's representatives include the coarser depths' ones, and any prefix
(even one cut within a depth) is an even spatial sample rather than the points of one corner.

The points are written as a :class:`~slam6d.scan_store.ScanStore` (float32, the scanner's own frame)
whose index also carries the level sizes and a fingerprint of what the scans were read from; a store
with another fingerprint (changed scan files, other read settings) is rebuilt, not trusted.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from slam6d.scan import Scan
from slam6d.scan_store import ScanStore, ScanStoreError
from slam6d.session import CACHE_DIR, Session

__all__ = ["FIRST_LEVEL", "LEVEL_STEP", "ScanLevels", "level_sizes", "progressive_order", "session_levels"]

FIRST_LEVEL = 128  # points of level 0: the whole map of 1,000 scans in 128k points
LEVEL_STEP = 4  # each level has 4x the points of the one before (twice as dense on a surface)
GRID_CELL = 0.01  # m: the finest octree cell; points closer than this are ordered by priority alone
_AXIS_BITS = 21  # bits per axis of the Morton code (63 bits in all)
_FORMAT = 1  # bumped when the order changes, so older stores are rebuilt


def level_sizes(count: int, first: int = FIRST_LEVEL, step: int = LEVEL_STEP) -> list[int]:
    """Points of each level of a scan of ``count`` points: first, first*step, ... then all of them."""
    sizes: list[int] = []
    size = first
    while size < count:
        sizes.append(size)
        size *= step
    sizes.append(count)
    return sizes


def _spread_bits(values: NDArray[np.uint64]) -> NDArray[np.uint64]:
    """Put bit i of each 21-bit value at bit 3i (one axis of a Morton code)."""
    v = values & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    for shift, mask in ((4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def progressive_order(points: NDArray[np.floating], seed: int = 0) -> NDArray[np.int64]:
    """A permutation of ``points`` whose every prefix is an even spatial sample (module docstring)."""
    count = len(points)
    if count <= 1:
        return np.arange(count, dtype=np.int64)
    p = np.asarray(points, dtype=np.float64)
    lower = p.min(axis=0)
    extent = float((p.max(axis=0) - lower).max())
    cell = max(GRID_CELL, extent / (2**_AXIS_BITS - 1))
    grid = np.minimum(((p - lower) / cell).astype(np.uint64), np.uint64(2**_AXIS_BITS - 1))
    code = (
        _spread_bits(grid[:, 0])
        | (_spread_bits(grid[:, 1]) << np.uint64(1))
        | (_spread_bits(grid[:, 2]) << np.uint64(2))
    )
    along = np.argsort(code, kind="stable")
    code = code[along]
    priority = np.random.default_rng(seed).permutation(count)  # priority of each point (unique)
    by_priority = np.empty(count, dtype=np.int64)
    by_priority[priority] = np.arange(count)  # the point holding each priority
    priority_along = priority[along]
    depth = np.full(count, _AXIS_BITS + 1, dtype=np.int64)  # points never a cell's representative: last
    for level in range(_AXIS_BITS + 1):  # octree depth 0 (one cell) .. 21 (the 1 cm grid)
        cells = code >> np.uint64(3 * (_AXIS_BITS - level))
        starts = np.concatenate([[0], np.flatnonzero(cells[1:] != cells[:-1]) + 1])
        representatives = by_priority[np.minimum.reduceat(priority_along, starts)]
        depth[representatives] = np.minimum(depth[representatives], level)
        if len(starts) == count:  # every point alone in its cell: no finer depth changes anything
            break
    return np.lexsort((priority, depth)).astype(np.int64)


class ScanLevels:
    """The progressive store of a session's scans: level ``l`` of scan ``k`` is its first ``level_points[k][l]`` points."""

    def __init__(self, store: ScanStore) -> None:
        self.store = store
        self.level_points: list[list[int]] = [level_sizes(int(n)) for n in store.counts]

    @staticmethod
    def build(
        directory: Path | str,
        scans: Iterable[Scan],
        fingerprint: str,
        progress: Callable[[int], None] | None = None,
    ) -> ScanLevels:
        """Order each scan's points progressively and write them to ``directory`` (replacing what is there).

        ``fingerprint`` names what the scans were read from; :meth:`open` with another gives None.
        Written beside the final folder and renamed, so a crash never leaves a half store that opens.
        """
        target = Path(directory)
        partial = target.with_name(target.name + ".partial")
        shutil.rmtree(partial, ignore_errors=True)

        def ordered() -> Iterable[Scan]:
            for k, scan in enumerate(scans):
                order = progressive_order(scan.points, seed=k)
                yield Scan(scan.points[order], scan.pose, name=scan.name, has_pose=scan.has_pose)
                if progress is not None:
                    progress(k + 1)

        ScanStore.create(partial, ordered(), extra={"levels_fingerprint": _key(fingerprint)})
        shutil.rmtree(target, ignore_errors=True)
        partial.rename(target)
        return ScanLevels(ScanStore(target, budget=1))

    @staticmethod
    def open(directory: Path | str, fingerprint: str) -> ScanLevels | None:
        """The store at ``directory`` if it was built from the scans ``fingerprint`` names, else None."""
        if not ScanStore.holds(directory):
            return None
        try:
            store = ScanStore(directory, budget=1)  # prefix reads only: nothing is kept in its cache
        except ScanStoreError:  # damaged (e.g. cut short by a full disk): rebuilt like a stale one
            return None
        if store.extra.get("levels_fingerprint") != _key(fingerprint):
            return None
        return ScanLevels(store)

    def __len__(self) -> int:
        return len(self.store)

    @property
    def names(self) -> list[str]:
        return self.store.names

    @property
    def total_points(self) -> int:
        return int(self.store.counts.sum())

    def top_level(self, k: int) -> int:
        """Scan k's full-resolution level."""
        return len(self.level_points[k]) - 1

    def points(self, k: int, level: int) -> NDArray[np.float32]:
        """Scan k's points at ``level`` (float32, its own frame): one read of a prefix, nothing cached."""
        return self.store.prefix(k, self.size(k, level))

    def at_levels(self, levels: Sequence[int]) -> list[NDArray[np.float32]]:
        """Every scan at its level in ``levels`` (:meth:`points` for all scans, one open of the store)."""
        return self.store.prefixes((k, self.size(k, level)) for k, level in enumerate(levels))

    def size(self, k: int, level: int) -> int:
        """Points of scan k at ``level`` (clamped to its levels)."""
        sizes = self.level_points[k]
        return sizes[min(max(level, 0), len(sizes) - 1)]

    def samples(self, counts: Sequence[int]) -> list[NDArray[np.float32]]:
        """Each scan's first ``counts[k]`` points (all of them if it has fewer; float32, its own frame).

        Any prefix of the progressive order is an even sample of the scan, also one cut between two
        levels, so a caller needing a set number of points per scan (a first look at a thousand scans
        below their coarsest level, a bounded copy for residuals) reads exactly that many.
        """
        return self.store.prefixes(enumerate(counts))


def _key(fingerprint: str) -> str:
    return f"v{_FORMAT}|{FIRST_LEVEL}|{LEVEL_STEP}|{GRID_CELL}|{fingerprint}"


LEVELS_DIR = "levels"  # inside a session's cache folder


def session_levels(
    session: Session, scans: Callable[[], Iterable[Scan]], progress: Callable[[int], None] | None = None
) -> ScanLevels:
    """The levels of a session's scans: from its cache when built from the scans as they are now,
    else built from ``scans()`` (called only then: a reopened session reads no full scan)."""
    directory = session.folder / CACHE_DIR / LEVELS_DIR
    fingerprint = session.scan_cache().fingerprint()
    return ScanLevels.open(directory, fingerprint) or ScanLevels.build(directory, scans(), fingerprint, progress)
