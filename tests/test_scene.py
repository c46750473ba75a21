"""What the 3D view draws: point budget, float16 safety, residual colouring, graph segments."""

from __future__ import annotations

import numpy as np
import pytest

from app import scene
from slam6d.geometry import pose_from_xyzrpy


def test_budget_selection_keeps_the_map_within_budget_and_uses_real_points():
    rng = np.random.default_rng(0)
    clouds = [rng.uniform(-10, 10, (50_000, 3)) for _ in range(4)]
    selection = scene.budget_selection(clouds, budget=20_000, voxel_size=0.05)
    assert sum(len(s) for s in selection) <= 20_000
    assert all(len(s) == 5_000 for s in selection)  # dense clouds fill their share
    assert all(np.all(np.diff(s) > 0) for s in selection)  # real, distinct points in scan order
    # a coarse voxel gives fewer points than the cap: one per occupied voxel
    coarse = scene.budget_selection(clouds, budget=1_000_000, voxel_size=5.0)
    assert all(len(s) <= 64 for s in coarse)


def test_coarse_selection_covers_every_scan_within_the_coarse_budget():
    rng = np.random.default_rng(3)
    clouds = [rng.uniform(-10, 10, (n, 3)) for n in (60_000, 30_000, 500)]
    coarse = scene.coarse_selection(clouds, budget=30_000)
    assert sum(len(s) for s in coarse) <= 30_000
    assert [len(s) for s in coarse] == [10_000, 10_000, 500]  # every scan is in the first look, small ones whole
    assert all(np.all(np.diff(s) > 0) and s[-1] < len(c) for s, c in zip(coarse, clouds, strict=True))
    # spread over the whole scan, not its first points: the coarse map has the same extent
    np.testing.assert_allclose(clouds[0][coarse[0]].min(axis=0), clouds[0].min(axis=0), atol=0.1)
    np.testing.assert_allclose(clouds[0][coarse[0]].max(axis=0), clouds[0].max(axis=0), atol=0.1)


def test_cached_budget_selection_reuses_only_for_the_same_scans(tmp_path, monkeypatch):
    rng = np.random.default_rng(2)
    clouds = [rng.uniform(-10, 10, (20_000, 3)) for _ in range(3)]
    cache = tmp_path / "cache" / "display.npz"
    first = scene.cached_budget_selection(cache, clouds, budget=9_000, voxel_size=0.05)
    assert cache.exists()
    expected = scene.budget_selection(clouds, budget=9_000, voxel_size=0.05)
    assert all(np.array_equal(a, b) for a, b in zip(first, expected, strict=True))

    def no_recompute(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise AssertionError("recomputed although nothing changed")

    monkeypatch.setattr(scene, "budget_selection", no_recompute)
    again = scene.cached_budget_selection(cache, clouds, budget=9_000, voxel_size=0.05)
    assert all(np.array_equal(a, b) for a, b in zip(again, expected, strict=True))
    monkeypatch.undo()
    moved = [clouds[0], clouds[1] + 1.0, clouds[2]]  # one scan changed: its choice must be recomputed
    changed = scene.cached_budget_selection(cache, moved, budget=9_000, voxel_size=0.05)
    assert all(np.array_equal(a, b) for a, b in zip(changed, scene.budget_selection(moved, 9_000, 0.05), strict=True))
    smaller = scene.cached_budget_selection(cache, moved, budget=3_000, voxel_size=0.05)
    assert sum(len(s) for s in smaller) <= 3_000
    cache.write_bytes(b"damaged")
    assert sum(len(s) for s in scene.cached_budget_selection(cache, moved, budget=3_000, voxel_size=0.05)) <= 3_000


def test_far_from_origin_local_points_are_never_sent_as_float16():
    near = np.array([[0.0, 0.0, 0.0], [31.0, -5.0, 2.0]])
    assert scene.precision_for(near) == "float16"
    assert scene.precision_for(near + np.array([1000.0, 0, 0])) == "float32"


def test_residuals_measure_disagreement_between_scans():
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 5, 4000), rng.uniform(0, 5, 4000), np.zeros(4000)])
    same = scene.residuals([plane, plane], [np.eye(4), np.eye(4)])
    assert np.nanmax(same[0]) == pytest.approx(0.0, abs=1e-9)
    lifted = scene.residuals([plane, plane], [np.eye(4), pose_from_xyzrpy(0, 0, 0.2, 0, 0, 0)])
    assert np.nanmedian(lifted[1]) == pytest.approx(0.2, abs=0.01)
    apart = scene.residuals([plane, plane[:10]], [np.eye(4), pose_from_xyzrpy(100, 0, 0, 0, 0, 0)])
    assert np.isnan(apart[1]).all()  # no overlap: no residual (drawn grey), rather than a misleading number


def test_ramp_and_scan_colours():
    colours = scene.ramp(np.array([0.0, 1.0, np.nan]), 0.0, 1.0)
    assert colours.dtype == np.uint8 and tuple(colours[2]) == (150, 150, 150)
    assert not np.array_equal(colours[0], colours[1])
    assert len({scene.scan_color(k) for k in range(20)}) == 20


def test_segments_are_relative_to_the_first_scan():
    poses = [pose_from_xyzrpy(1e5 + k, 2e5, 0, 0, 0, 0) for k in range(3)]
    seg = scene.segments([(0, 1), (1, 2)], poses)
    assert seg.dtype == np.float32 and seg.shape == (2, 2, 3)
    np.testing.assert_allclose(seg[1], [[1, 0, 0], [2, 0, 0]])
