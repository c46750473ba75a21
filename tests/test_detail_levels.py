"""Levels of detail: progressive scans on disk (engine) and the choice of levels by camera distance (view)."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest

from app.view.detail_levels import choose_levels, points_at
from slam6d.geometry import make_pose
from slam6d.scan import Scan
from slam6d.scan_levels import ScanLevels, level_sizes, progressive_order


def _wall_and_floor(rng: np.random.Generator, count: int) -> np.ndarray:
    """A scan-like cloud: dense near the scanner (points per area falling with range), a floor and a wall."""
    r = 1.0 + 40.0 * rng.random(count) ** 2
    a = rng.uniform(0, 2 * np.pi, count)
    floor = np.c_[r * np.cos(a), r * np.sin(a), np.full(count, -1.0)]
    wall = np.c_[np.full(count, 12.0), rng.uniform(-30, 30, count), rng.uniform(-1, 8, count)]
    return np.where((rng.random(count) < 0.3)[:, None], wall, floor)


def test_progressive_order_is_a_permutation_whose_prefixes_cover_the_scan_evenly() -> None:
    rng = np.random.default_rng(4)
    points = _wall_and_floor(rng, 60_000)
    order = progressive_order(points, seed=1)
    np.testing.assert_array_equal(np.sort(order), np.arange(len(points)))
    np.testing.assert_array_equal(order, progressive_order(points, seed=1))  # deterministic
    # a 2 m grid over the floor: the first 512 points reach cells a random 512 would mostly miss,
    # because the raw cloud crowds the scanner (the first points of the file are no better)
    floor = points[:, 2] < 0

    def cells(idx: np.ndarray) -> int:
        chosen = points[idx][floor[idx]]
        return len(np.unique(np.floor(chosen[:, :2] / 2.0), axis=0))

    prefix, random = cells(order[:512]), cells(rng.choice(len(points), 512, replace=False))
    assert prefix > 1.5 * random
    # and every level contains the coarser ones (prefixes), ending with every point
    sizes = level_sizes(len(points))
    assert sizes[0] == 128 and sizes[-1] == len(points) and all(b == 4 * a for a, b in pairwise(sizes[:-1]))


def test_levels_are_stored_once_and_reopened_only_for_the_same_scans(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    scans = [
        Scan(_wall_and_floor(rng, 3000 + 500 * k), make_pose(np.eye(3), [k, 0, 0]), name=f"s{k}") for k in range(3)
    ]
    built = ScanLevels.build(tmp_path / "levels", iter(scans), "sources-a")
    opened = ScanLevels.open(tmp_path / "levels", "sources-a")
    assert opened is not None and opened.names == ["s0", "s1", "s2"]
    assert opened.total_points == sum(len(s) for s in scans) == built.total_points
    for k, scan in enumerate(scans):
        full = opened.points(k, opened.top_level(k))
        assert full.dtype == np.float32 and len(full) == len(scan)
        # the full level is the scan's points, reordered
        np.testing.assert_array_equal(np.unique(full, axis=0), np.unique(scan.points.astype(np.float32), axis=0))
        coarse = opened.points(k, 0)
        np.testing.assert_array_equal(coarse, full[:128])  # a level is a prefix of the next
    assert ScanLevels.open(tmp_path / "levels", "sources-b") is None  # other sources: rebuilt, not trusted
    assert ScanLevels.open(tmp_path / "missing", "sources-a") is None


def test_choice_stays_within_the_budget_and_gives_nearer_scans_finer_levels() -> None:
    sizes = [level_sizes(100_000)] * 50
    distances = np.linspace(5.0, 500.0, 50)
    for budget in (50 * 128, 100_000, 750_000, 3_000_000):
        levels = choose_levels(sizes, distances, budget)
        assert points_at(sizes, levels) <= budget
        assert all(a >= b for a, b in pairwise(levels))  # nearer: never coarser
        # the budget is used: the next refinement in line would not fit
        assert budget - points_at(sizes, levels) < max(b - a for a, b in pairwise(sizes[0]))
    levels = choose_levels(sizes, distances, 750_000)
    assert levels[0] == len(sizes[0]) - 1 and levels[-1] < levels[0]
    # moving the camera next to the last scan brings it up and the first one down
    moved = choose_levels(sizes, distances[::-1], 750_000)
    assert moved[-1] == levels[0] and moved[0] == levels[-1]
    # enough budget for everything: every scan in full
    assert choose_levels(sizes, distances, 50 * 100_000) == [len(sizes[0]) - 1] * 50


def test_scans_asked_for_in_full_are_full_and_paid_from_the_budget() -> None:
    sizes = [level_sizes(100_000)] * 20
    distances = np.full(20, 50.0)
    levels = choose_levels(sizes, distances, 300_000, full={7})
    assert levels[7] == len(sizes[7]) - 1
    assert points_at(sizes, levels) <= 300_000
    without = choose_levels(sizes, distances, 300_000)
    assert all(levels[k] <= without[k] for k in range(20) if k != 7) and levels != without
    # a budget smaller than the coarsest map still shows every scan at its first level
    assert choose_levels(sizes, distances, 1_000) == [0] * 20


@pytest.mark.parametrize("scans", [1, 7])
def test_choice_of_one_level_scans(scans: int) -> None:
    sizes = [[40]] * scans  # scans smaller than the first level have one level: all of them
    assert choose_levels(sizes, np.ones(scans), 10) == [0] * scans


def test_a_damaged_level_store_is_not_opened(tmp_path: Path) -> None:
    scans = [Scan(np.random.default_rng(1).normal(0, 5, (500, 3)), np.eye(4), name="s0")]
    ScanLevels.build(tmp_path / "levels", iter(scans), "sources")
    points = tmp_path / "levels" / "points.f32"
    points.write_bytes(points.read_bytes()[:-12])  # one point short: cut off while writing
    assert ScanLevels.open(tmp_path / "levels", "sources") is None
