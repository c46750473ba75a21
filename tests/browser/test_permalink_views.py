"""Permalinks in a real browser: a colour mode of one's own at the head, and a pick in the 3D view carried by the link."""

from __future__ import annotations

import httpx
import numpy as np
import pytest

from app.tokens import Role
from app.view import display
from app.view.panels.edges import EdgesPanel
from tests.browser.conftest import viewer_frame
from tests.browser.test_editing import open_folder
from tests.browser.test_picking import aim_at_scan, lift_scan
from tests.browser.test_render_panel import choose_option
from tests.browser.test_sharing import _address, _view_state, _wait
from tests.browser.test_workbench import wait_for_map

pytestmark = pytest.mark.browser


def _scan_colours(node) -> np.ndarray:  # type: ignore[no-untyped-def]
    """The colours a point-cloud node last sent its browser: one RGB triple, or one per point."""
    return np.asarray(node.colors, np.uint8)


def test_a_viewer_link_with_another_colour_mode_is_drawn_in_it_while_the_editor_keeps_the_shared_one(
    corridor_sessions, live_server, new_browser
):
    from app.view.presence import presence_of

    server = live_server(corridor_sessions, require_token=True)
    editor, _ = server.app.state.tokens.issue(Role.editor, "corridor", name="ann")
    viewer, _ = server.app.state.tokens.issue(Role.viewer, "corridor", name="vic")
    ann = new_browser()
    ann.goto(f"{server.url}/sessions/corridor?token={editor}")
    viewer_frame(ann).get_by_text("points shown").wait_for(timeout=60_000)
    live = server.app.state.viewers.get("corridor")
    assert live.as_dict()["colour"] == "scan"

    vic = new_browser()
    vic.goto(f"{server.url}/sessions/corridor?colour=height&token={viewer}")
    viewer_frame(vic).get_by_text("following every new revision", exact=False).wait_for(timeout=120_000)
    own = server.app.state.revision_views.get("corridor", None)  # the head, in browsers' own colours
    key = _view_state(vic)["key"]
    person = _wait(lambda: presence_of(own).person(key), what="vic on the view of the head in own colours")
    _wait(lambda: own.as_dict()["colours"].get(str(person.client.client_id)) == "height", what="vic's colours")
    scene = own.browser(person.client.client_id)
    head = server.workbench.state("corridor").session.revision
    assert own.as_dict()["revision_shown"] == head and own.as_dict()["follows_head"] is True
    # vic's points are coloured by height: one colour per point, the height ramp over the drawn map
    low, high = display.height_range(own.local, own.poses)
    for k in (0, 3):
        expected = display.ramp(display.world_heights(own.local[k], own.poses[k]), low, high)
        drawn = _scan_colours(scene.nodes[k])
        assert drawn.shape == (len(own.local[k]), 3) and np.array_equal(drawn, np.asarray(expected, np.uint8))
    _wait(lambda: _view_state(vic)["colour"] == "height", what="vic's page restoring the link's colour")
    assert "colour=height" in _address(vic)
    state = _view_state(vic)
    assert state["own"] is True and state["colour"] == "height" and vic.locator("#colour").input_value() == "height"
    # ann, an editor on the shared live view, keeps its colouring: one colour per scan
    assert live.as_dict()["colour"] == "scan"
    for k in (0, 3):
        assert np.array_equal(_scan_colours(live.scans.nodes[k]), display.scan_color(k))
    assert ann.locator("#colour").input_value() == "scan" and _view_state(ann)["own"] is False

    # an edit moves the head (scan 3 lifted 30 m): vic's view follows it, still in vic's colours
    pose = server.workbench.current_poses("corridor")[3].copy()
    pose[2, 3] += 30.0
    moved = httpx.post(
        f"{server.url}/api/sessions/corridor/scans/3/pose",
        json={"pose": pose.tolist()},
        headers={"Authorization": f"Bearer {editor}"},
    )
    assert moved.status_code == 200, moved.text
    assert own.as_dict()["revision_shown"] == moved.json()["revision"]
    assert np.allclose(own.as_dict()["positions"][3], pose[:3, 3], atol=1e-9)
    assert np.allclose(scene.nodes[3].position, pose[:3, 3], atol=1e-5)
    low, high = display.height_range(own.local, own.poses)
    expected = display.ramp(display.world_heights(own.local[3], own.poses[3]), low, high)
    assert np.array_equal(_scan_colours(scene.nodes[3]), np.asarray(expected, np.uint8))
    assert live.as_dict()["colour"] == "scan"

    # a click on scan 3 in vic's own view selects it there, and vic's address carries it
    aim_at_scan(person.client, own.local[3], pose)
    canvas = viewer_frame(vic).locator("canvas[data-engine]")
    box = canvas.bounding_box()
    assert box is not None
    canvas.click(position={"x": box["width"] / 2, "y": box["height"] / 2})
    _wait(lambda: "sel=scan:3" in _address(vic), what="vic's pick in the address")
    vic.locator("#selection-title").get_by_text("Scan 3").wait_for(timeout=10_000)

    # the viewer's colour control changes only its own view
    vic.locator("#colour").select_option("component")
    _wait(lambda: own.as_dict()["colours"].get(str(person.client.client_id)) == "component", what="vic's recolour")
    _wait(lambda: "colour=component" in _address(vic), what="the address following the colour")
    assert live.as_dict()["colour"] == "scan"

    # a reviewer on the shared view who picks another colour is moved to the head in own colours
    reviewer, _ = server.app.state.tokens.issue(Role.reviewer, "corridor", name="rita")
    rita = new_browser()
    rita.goto(f"{server.url}/sessions/corridor?token={reviewer}")
    viewer_frame(rita).get_by_text("points shown").wait_for(timeout=60_000)
    rita_key = _view_state(rita)["key"]
    _wait(lambda: presence_of(live).person(rita_key), what="rita on the shared view")
    assert _view_state(rita)["own"] is False
    rita.locator("#colour").select_option("residual")
    moved_on = _wait(lambda: presence_of(own).person(rita_key), what="rita on the view in own colours")
    _wait(lambda: own.as_dict()["colours"].get(str(moved_on.client.client_id)) == "residual", what="rita's colours")
    assert live.as_dict()["colour"] == "scan" and own.as_dict()["colours"][str(person.client.client_id)] == "component"


