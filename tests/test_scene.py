"""What the 3D view draws: levels within the budget, float16 safety, residual colouring, graph segments."""

from __future__ import annotations

import numpy as np
import pytest

from app.view import display
from app.view.panels.edges import EdgesPanel
from app.view.picking import pick_scan
from slam6d.geometry import pose_from_xyzrpy


def test_far_from_origin_local_points_are_never_sent_as_float16():
    near = np.array([[0.0, 0.0, 0.0], [31.0, -5.0, 2.0]])
    assert display.precision_for(near) == "float16"
    assert display.precision_for(near + np.array([1000.0, 0, 0])) == "float32"


def test_residuals_measure_disagreement_between_scans():
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 5, 4000), rng.uniform(0, 5, 4000), np.zeros(4000)])
    same = display.residuals([plane, plane], [np.eye(4), np.eye(4)])
    assert np.nanmax(same[0]) == pytest.approx(0.0, abs=1e-9)
    lifted = display.residuals([plane, plane], [np.eye(4), pose_from_xyzrpy(0, 0, 0.2, 0, 0, 0)])
    assert np.nanmedian(lifted[1]) == pytest.approx(0.2, abs=0.01)
    apart = display.residuals([plane, plane[:10]], [np.eye(4), pose_from_xyzrpy(100, 0, 0, 0, 0, 0)])
    assert np.isnan(apart[1]).all()  # no overlap: no residual (drawn grey), rather than a misleading number


def test_ramp_and_scan_colours():
    colours = display.ramp(np.array([0.0, 1.0, np.nan]), 0.0, 1.0)
    assert colours.dtype == np.uint8 and tuple(colours[2]) == (150, 150, 150)
    assert not np.array_equal(colours[0], colours[1])
    assert len({display.scan_color(k) for k in range(20)}) == 20


def test_segments_are_relative_to_the_first_scan():
    poses = [pose_from_xyzrpy(1e5 + k, 2e5, 0, 0, 0, 0) for k in range(3)]
    seg = display.segments([(0, 1), (1, 2)], poses)
    assert seg.dtype == np.float32 and seg.shape == (2, 2, 3)
    np.testing.assert_allclose(seg[1], [[1, 0, 0], [2, 0, 0]])


def _box_room(rng: np.random.Generator, count: int) -> np.ndarray:
    """Points on the floor and three walls of a 10 m room: enough structure to pin a pose in 3D."""
    face = rng.integers(0, 4, count)  # 0 floor, 1 wall x=0, 2 wall x=10, 3 wall y=10
    u, w, v = rng.uniform(0, 10, count), rng.uniform(0, 10, count), rng.uniform(0, 3, count)
    x = np.select([face == 1, face == 2], [0.0, 10.0], u)
    y = np.select([face == 0, face == 3], [w, 10.0], u)
    z = np.where(face == 0, 0.0, v)
    return np.column_stack([x, y, z])


def test_an_edge_whose_scans_disagree_gets_a_clearly_worse_colour():
    from slam6d.icp import ICPConfig
    from slam6d.relax import ScanModels
    from slam6d.residuals import residual_summary

    rng = np.random.default_rng(4)
    room = _box_room(rng, 60_000)
    truth = [pose_from_xyzrpy(k * 0.8, 0.1 * k, 0, 0, 0, 0.05 * k) for k in range(3)]
    local = [(room[rng.choice(len(room), 20_000, replace=False)] - p[:3, 3]) @ p[:3, :3] for p in truth]
    models = ScanModels(local, ICPConfig())
    shown = [truth[0], truth[1], truth[2] @ pose_from_xyzrpy(0.15, -0.1, 0.05, 0.02, 0, 0.03)]  # scan 2 off
    summary = residual_summary(models, shown, [(0, 1), (1, 2)])
    good, bad = (e["plane"] for e in summary.edges)
    assert good < 0.01 and bad > 0.04
    scale = ICPConfig().max_distance / 4  # the viewer's edge scale
    colours = display.edge_colours([good, bad, np.nan], scale)
    assert colours.shape == (3, 2, 3) and colours.dtype == np.uint8
    assert np.array_equal(colours[:, 0], colours[:, 1])  # one colour per edge, both ends
    position = np.linspace(0, scale, 101)  # where on the edge scale each colour sits
    ramp = display.edge_colours(position, scale)[:, 0].astype(int)
    where = [position[np.abs(ramp - c.astype(int)).sum(axis=1).argmin()] for c in colours[:, 0]]
    assert where[0] < 0.25 * scale and where[1] > where[0] + 0.3 * scale
    top = display.edge_colours([scale], scale)[0, 0]
    assert np.array_equal(colours[2, 0], top)  # no overlap at all is the top of the scale, not "no data"
    assert len({tuple(c) for c in ramp}) <= display.EDGE_SHADES + 1  # a few shades, one line node each


