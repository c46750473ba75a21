"""Picking scans for an edit by clicking them in the 3D view of a real browser."""

from __future__ import annotations

import numpy as np
import pytest

from app.view.panels.edges import EdgesPanel
from tests.browser.conftest import viewer_frame
from tests.browser.test_editing import open_folder, wait_until
from tests.browser.test_workbench import open_session, wait_for_map

pytestmark = pytest.mark.browser


def lift_scan(viewer, scan: int) -> None:  # type: ignore[no-untyped-def]
    """Lift ``scan`` 30 m as drawn: the corridor scans overlap, and lifted it alone is under a
    camera aimed at it (:func:`aim_at_scan`), so a click at the canvas centre picks it."""
    poses = [p.copy() for p in viewer.scans.poses]
    poses[scan][2, 3] += 30.0
    viewer.set_poses(poses)


def aim_at_scan(client, local_points: np.ndarray, pose: np.ndarray) -> None:  # type: ignore[no-untyped-def]
    """Put ``client``'s camera 25 m off the scan's centre looking at it (the look-at point is drawn at
    the canvas centre) and wait until the browser's camera is there."""
    target = np.asarray(local_points, dtype=np.float64).mean(axis=0) @ pose[:3, :3].T + pose[:3, 3]
    client.camera.position = target + np.array([-25.0, -25.0, 15.0])  # (moving it carries the look-at along)
    client.camera.look_at = target
    wait_until(lambda: np.allclose(client.camera.look_at, target, atol=1e-3), 10, "the camera did not move")


def test_click_a_scan_in_the_view_selects_it_in_the_edit_panel(
    corridor_sessions, live_server, new_browser, artifacts_dir
):
    server = live_server(corridor_sessions)
    page = new_browser()
    open_session(page, server, "corridor")
    assert wait_for_map(page) >= 0.01
    viewer = server.app.state.viewers.get("corridor")
    edit = next(p for p in viewer.panels if isinstance(p, EdgesPanel))
    lift_scan(viewer, 3)
    wait_until(lambda: len(viewer.server.get_clients()) == 1, 10, "the 3D view did not connect")
    client = next(iter(viewer.server.get_clients().values()))
    aim_at_scan(client, viewer.scans.local[3], viewer.scans.poses[3])

    frame = viewer_frame(page)
    canvas = frame.locator("canvas[data-engine]")  # the 3D view (three.js), not an overlay
    box = canvas.bounding_box()
    assert box is not None
    canvas.click(position={"x": box["width"] / 2, "y": box["height"] / 2})
    wait_until(lambda: int(edit.scan_a.value) == 3, 10, "the click did not pick scan 3")
    assert viewer.colouring.selected.get(3) is not None  # drawn highlighted

    open_folder(frame, "Edit graph")
    picked = frame.get_by_text("as A", exact=False).filter(has_text="Picked scan 3")
    picked.wait_for(timeout=10_000)
    assert frame.get_by_role("textbox", name="Scan A").input_value() == "3"  # the number field shows the pick too
    picked.scroll_into_view_if_needed()
    page.screenshot(path=str(artifacts_dir / "workbench_scan_picked.png"))
