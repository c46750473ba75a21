"""The 3D view's editing panels driven directly (no browser): replay, displacement colours, gizmo moves."""

from __future__ import annotations

import numpy as np
import pytest

from app.resources import ResourceLimits
from app.server import create_app
from tests.session_fixtures import corridor_session


class Click:
    client_id = -1  # no browser: the journal records "anonymous"


@pytest.fixture
def viewer(tmp_path):
    root = tmp_path / "sessions"
    corridor_session(root, scans=3, points=1500, odometry_noise=0.1)
    app = create_app(root, limits=ResourceLimits(viewer_grace_s=3600))  # no browser: keep the view
    view = app.state.viewers.get("corridor")
    assert view.ready.wait(30) and view.error is None
    yield view
    app.state.viewers.stop_all()


def panel(view, name: str):  # type: ignore[no-untyped-def]
    return next(p for p in view.panels if type(p).__name__ == name)


def test_replay_moves_the_scans_to_the_stored_run_poses(viewer):
    workbench = viewer.workbench
    from app.registration import registration_job

    job = workbench.jobs.submit("corridor", "register", registration_job(workbench, "corridor", "ana", {}), "ana")
    assert workbench.jobs.wait(job.id, 120).status == "done"
    committed = workbench.current_poses("corridor")
    replay = panel(viewer, "ReplayPanel")
    replay.refresh()
    assert replay.trace.value == job.result["trace"]
    replay._load()
    assert np.allclose(viewer.scans.poses[2], workbench.state("corridor").session.poses(0)[2])  # back at the start
    steps = 0
    while replay._next():
        steps += 1
    assert steps == len(replay.frames) > 5
    for shown, stored in zip(viewer.scans.poses, committed, strict=True):
        assert np.allclose(shown, stored, atol=1e-9)
    assert "end of the run" in replay.status.content or "finished" in replay.status.content


def test_gizmo_move_and_displacement_colours(viewer):
    edit, loops = panel(viewer, "EdgesPanel"), panel(viewer, "LoopsPanel")
    edit.scan_a.value = 1
    edit.drag.value = True
    edit._toggle_gizmo()
    edit.gizmo.position = np.asarray(edit.gizmo.position) + np.array([0.0, 0.0, 1.5])
    edit._move(Click(), refine=False)
    session = viewer.state.session
    assert session.revision == 1 and session.journal.entries()[-1].kind == "manual_move"
    assert "residuals jumped" in viewer.controls.warnings.content  # the guardrail is on screen
    loops.by_displacement.value = True
    loops._colour()
    assert set(viewer.colouring.highlight) == {0, 1, 2}
    assert viewer.colouring.highlight[1] != viewer.colouring.highlight[0]  # the moved scan is coloured apart
    assert "1.50 m" in loops.legend.content


def test_a_component_is_shown_apart_and_carried_along_with_a_dragged_scan(viewer):
    from app.editing import editor_for

    edit, loops, pieces = panel(viewer, "EdgesPanel"), panel(viewer, "LoopsPanel"), panel(viewer, "ComponentsPanel")
    pieces.refresh()  # lum (the default) finds its graph from the scans: only when asked or after a failed run
    assert viewer.colouring.component_of == {} and "Choose *Colour by* `component`" in pieces.message.content
    editor_for(viewer.workbench).edges.delete("corridor", 0, "ana")  # the edge 0-1: pieces [0] and [1, 2]
    loops.method.value = "graph"  # the components of the graph that graph relaxation would use
    pieces.refresh()
    assert viewer.colouring.component_of == {0: 0, 1: 1, 2: 1}
    assert "2 components [0]; [1-2]" in pieces.message.content
    assert viewer.controls.colour.value == "component"
    assert viewer.colouring.scan_colours(1) == viewer.colouring.scan_colours(2) != viewer.colouring.scan_colours(0)

    before = viewer.state.session.poses()
    edit.scan_a.value = 1
    edit.carry.value = True
    edit.drag.value = True
    edit._toggle_gizmo()
    edit.gizmo.position = np.asarray(edit.gizmo.position) + np.array([0.0, 0.0, 1.5])
    edit._move(Click(), refine=False)
    after = viewer.state.session.poses()
    assert viewer.state.session.journal.entries()[-1].parameters["carry"] == [2]
    for k, lift in ((0, 0.0), (1, 1.5), (2, 1.5)):  # scan 2 came along with scan 1, scan 0 stayed
        np.testing.assert_allclose(after[k][:3, 3] - before[k][:3, 3], [0.0, 0.0, lift], atol=1e-9)
    assert "with 1 scan(s) of its component" in edit.result.content


def test_a_failed_run_with_pieces_turns_the_component_colours_on_with_its_reason(viewer):
    workbench = viewer.workbench
    poses = workbench.current_poses("corridor")
    poses[2] = poses[2].copy()
    poses[2][0, 3] += 1000.0  # the run lost scan 2: it sits 1 km off, overlapping nothing
    failure = {"stage": "relaxation", "reason": "the pose graph is disconnected", "error": "DisconnectedGraphError"}
    workbench.commit("corridor", poses, "ana", "register", {"failure": failure, "components": [[0, 1], [2]]})
    pieces = panel(viewer, "ComponentsPanel")
    pieces.refresh()  # lum (the default): computed because the revision comes from a failed run
    assert viewer.colouring.component_of == {0: 0, 1: 0, 2: 1}
    assert viewer.controls.colour.value == "component"
    assert pieces.message.content.startswith(
        "**⚠ the relaxation stage failed (revision 1): the pose graph is disconnected. "
        "lum relaxation would find the graph disconnected: 2 components [0-1]; [2]"
    )


def test_long_lists_are_paged() -> None:
    from app.view.panels.paging import PAGE_ROWS, page_bounds

    assert page_bounds(0, 1) == (0, 0, 1)
    assert page_bounds(1000, 1) == (0, PAGE_ROWS, 40)
    assert page_bounds(1001, 41) == (1000, 1001, 41)
    assert page_bounds(1001, 99) == (1000, 1001, 41)  # past the end: the last page
    assert page_bounds(30, 0) == (0, PAGE_ROWS, 2)


def test_the_edge_list_of_a_long_trajectory_is_sent_a_page_at_a_time(tmp_path):
    from app.view.panels.paging import PAGE_ROWS
    from slam6d.session import Session
    from slam6d.simulate import SimulationConfig, simulate_session

    simulate_session(tmp_path / "scans", SimulationConfig(scans=60, points_per_scan=2000))
    Session.create(tmp_path / "sessions" / "corridor", "Loop", tmp_path / "scans")
    app = create_app(tmp_path / "sessions")
    view = app.state.viewers.get("corridor")
    assert view.ready.wait(60) and view.error is None
    try:
        edges = panel(view, "EdgesPanel")
        edges.refresh()
        assert len(edges.edge.options) == PAGE_ROWS and edges.edge.options[0].startswith("0: 0–1")
        edges.edge_pages.number.value = 3  # the last page: edges 50..58
        edges.refresh()
        assert len(edges.edge.options) == 59 - 2 * PAGE_ROWS and edges.edge.options[-1].startswith("58: 58–59")
    finally:
        app.state.viewers.stop_all()