def test_pick_scan_takes_the_scan_under_the_cursor_and_in_front():
    rng = np.random.default_rng(5)
    blob = rng.normal(0, 0.3, (2000, 3))  # each scan a small cluster around its own origin
    poses = [pose_from_xyzrpy(x, y, 0, 0, 0, yaw) for x, y, yaw in ((0, 0, 0), (10, 0, 1.0), (20, 0, -0.5))]
    camera = np.array([10.0, -30.0, 5.0])

    def ray_to(target):  # type: ignore[no-untyped-def]
        return camera, np.asarray(target, float) - camera

    assert pick_scan([blob] * 3, poses, *ray_to([10, 0, 0])) == 1
    assert pick_scan([blob] * 3, poses, *ray_to([20.2, 0.1, 0])) == 2
    assert pick_scan([blob] * 3, poses, *ray_to([0, 0, 0])) == 0
    assert pick_scan([blob] * 3, poses, *ray_to([5, 0, 8])) is None  # empty sky between scans
    assert pick_scan([blob] * 3, poses, camera, camera - np.array([10.0, 0, 0])) is None  # behind the camera
    # two scans on the same line of sight: the nearer one hides the farther one
    behind = [pose_from_xyzrpy(10, 0, 0, 0, 0, 0), pose_from_xyzrpy(10, 15, 0, 0, 0, 0)]
    assert pick_scan([blob, blob], behind, *ray_to([10, 0, 0])) == 0
    assert pick_scan([blob, blob], behind[::-1], *ray_to([10, 0, 0])) == 1
    # far from the origin (UTM-like coordinates) the local-frame test is just as exact
    offset = np.array([4.5e5, 5.4e6, 0.0])
    far = [p.copy() for p in poses]
    for p in far:
        p[:3, 3] += offset
    assert pick_scan([blob] * 3, far, camera + offset, np.array([10.0, 0, 0]) - camera) == 1


@pytest.fixture
def corridor_view(tmp_path):  # type: ignore[no-untyped-def]
    from app.resources import ResourceLimits
    from app.server import create_app
    from tests.session_fixtures import corridor_session

    corridor_session(tmp_path / "sessions", scans=3, points=20_000)  # true poses: every edge agrees
    app = create_app(tmp_path / "sessions", limits=ResourceLimits(viewer_grace_s=3600))
    view = app.state.viewers.get("corridor")
    assert view.ready.wait(30) and view.error is None
    yield view
    app.state.viewers.stop_all()


def _edge_colours_when_computed(view):  # type: ignore[no-untyped-def]
    import time

    deadline = time.monotonic() + 30
    while view.graph.edge_residual_version != view.scans.pose_version:
        assert time.monotonic() < deadline, "edge residuals never arrived"
        time.sleep(0.05)
    with view.lock:  # the residuals and the edges drawn with them are set together under it
        colours = view.graph.edge_colours["/graph/trajectory"]
        drawn = {tuple(int(c) for c in node.colors) for node in view.graph.edge_nodes}
        assert {tuple(int(c) for c in rgb) for rgb in colours} <= drawn  # each shade is drawn
        return colours


def test_the_view_recolours_an_edge_when_a_scan_moves_off(corridor_view):
    view = corridor_view
    before = _edge_colours_when_computed(view)
    assert np.abs(before[0].astype(int) - before[1]).max() <= 10  # both edges agree about as well
    assert "worst" in view.controls.edge_legend.content
    moved = [p.copy() for p in view.scans.poses]
    moved[2] = moved[2] @ pose_from_xyzrpy(0.3, 0.2, 0, 0, 0, 0.05)
    view.set_poses(moved)
    view.graph.draw()  # what a new revision does
    after = _edge_colours_when_computed(view)
    assert np.array_equal(after[0], before[0])  # the untouched edge keeps its colour
    position = np.linspace(0, view.graph.edge_scale, 101)  # where on the edge scale each colour sits
    ramp = display.edge_colours(position, view.graph.edge_scale)[:, 0].astype(int)
    where = [position[np.abs(ramp - c.astype(int)).sum(axis=1).argmin()] for c in (after[0], after[1])]
    assert where[1] > where[0] + 0.4 * view.graph.edge_scale  # the moved one: far up the scale
    assert view.graph.edge_residuals[(1, 2)] > 3 * view.graph.edge_residuals[(0, 1)]
    assert "worst 1–2" in view.controls.edge_legend.content


class _Click:
    def __init__(self, origin, direction) -> None:  # type: ignore[no-untyped-def]
        self.ray_origin, self.ray_direction = tuple(origin), tuple(direction)
        self.client_id, self.client = -1, None