def test_a_scan_picked_in_the_3d_view_goes_into_the_address_and_a_fresh_browser_opens_it_selected(
    corridor_sessions, live_server, new_browser
):
    from app.view.presence import presence_of
    from app.view.selection_marker import marker_of

    server = live_server(corridor_sessions)
    page = new_browser()
    page.goto(f"{server.url}/sessions/corridor")
    viewer_frame(page).get_by_text("points shown").wait_for(timeout=60_000)
    assert wait_for_map(page) >= 0.01
    viewer = server.app.state.viewers.get("corridor")
    edit = next(p for p in viewer.panels if isinstance(p, EdgesPanel))
    lift_scan(viewer, 3)
    key = _view_state(page)["key"]
    person = _wait(lambda: presence_of(viewer).person(key), what="the page's 3D view")
    client = person.client
    aim_at_scan(client, viewer.scans.local[3], viewer.scans.poses[3])

    canvas = viewer_frame(page).locator("canvas[data-engine]")
    box = canvas.bounding_box()
    assert box is not None
    canvas.click(position={"x": box["width"] / 2, "y": box["height"] / 2})
    _wait(lambda: int(edit.scan_a.value) == 3, what="the click picking scan 3")
    link = _wait(lambda: "sel=scan:3" in _address(page) and _address(page), what="the pick in the address")
    page.locator("#selection-title").get_by_text("Scan 3").wait_for(timeout=10_000)
    assert _view_state(page)["selection"] == "scan:3"
    assert len(marker_of(client).handles) == 1  # marked in the picking browser's own scene

    fresh = new_browser()
    fresh.goto(link)
    fresh.locator("#selection-title").get_by_text("Scan 3").wait_for(timeout=120_000)
    other = _view_state(fresh)["key"]
    assert other != key and _view_state(fresh)["selection"] == "scan:3"
    marker = _wait(lambda: marker_of(presence_of(viewer).person(other).client).handles, what="the fresh marker")
    journal_pose = server.workbench.current_poses("corridor")[3]
    assert np.allclose(marker[0].position, journal_pose[:3, 3], atol=1e-4)  # the box sits on scan 3


def test_an_edge_chosen_in_the_3d_views_panel_is_the_pages_selection(corridor_sessions, live_server, new_browser):
    from app.view.presence import presence_of
    from app.view.selection_marker import marker_of

    server = live_server(corridor_sessions)
    page = new_browser()
    page.goto(f"{server.url}/sessions/corridor")
    viewer_frame(page).get_by_text("points shown").wait_for(timeout=60_000)
    viewer = server.app.state.viewers.get("corridor")
    edit = next(p for p in viewer.panels if isinstance(p, EdgesPanel))
    _wait(lambda: len(edit.edge_choices) > 1, what="the Edge dropdown filled")
    label, i, j = next((text, e.i, e.j) for text, e in edit.edge_choices.items() if (e.i, e.j) == (2, 3))
    frame = viewer_frame(page)
    open_folder(frame, "Edit graph")
    choose_option(frame, "Edge", label)
    _wait(lambda: f"sel=edge:{i}-{j}" in _address(page), what="the chosen edge in the address")
    page.locator("#selection-title").get_by_text(f"Edge {i}–{j}").wait_for(timeout=10_000)
    person = presence_of(viewer).person(_view_state(page)["key"])
    assert person is not None
    marker = _wait(lambda: marker_of(person.client).handles, what="the edge marked in the page's 3D view")
    assert np.allclose(marker[0].position, server.workbench.current_poses("corridor")[i][:3, 3], atol=1e-4)