def test_clicking_scans_in_the_view_picks_a_then_b_and_highlights_them(corridor_view):
    from app.view.panels.edges import PICKED_A, PICKED_B

    view = corridor_view
    edit = next(p for p in view.panels if isinstance(p, EdgesPanel))
    apart = [p.copy() for p in view.scans.poses]
    for k, p in enumerate(apart):
        p[2, 3] += 40.0 * k  # the corridor scans overlap; stack them 40 m apart to click one alone
    view.set_poses(apart)
    camera = np.array([10.0, -80.0, 40.0])
    centres = [view.scans.local[k].astype(float).mean(axis=0) @ apart[k][:3, :3].T + apart[k][:3, 3] for k in range(3)]
    painted = []
    view.colouring.paint = lambda k: painted.append(k)  # type: ignore[method-assign]  # what would be resent

    edit._clicked(_Click(camera, centres[2] - camera))
    assert int(edit.scan_a.value) == 2 and view.colouring.selected == {2: PICKED_A}  # B not chosen yet: not marked
    assert "Picked scan **2**" in edit.pick_status.content and "as **A**" in edit.pick_status.content
    edit._clicked(_Click(camera, centres[0] - camera))
    assert (int(edit.scan_a.value), int(edit.scan_b.value)) == (2, 0)
    assert view.colouring.selected == {2: PICKED_A, 0: PICKED_B}
    assert (
        view.colouring.scan_colours(0) == PICKED_B
        and view.colouring.scan_colours(2) == PICKED_A
        and view.colouring.scan_colours(1) == display.scan_color(1)
    )
    assert 0 in painted and 2 in painted
    edit._clicked(_Click(camera, (0.0, -1.0, 0.5)))  # away from the map: nothing picked, nothing changed
    assert (int(edit.scan_a.value), int(edit.scan_b.value)) == (2, 0) and "No scan" in edit.pick_status.content


def test_playing_draws_the_current_pair_in_full_and_the_rest_light_without_resending(corridor_view, monkeypatch):
    view = corridor_view
    monkeypatch.setattr(display, "PLAYBACK_BUDGET", 900)
    full = [len(p) for p in view.scans.local]
    view.begin_playback([2, 1])
    assert [n.visible for n in view.scans.nodes] == [False, True, True]
    assert set(view.scans.light) == {0} and view.scans.light[0][0].visible
    light_points = len(view.scans.light[0][0].points)
    assert 0 < light_points <= 900 // 3 < full[0]
    # moving the current scan sends its pose to its full node only; the light node is not re-sent
    sent = view.scans.light[0][0]
    moved = [p.copy() for p in view.scans.poses]
    moved[2] = moved[2] @ pose_from_xyzrpy(0.1, 0, 0, 0, 0, 0.02)
    view.set_poses(moved, [2])
    np.testing.assert_allclose(view.scans.nodes[2].position, moved[2][:3, 3])
    # the pair moves on: scan 1 becomes light, scan 0 full again; existing light nodes are reused
    view.begin_playback([0])
    assert [n.visible for n in view.scans.nodes] == [True, False, False]
    assert view.scans.light[0][0] is sent and not sent.visible and view.scans.light[2][0].visible
    np.testing.assert_allclose(view.scans.light[2][0].position, moved[2][:3, 3])  # shown where the scan now is
    view.end_playback()
    assert view.scans.focus is None and all(n.visible for n in view.scans.nodes)
    assert not any(node.visible for node, _ in view.scans.light.values())
    assert [len(n.points) for n in view.scans.nodes] == full  # the whole budget is back, never re-sent


def test_stepper_play_enters_playback_and_pause_leaves_it(corridor_view):
    import time

    view = corridor_view
    stepper = view._stepper("ana")
    stepper.play(rate=5.0)
    deadline = time.monotonic() + 60
    while stepper.current is None and not stepper.finished:
        assert time.monotonic() < deadline, "stepping did not start"
        time.sleep(0.05)
    stepper.pause()
    assert view.scans.focus is None and all(n.visible for n in view.scans.nodes)
    stepper.play(rate=5.0)
    assert view.scans.focus == stepper._focus() and stepper.current in view.scans.focus
    stepper.pause()
    assert view.scans.focus is None


def test_edge_residual_tells_aligned_sparse_scans_from_misaligned_ones():
    """Sparse scans: closest-point distances grow with the point spacing, the plane residual does not."""
    from slam6d.icp import ICPConfig
    from slam6d.relax import ScanModels
    from slam6d.residuals import residual_summary

    rng = np.random.default_rng(5)
    room = _box_room(rng, 60_000)
    truth = [pose_from_xyzrpy(k * 0.8, 0.1 * k, 0, 0, 0, 0.05 * k) for k in range(3)]
    local = [(room[rng.choice(len(room), 1_500, replace=False)] - p[:3, 3]) @ p[:3, :3] for p in truth]
    local = [points + rng.normal(0, 0.003, points.shape) for points in local]  # range noise
    models = ScanModels(local, ICPConfig())
    shown = [truth[0], truth[1], truth[2] @ pose_from_xyzrpy(0.05, -0.04, 0.0, 0, 0, 0.01)]  # scan 2 a few cm off
    aligned, off = residual_summary(models, shown, [(0, 1), (1, 2)]).edges
    assert aligned["rms"] > 0.1  # spacing alone: closest points of aligned sparse scans are far apart
    assert aligned["plane"] < 0.01 and off["plane"] > 0.025 and off["plane"] > 3 * aligned["plane"]


def test_a_reopened_view_reads_the_levels_of_the_first_open_without_recomputing(tmp_path, monkeypatch):
    """The first open orders every scan into levels of detail once; later opens only read prefixes."""
    from app.resources import ResourceLimits
    from app.server import create_app
    from slam6d import scan_levels
    from tests.session_fixtures import corridor_session

    corridor_session(tmp_path / "sessions", scans=3, points=20_000)
    shown = []
    for attempt in range(2):
        if attempt:
            monkeypatch.setattr(scan_levels, "progressive_order", _never_recomputed)
        app = create_app(tmp_path / "sessions", limits=ResourceLimits(viewer_grace_s=3600))
        view = app.state.viewers.get("corridor")
        assert view.ready.wait(30) and view.error is None
        shown.append([p.copy() for p in view.scans.local])
        app.state.viewers.stop_all()
    assert all(np.array_equal(a, b) for a, b in zip(*shown, strict=True))


def _never_recomputed(*args, **kwargs):  # type: ignore[no-untyped-def]
    raise AssertionError("the levels of detail were recomputed")


def test_a_smaller_budget_coarsens_the_map_and_a_picked_scan_is_shown_in_full(corridor_view):
    view = corridor_view
    detail = view.stream.detail
    full = [len(p) for p in view.scans.local]
    assert full == [detail.levels.level_points[k][-1] for k in range(3)]  # 60k points: all fit the budget
    with view.lock:
        view.controls.budget.value = 10_000
    detail.refresh()
    coarse = [len(p) for p in view.scans.local]
    assert sum(coarse) <= 10_000 and all(c < f for c, f in zip(coarse, full, strict=True))
    view.colouring.select({1: (255, 255, 255)})
    detail.refresh()
    assert len(view.scans.local[1]) == full[1]  # picked for editing: every point
    assert [len(p) for p in view.scans.local] == [
        detail.levels.level_points[k][lv] for k, lv in enumerate(detail.shown)
    ]
    assert view.scans.nodes[1].colors.tolist() == [255, 255, 255]  # the resent node keeps the pick colour


def test_edge_colours_come_from_bounded_samples_of_the_scans_and_match_the_full_scans(tmp_path):
    """A reopened view colours its edges without reading any scan in full, within a shade of the full scans' colours."""
    from app.resources import ResourceLimits
    from app.server import create_app
    from app.view.graph_overlay import RESIDUAL_SAMPLE
    from tests.session_fixtures import corridor_session

    corridor_session(tmp_path / "sessions", scans=4, points=30_000)
    first = create_app(tmp_path / "sessions", limits=ResourceLimits(viewer_grace_s=3600))
    assert first.state.viewers.get("corridor").ready.wait(60)  # the first open orders the levels once
    first.state.viewers.stop_all()

    app = create_app(tmp_path / "sessions", limits=ResourceLimits(viewer_grace_s=3600))
    view = app.state.viewers.get("corridor")
    assert view.ready.wait(30) and view.error is None
    try:
        moved = [p.copy() for p in view.scans.poses]
        moved[3] = moved[3] @ pose_from_xyzrpy(0.02, -0.015, 0, 0, 0, 0.004)  # one edge half-way up the scale
        view.set_poses(moved)
        view.graph.draw()
        colours = _edge_colours_when_computed(view)
        assert not view.state.loaded  # no scan was read in full
        models = view.graph.models
        assert models is not None and all(len(p) <= RESIDUAL_SAMPLE for p in models.points)
        assert sum(len(p) for p in models.points) < 0.3 * view.scans.total_points

        full = view.editor.context.residuals("corridor", moved)  # the editor's models of the full scans
        for edge in full.edges:
            sampled = view.graph.edge_residuals[(edge["i"], edge["j"])]
            assert abs(sampled - edge["plane"]) <= 0.1 * view.graph.edge_scale, (edge, sampled)
        assert view.graph.edge_residuals[(2, 3)] > 3 * view.graph.edge_residuals[(0, 1)]
        expected = display.edge_colours([e["plane"] for e in full.edges if e["j"] == e["i"] + 1], view.graph.edge_scale)
        assert np.abs(colours.astype(int) - expected[:, 0].astype(int)).max() <= 60  # within about one shade
    finally:
        app.state.viewers.stop_all()
